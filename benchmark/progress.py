"""Progress on a terminal with tqdm (done / total, rate, time left, within 80 columns); silent
when the output is not a terminal (logs stay clean).

The time left of a sweep whose items cost differently (an MPC run costs a hundred times a
linear law's, a run of N = 16 twice one of N = 8) is reckoned per group (per controller) and
per unit of work (vehicle-steps): the measured seconds per unit of the group's finished items
times its units left, summed and shared among the parallel workers. While a group with items
left has none finished, there is no estimate, and the line says so instead of guessing from the
cheap ones.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any, TextIO

#: Width of a progress line (fits an 80-column terminal).
WIDTH = 80


def _clock(seconds: float) -> str:
    """``m:ss`` or ``h:mm:ss``."""
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Progress:
    """A one-line tqdm bar on ``stream`` if it is a terminal, counting ``label``.

    Parameters
    ----------
    total : int
        Items to do.
    label : str
        What an item is (``runs``).
    stream : file, optional
        Where the bar goes (default: standard error).
    groups : sequence of str, optional
        The group of each item to do (the controller of each run): the time left is reckoned
        per group (:meth:`eta_s`); without it, tqdm's (the mean rate so far).
    weights : sequence of float, optional
        The work of each item to do, in units the cost scales with (vehicle-steps; default 1).
    parallel : int
        Workers that share the items (the time left is the summed cost over them).
    """

    def __init__(self, total: int, label: str = "runs", stream: TextIO | None = None,
                 groups: Sequence[str] | None = None, parallel: int = 1,
                 weights: Sequence[float] | None = None) -> None:
        self.total = total
        self.done = 0
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)()) and total > 0
        self.parallel = max(1, int(parallel))
        self._left: dict[str, float] | None = None  # group -> work left
        if groups is not None:
            self._left = {}
            for g, w in zip(groups, weights if weights is not None else [1.0] * len(groups),
                            strict=True):
                self._left[g] = self._left.get(g, 0.0) + float(w)
        self._cost: dict[str, tuple[float, float]] = {}  # group -> (seconds, work) measured
        self._bar: Any = None
        if self.enabled:
            from tqdm import tqdm

            left = "<{remaining} " if self._left is None else " "  # else in the postfix
            self._bar = tqdm(total=total, unit=f" {label}", file=self.stream, ncols=WIDTH,
                             mininterval=0.1, dynamic_ncols=False, leave=True,
                             bar_format="{n_fmt}/{total_fmt}{unit} {percentage:3.0f}% "
                                        "|{bar}| {elapsed}" + left + "{rate_fmt}{postfix}")
            if self._left is not None:
                self._bar.set_postfix_str(self.eta_text())

    def eta_s(self) -> float | None:
        """Seconds left by the per-group costs measured so far (None: a group with items left
        has no finished item yet, or no groups were given; 0 when nothing is left)."""
        if self._left is None:
            return None
        total = 0.0
        for group, work in self._left.items():
            if work <= 1e-9:
                continue
            seconds, done = self._cost.get(group, (0.0, 0.0))
            if done <= 0:
                return None
            total += work * seconds / done
        return total / self.parallel

    def eta_text(self) -> str:
        """``left ~m:ss``, or what is not yet timed."""
        eta = self.eta_s()
        if eta is not None:
            return f"left ~{_clock(eta)}"
        untimed = [g for g, w in (self._left or {}).items() if w > 1e-9 and g not in self._cost]
        return f"left ? ({len(untimed)} not timed yet)"

    def advance(self, n: int = 1, note: str = "", group: str | None = None,
                seconds: float | None = None, weight: float = 1.0) -> None:
        """Count ``n`` finished items; ``note`` (the last item) shows after the bar, shortened
        to keep the line within :data:`WIDTH` columns; ``group``, ``weight`` (each item's work)
        and ``seconds`` (each item's measured time) feed the time left."""
        self.done += n
        if self._left is not None and group is not None:
            self._left[group] = self._left.get(group, 0.0) - n * weight
            if seconds is not None:
                spent, done = self._cost.get(group, (0.0, 0.0))
                self._cost[group] = (spent + float(seconds) * n, done + n * weight)
        if self._bar is not None:
            if self._left is not None:
                text = self.eta_text() + (f" {note}" if note else "")
                self._bar.set_postfix_str(text[:34], refresh=False)
            elif note:
                self._bar.set_postfix_str(note[:24], refresh=False)
            self._bar.update(n)

    def close(self) -> None:
        """End the progress line."""
        if self._bar is not None:
            self._bar.close()
