"""Interrupt requests (SIGINT, SIGTERM) that no fallback may swallow and no second one re-enters.

The command line installs :func:`install`; a signal then sets a flag and raises
:class:`Interrupted`. Code that catches broad exceptions to keep a run going (a solver error
becomes a fallback action, a failing controller a failed run) calls :func:`raise_if_interrupted`
first, so an interrupt is never recorded as a solver failure or a failed run, even when a solver
library turned the signal into its own error or status; long loops call it too.

A second signal never interrupts the shutdown the first one started: within
:data:`REPEAT_GRACE_S` of the first raise, and at any time inside :func:`held` (the cleanup of
worker pools, the command line's exit path), a signal is only recorded. A later one, outside
:func:`held`, raises again (in case a library swallowed the first and nothing checked).
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

#: Seconds after a raise during which a repeated signal is only recorded.
REPEAT_GRACE_S = 10.0

_received: int | None = None
_raised_at: float | None = None
_holding = 0
_exit_line: Callable[[int], str] | None = None
_exiting_at_once = 0
#: Run by a signal inside :func:`exit_at_once` just before the process ends (its argument).
_before_exit: Callable[[], None] | None = None


class Interrupted(KeyboardInterrupt):
    """Raised on SIGINT or SIGTERM once :func:`install` ran; ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _handler(signum: int, frame: Any) -> None:
    global _received, _raised_at
    if _received is None:
        _received = signum  # the first signal names the interrupt (and the exit status)
    if _exiting_at_once > 0 and _exit_line is not None:
        if _before_exit is not None:
            try:
                _before_exit()
            except Exception:  # ending is what matters now
                pass
        try:
            os.write(2, (_exit_line(_received) + "\n").encode())
        except OSError:  # no stderr to tell: the status still says it
            pass
        os._exit(128 + _received)
    if _holding > 0:
        return
    if _raised_at is not None and time.monotonic() - _raised_at < REPEAT_GRACE_S:
        return
    _raised_at = time.monotonic()
    raise Interrupted(_received)


def install() -> dict[int, Any]:
    """Handle SIGINT and SIGTERM by raising :class:`Interrupted` (main thread only); returns
    the previous handlers for :func:`restore`."""
    global _received, _raised_at, _holding
    _received, _raised_at, _holding = None, None, 0
    return {sig: signal.signal(sig, _handler) for sig in (signal.SIGINT, signal.SIGTERM)}


def reinstall() -> None:
    """Put :func:`install`'s handlers back after a library replaced them (Ray installs its own
    SIGTERM handler, which prints a native stack dump and exits 1), keeping what was received."""
    if signal.getsignal(signal.SIGINT) is _handler:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, _handler)


def restore(previous: dict[int, Any]) -> None:
    """Put back the handlers :func:`install` replaced, and forget what was received (code run
    afterwards in the same process is not interrupted by a command's past signal)."""
    global _received, _raised_at, _holding
    for sig, handler in previous.items():
        signal.signal(sig, handler)
    _received, _raised_at, _holding = None, None, 0


def received() -> int | None:
    """The signal number received since :func:`install`, or None."""
    return _received


def raise_if_interrupted() -> None:
    """Raise :class:`Interrupted` again if a signal arrived (call before any fallback and in
    long loops)."""
    global _raised_at
    if _received is not None and _holding == 0:
        _raised_at = time.monotonic()
        raise Interrupted(_received)


def caught_by_library(signum: int) -> None:
    """A library caught a signal meant for the command and reported it as its own status (OSQP
    ends its solve with status ``OSQP_SIGINT``; our handler never runs): record it as received
    and raise :class:`Interrupted` as the handler would (inside :func:`held`: only recorded).
    Without :func:`install`'s handlers (a Python caller) it is the user's Ctrl-C: a
    :class:`KeyboardInterrupt`."""
    global _received
    if signal.getsignal(signal.SIGINT) is not _handler:
        raise KeyboardInterrupt(signal.Signals(signum).name)
    if _received is None:
        _received = signum
    raise_if_interrupted()


@contextmanager
def held() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM are recorded but raise nothing (a cleanup that must
    finish: stopping workers, closing the store); :func:`raise_if_interrupted` afterwards."""
    global _holding
    _holding += 1
    try:
        yield
    finally:
        _holding -= 1


def set_exit_line(line: Callable[[int], str] | None) -> None:
    """The line (from the signal's number) a signal prints inside :func:`exit_at_once` before
    the process ends; set by the command line for a command run as its own process, never for
    one called from Python (None: the block only holds signals)."""
    global _exit_line
    _exit_line = line


@contextmanager
def exit_at_once(before_exit: Callable[[], None] | None = None) -> Iterator[None]:
    """Within the block, a signal ends the process at once: ``before_exit()`` (quick, and only
    what must happen while the process lives), :func:`set_exit_line`'s line on stderr, exit
    status 128 + the signal's number, no Python clean-up. For a start-up that can neither be
    interrupted half-way nor be waited for (Ray's ``ray.init``: several seconds; a half-made
    core worker crashed the process at exit) while nothing of the command's own is being
    written; the processes it started are ended by :mod:`benchmark.reaper`. Without an exit
    line it is :func:`held`."""
    global _exiting_at_once, _before_exit
    _exiting_at_once += 1
    previous, _before_exit = _before_exit, before_exit
    try:
        with held():
            yield
    finally:
        _exiting_at_once -= 1
        _before_exit = previous


def hold_forever() -> None:
    """From now on signals are only recorded (the command is ending)."""
    global _holding
    _holding += 1
