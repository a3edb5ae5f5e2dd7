"""Version and git sha recorded with every run."""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path


@functools.cache
def version() -> str:
    """Installed version of cacc-bench."""
    try:
        from importlib.metadata import version as _v

        return _v("cacc-bench")
    except Exception:
        return "0.1.0"


@functools.cache
def git_sha() -> str:
    """Short git sha of the source tree (``unknown`` outside a checkout); ``+dirty`` if modified."""
    root = Path(__file__).resolve().parent.parent
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"],
            cwd=root, capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()
    except Exception:
        return "unknown"
    return sha or "unknown"
