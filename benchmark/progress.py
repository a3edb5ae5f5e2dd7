"""Progress on a terminal with tqdm (done / total, rate, time left, within 80 columns); silent
when the output is not a terminal (logs stay clean)."""

from __future__ import annotations

import sys
from typing import Any, TextIO

#: Width of a progress line (fits an 80-column terminal).
WIDTH = 80


class Progress:
    """A one-line tqdm bar on ``stream`` if it is a terminal, counting ``label``."""

    def __init__(self, total: int, label: str = "runs", stream: TextIO | None = None) -> None:
        self.total = total
        self.done = 0
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)()) and total > 0
        self._bar: Any = None
        if self.enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=total, unit=f" {label}", file=self.stream, ncols=WIDTH,
                             mininterval=0.1, dynamic_ncols=False, leave=True,
                             bar_format="{n_fmt}/{total_fmt}{unit} {percentage:3.0f}% "
                                        "|{bar}| {elapsed}<{remaining} {rate_fmt}{postfix}")

    def advance(self, n: int = 1, note: str = "") -> None:
        """Count ``n`` finished items; ``note`` (the last item) shows after the bar, shortened
        to keep the line within :data:`WIDTH` columns."""
        self.done += n
        if self._bar is not None:
            if note:
                self._bar.set_postfix_str(note[:24], refresh=False)
            self._bar.update(n)

    def close(self) -> None:
        """End the progress line."""
        if self._bar is not None:
            self._bar.close()
