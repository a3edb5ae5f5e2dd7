"""Output folders checked before any work: a folder that cannot be made or written is a clear
error (exit 2), not a traceback after the first runs."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from infra.errors import ConfigError

#: Longest folder name and path the filesystem takes (POSIX values where unknown).
_NAME_MAX = 255
_PATH_MAX = 4096


def writable_dir(path: str | Path, flag: str = "--out", create: bool = False) -> Path:
    """Check that ``path`` is, or can be made as, a folder files can be written in; make it
    when ``create`` (otherwise nothing is made, so a refusal later leaves no trace). An empty
    ``path`` or one with a name the filesystem cannot hold is refused."""
    if not str(path).strip():  # Path("") is the current folder: never what was meant
        raise ConfigError(f"{flag} is empty; name a folder")
    out = Path(path)
    too_long = [part for part in out.parts if len(os.fsencode(part)) > _NAME_MAX]
    if too_long or len(os.fsencode(str(out.absolute()))) >= _PATH_MAX:
        raise ConfigError(f"{flag} {str(out)[:60]}...: a folder name longer than {_NAME_MAX} "
                          f"bytes or a path longer than {_PATH_MAX} cannot be made; choose a "
                          f"shorter {flag}")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{flag} {out} exists and is not a folder; choose another {flag}")
    probe = out.absolute()
    while not probe.exists():
        if probe.is_symlink():  # a link to nothing: mkdir would say "File exists"
            given = next((p for p in (out, *out.parents) if p.absolute() == probe), probe)
            raise ConfigError(f"{flag} {out}: {given} is a link to {os.readlink(probe)}, which "
                              f"does not exist; make that folder, remove the link, or choose "
                              f"another {flag}")
        probe = probe.parent
    if not probe.is_dir():
        given = next((p for p in (out, *out.parents) if p.absolute() == probe), probe)
        raise ConfigError(f"{flag} {out}: {given} is a file, so the folder cannot be made; "
                          f"choose another {flag}")
    try:  # the real test (root passes os.access everywhere): a private probe folder in the
        # nearest existing ancestor, so two commands checking the same --out never race
        os.rmdir(tempfile.mkdtemp(prefix=".cacc-bench-probe-", dir=probe))
        if create:
            out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        what = "write in" if probe == out.absolute() else "make"
        raise ConfigError(f"{flag} {out}: cannot {what} this folder ({exc.strerror}); choose "
                          f"a writable place for {flag}") from None
    if out.exists() and not os.access(out, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag} {out} is not writable; choose another {flag}")
    return out
