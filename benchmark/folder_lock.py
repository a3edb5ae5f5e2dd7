"""The folder lock of every command that writes a folder (``train``, ``tune``, ``reproduce``,
``pareto``, ``sensitivity``, ``stability``): the same lock as the results store's writer
(``store.lock`` via ``filelock``, the holder's pid and command in ``store.owner``), so two
commands never write one folder, and the second is refused before any work, naming the first.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from infra.errors import ConfigError

#: The lock and owner files (the results store's names, :mod:`benchmark.store`).
LOCK_NAME = "store.lock"
OWNER_NAME = "store.owner"
#: What a check for an empty folder leaves out.
LOCK_FILES = frozenset({LOCK_NAME, OWNER_NAME})
#: How long a writer refused by the lock waits for its holder to name itself (s): the holder
#: writes its owner file just after it took the lock.
OWNER_WAIT_S = 2.0


def holder(folder: Path, wait_s: float = OWNER_WAIT_S) -> str:
    """Who holds ``folder``'s lock, from its owner file, waiting up to ``wait_s`` for a holder
    that has not yet written it (``another process`` if it stays unreadable)."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            info = json.loads((folder / OWNER_NAME).read_text())
            return f"pid {info['pid']} (`{info['command']}`, started {info['started']})"
        except (OSError, ValueError, KeyError, TypeError):
            if time.monotonic() >= deadline:
                return "another process"
            time.sleep(0.02)


def write_owner(folder: Path) -> None:
    """Name this process as the lock's holder (whole or absent for a reader racing it)."""
    from infra.atomic import write_text

    write_text(folder / OWNER_NAME, json.dumps({
        "pid": os.getpid(), "command": " ".join(["cacc-bench", *sys.argv[1:]]),
        "started": time.strftime("%Y-%m-%d %H:%M:%S")}))


@contextlib.contextmanager
def folder_lock(folder: str | Path, flag: str = "--out") -> Iterator[Path]:
    """Hold ``folder``'s writer lock inside the block (the folder is made if needed).

    Raises
    ------
    ConfigError
        Another process holds the lock (the message names it), or the folder or its lock
        file cannot be made.
    """
    from filelock import FileLock, Timeout

    folder = Path(folder)
    lock_path = folder / LOCK_NAME
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if lock_path.exists() and not lock_path.is_file():
            raise ConfigError(f"{lock_path} is not a file, so {folder} cannot be locked; remove "
                              f"it or choose another {flag}")
        lock = FileLock(lock_path, timeout=0)
        lock.acquire()
    except Timeout:
        raise ConfigError(f"{folder} is being written by {holder(folder)}; wait for it to "
                          f"finish, or choose another {flag}") from None
    except OSError as exc:
        raise ConfigError(f"{flag} {folder}: cannot lock this folder ({exc.strerror or exc}); "
                          f"choose a writable place for {flag}") from None
    owner = folder / OWNER_NAME
    try:
        try:
            write_owner(folder)
        except OSError as exc:
            raise ConfigError(f"{flag} {folder}: cannot write {owner.name} ({exc.strerror}); "
                              f"choose a writable place for {flag}") from None
        yield folder
    finally:
        owner.unlink(missing_ok=True)
        lock.release()
