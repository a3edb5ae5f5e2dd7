"""Markdown tables of a leaderboard (for READMEs and notes, from runs one has made)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

Column = tuple[str, Callable[[Any], str]]


def _ci(metric: str, digits: int = 2) -> Callable[[Any], str]:
    def fmt(r: Any) -> str:
        return (f"{r[metric + '_mean']:.{digits}f} [{r[metric + '_ci_low']:.{digits}f}, "
                f"{r[metric + '_ci_high']:.{digits}f}]")

    return fmt


def _mean(metric: str, digits: int) -> Callable[[Any], str]:
    return lambda r: f"{r[metric + '_mean']:.{digits}f}"


DEFAULT_COLUMNS: tuple[Column, ...] = (
    ("scenario", lambda r: str(r["scenario"])),
    ("rank", lambda r: str(int(r["rank"]))),
    ("controller", lambda r: f"`{r['controller']}`"),
    ("collisions", lambda r: f"{int(r['collisions'])}/{int(r['n_episodes'])}"),
    ("reward [95% CI]", _ci("reward")),
    ("tracking", _mean("tracking_reward", 2)),
    ("energy kWh", _mean("energy_kwh", 3)),
    ("gap RMSE m", _mean("gap_rmse_m", 2)),
    ("jerk RMS m/s^3", _mean("jerk_rms_mps3", 2)),
    ("string gain", _mean("string_gain", 3)),
    ("ms/veh/step", _mean("compute_ms_p50", 3)),
    ("V2V bit/s", _mean("comm_bits_per_s", 0)),
)


def markdown_leaderboard(lb: Any, columns: Sequence[Column] = DEFAULT_COLUMNS) -> str:
    """A Markdown table of a leaderboard DataFrame, one row per controller x setting."""
    head = "| " + " | ".join(name for name, _ in columns) + " |"
    rule = "|" + "---|" * len(columns)
    rows = ["| " + " | ".join(fmt(r) for _, fmt in columns) + " |" for _, r in lb.iterrows()]
    return "\n".join([head, rule, *rows])
