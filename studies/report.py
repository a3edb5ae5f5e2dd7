"""What the studies' reports are made of: Markdown tables, numbers as the reports print them,
and figures."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def num(x: Any, spec: str = ",.2f") -> str:
    """``x`` formatted by ``spec``; ``n/a`` for None or NaN."""
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def row(cells: Iterable[Any]) -> str:
    """One line of a Markdown table: ``| a | b |``."""
    return "| " + " | ".join(str(c) for c in cells) + " |"


def table_lines(header: Sequence[str], rows: Iterable[Iterable[Any]]) -> list[str]:
    """The lines of a Markdown table: ``header``, the rule (``|---|---|``) and one line per row."""
    return [row(header), "|" + "---|" * len(header), *(row(r) for r in rows)]


def format_table(df: Any, columns: Sequence[tuple[str, str]] | None = None, digits: int = 2, *,
                 significant: bool = False, missing: str = "-") -> str:
    """A Markdown table of ``df``'s ``columns`` (key, header; default: every column under its
    own name) with a ``| --- |`` rule: a float to ``digits`` decimals (``significant``:
    significant digits), NaN as ``missing``."""
    columns = [(c, c) for c in df.columns] if columns is None else columns
    spec = f".{digits}{'g' if significant else 'f'}"

    def cell(v: Any) -> str:
        if isinstance(v, float | np.floating):
            return missing if math.isnan(v) else format(v, spec)
        return str(v)

    lines = [row(h for _, h in columns), row("---" for _ in columns)]
    lines += [row(cell(r[key]) for key, _ in columns) for _, r in df.iterrows()]
    return "\n".join(lines)


def save_png(fig: Any, path: Path) -> Path:
    """Lay ``fig`` out tight, write it to ``path`` (PNG, 90 dpi) and close it."""
    from analysis.plots import _plt, savefig_atomic

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    savefig_atomic(fig, path, dpi=90)
    _plt().close(fig)
    return path
