"""Atomic file writes: a reader sees the old file or the new one, never half of one.

Every write goes to a temporary file in the target's folder (same filesystem), is flushed and
``fsync``-ed, then renamed over the target with :func:`os.replace` (atomic on POSIX), and the
folder is synced so the rename survives a crash. A failure at any point (a full disk, a
permission error, an interrupt) removes the temporary file and leaves the target as it was.

:class:`StagedFiles` writes several files this way and renames them together at the end, with
SIGINT and SIGTERM held back during the renames, so an interrupt arriving then takes effect after
the last rename: a run's files are all old or all new.
"""

from __future__ import annotations

import contextlib
import os
import signal
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _umask_mode() -> int:
    """The permission bits a plain ``open(path, "w")`` would give a new file."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def _sync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def temporary_beside(path: str | Path) -> Path:
    """A new, empty temporary file in ``path``'s folder (hidden, named after ``path``)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    return Path(tmp)


def _synced(tmp: Path) -> None:
    """Flush ``tmp`` to the disk and give it the mode a new file gets."""
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.chmod(tmp, _umask_mode())


@contextlib.contextmanager
def _replacing(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path``; on a clean exit it is synced and renamed over
    ``path``, on any exception removed (the target left as it was)."""
    tmp = temporary_beside(path)
    try:
        yield tmp
        _synced(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _sync_folder(path.parent)


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns ``path``."""
    return write_with(path, lambda tmp: tmp.write_bytes(data))


def write_text(path: str | Path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically; returns ``path``."""
    return write_with(path, lambda tmp: tmp.write_text(text, encoding=encoding))


def write_with(path: str | Path, writer: Callable[[Path], object]) -> Path:
    """Atomically (re)place ``path`` with what ``writer(tmp)`` writes to a temporary path (for
    libraries that take a file name, e.g. ``torch.save`` or ``DataFrame.to_csv``)."""
    path = Path(path)
    with _replacing(path) as tmp:
        writer(tmp)
    return path


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back inside the block (main thread, POSIX); a signal that
    arrives meanwhile is delivered when the block ends."""
    block = getattr(signal, "pthread_sigmask", None)
    if block is None:
        yield
        return
    previous = block(signal.SIG_BLOCK, _SIGNALS)
    try:
        yield
    finally:
        block(signal.SIG_SETMASK, previous)


class StagedFiles:
    """Files written to temporaries now and renamed over their targets together by
    :meth:`commit` (or removed by :meth:`discard`); a context manager that discards what was
    not committed.

    Examples
    --------
    >>> with StagedFiles() as staged:                                    # doctest: +SKIP
    ...     staged.write_with(out / "a.pt", lambda p: torch.save(data, p))
    ...     staged.write_text(out / "a.log", text)
    ...     staged.commit()
    """

    def __init__(self) -> None:
        self._pending: list[tuple[Path, Path]] = []

    def write_with(self, path: str | Path, writer: Callable[[Path], object]) -> None:
        """Stage ``path`` with what ``writer(tmp)`` writes (synced now, renamed at commit)."""
        path = Path(path)
        tmp = temporary_beside(path)
        self._pending.append((tmp, path))
        writer(tmp)
        _synced(tmp)

    def write_text(self, path: str | Path, text: str) -> None:
        """Stage ``path`` with ``text`` (UTF-8)."""
        self.write_with(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))

    def adopt(self, tmp: str | Path, path: str | Path) -> None:
        """Stage an already written temporary file ``tmp`` (in ``path``'s folder) for ``path``."""
        tmp = Path(tmp)
        _synced(tmp)
        self._pending.append((tmp, Path(path)))

    def commit(self) -> None:
        """Rename every staged file over its target, with SIGINT and SIGTERM held back."""
        with signals_held():
            for tmp, path in self._pending:
                os.replace(tmp, path)
            folders = {path.parent for _, path in self._pending}
            self._pending = []
        for folder in folders:
            _sync_folder(folder)

    def discard(self) -> None:
        """Remove the staged temporaries; the targets stay as they were."""
        for tmp, _ in self._pending:
            tmp.unlink(missing_ok=True)
        self._pending = []

    def __enter__(self) -> StagedFiles:
        return self

    def __exit__(self, *exc: object) -> None:
        self.discard()
