"""Commands that work inside their output folder (``reproduce``, ``sensitivity``).

Such a command holds the folder's lock (:func:`benchmark.folder_lock.folder_lock`) and runs
with the folder as its working directory, so every path it records (checkpoint folders in run
keys and labels, a training job's ``out``, the report's links) is relative to the folder: the same folder
spelled differently (absolute, relative, through a link) or moved keeps every run's identity,
and a resumed command reruns nothing. Workers (process pool, a local Ray instance) start inside
the command and inherit the working directory.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

from benchmark.folder_lock import folder_lock

_STARTED_IN: list[str] = []  # the working directories the open working_in blocks left


def shown_path(path: str | Path) -> str:
    """``path`` as the user who typed the command can open it: relative to the directory they
    ran it from (not to an output folder a command works inside, :func:`working_in`) when it
    lies inside it, else absolute."""
    user_dir = Path(_STARTED_IN[0] if _STARTED_IN else os.getcwd())
    full = Path(os.path.abspath(path))
    return str(full.relative_to(user_dir)) if full.is_relative_to(user_dir) else str(full)


@contextlib.contextmanager
def working_in(folder: str | Path) -> Iterator[Path]:
    """Lock ``folder`` and make it the working directory inside the block (restored after);
    yields the folder's resolved path."""
    with folder_lock(folder):
        here = Path(folder).resolve()
        previous = os.getcwd()
        os.chdir(here)
        _STARTED_IN.append(previous)
        try:
            yield here
        finally:
            _STARTED_IN.pop()
            os.chdir(previous)


def command_text(prog: str, argv: Sequence[str], flag: str = "--out") -> str:
    """``prog`` and its arguments as a report prints them: the value of ``flag`` becomes
    ``OUT`` (the report's own folder), so a report never prints where its folder lay."""
    args: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            args.append("OUT")
            skip = False
        elif arg == flag:
            args.append(arg)
            skip = True
        elif arg.startswith(flag + "="):
            args.append(f"{flag}=OUT")
        else:
            args.append(arg)
    return " ".join([prog, *args])
