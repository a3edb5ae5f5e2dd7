"""Interrupt requests (SIGINT, SIGTERM) that no fallback may swallow.

The command line installs :func:`install`; a signal then sets a flag and raises
:class:`Interrupted`. Code that catches broad exceptions to keep a run going (a solver error
becomes a fallback action, a failing controller a failed run) calls :func:`raise_if_interrupted`
first, so an interrupt is never recorded as a solver failure or a failed run, even when a solver
library turned the signal into its own error or status.
"""

from __future__ import annotations

import signal
from typing import Any

_received: int | None = None


class Interrupted(KeyboardInterrupt):
    """Raised on SIGINT or SIGTERM once :func:`install` ran; ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _handler(signum: int, frame: Any) -> None:
    global _received
    _received = signum
    raise Interrupted(signum)


def install() -> dict[int, Any]:
    """Handle SIGINT and SIGTERM by raising :class:`Interrupted` (main thread only); returns
    the previous handlers for :func:`restore`."""
    global _received
    _received = None
    previous: dict[int, Any] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, _handler)
    return previous


def restore(previous: dict[int, Any]) -> None:
    """Put back the handlers :func:`install` replaced."""
    for sig, handler in previous.items():
        signal.signal(sig, handler)


def received() -> int | None:
    """The signal number received since :func:`install`, or None."""
    return _received


def raise_if_interrupted() -> None:
    """Raise :class:`Interrupted` again if a signal arrived (call before any fallback)."""
    if _received is not None:
        raise Interrupted(_received)
