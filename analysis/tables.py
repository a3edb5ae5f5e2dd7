"""Markdown tables: of a leaderboard (for READMEs and notes, from runs one has made), and the
table lines, numbers and DataFrame tables every report is made of."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

Column = tuple[str, Callable[[Any], str]]


def _ci(metric: str, digits: int = 2) -> Callable[[Any], str]:
    def fmt(r: Any) -> str:
        return (f"{r[metric + '_mean']:.{digits}f} [{r[metric + '_ci_low']:.{digits}f}, "
                f"{r[metric + '_ci_high']:.{digits}f}]")

    return fmt


def _mean(metric: str, digits: int) -> Callable[[Any], str]:
    return lambda r: f"{r[metric + '_mean']:.{digits}f}"


def sweep_peak_text(r: Any) -> str:
    """A row's sweep peak (``benchmark.sweep``): three decimals, ``collides`` when an episode of
    the sweep collided, ``n/a`` without a sweep."""
    import math

    peak = r.get("sweep_peak_gain")
    if peak is None or (isinstance(peak, float) and math.isnan(peak)):
        return "n/a"
    return "collides" if math.isinf(peak) else f"{float(peak):.3f}"


def string_stable_mark(r: Any) -> str:
    """The string-stability mark of a row: ``yes`` (the sweep peaks at most 1 + tolerance),
    ``**no**``, or ``n/a`` without a sweep."""
    stable = r.get("sweep_string_stable")
    if stable is None or (isinstance(stable, float) and stable != stable):
        return "n/a"
    return "yes" if bool(stable) else "**no**"


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
    ("time-domain string gain", _mean("string_gain", 3)),
    ("sweep peak", sweep_peak_text),
    ("string stable", string_stable_mark),
    ("ms/veh/step", _mean("compute_ms_p50", 3)),
    ("V2V bit/s", _mean("comm_bits_per_s", 0)),
)
#: The columns that read the frequency sweep (:data:`benchmark.export.SWEEP_COLUMNS`): left out
#: of a table whose leaderboard has none (one built without sweeps).
SWEEP_HEADERS: tuple[str, ...] = ("sweep peak", "string stable")


def markdown_leaderboard(lb: Any, columns: Sequence[Column] = DEFAULT_COLUMNS) -> str:
    """A Markdown table of a leaderboard DataFrame, one row per controller x setting: the
    time-domain string gain on the row's scenario, then the standard frequency sweep's peak and
    the string-stability mark (``yes`` when the peak is at most 1 + tolerance; the sweep's
    columns are left out for a leaderboard without them)."""
    if "sweep_peak_gain" not in lb:
        columns = [c for c in columns if c[0] not in SWEEP_HEADERS]
    return "\n".join(table_lines([name for name, _ in columns],
                                  ([fmt(r) for _, fmt in columns] for _, r in lb.iterrows())))


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
    import numpy as np

    columns = [(c, c) for c in df.columns] if columns is None else columns
    spec = f".{digits}{'g' if significant else 'f'}"

    def cell(v: Any) -> str:
        if isinstance(v, float | np.floating):
            return missing if math.isnan(v) else format(v, spec)
        return str(v)

    lines = [row(h for _, h in columns), row("---" for _ in columns)]
    lines += [row(cell(r[key]) for key, _ in columns) for _, r in df.iterrows()]
    return "\n".join(lines)


#: Width of the printed leaderboard (``run``, ``leaderboard``): a row fits it unless its label
#: is longer than the room left, when the label takes a line of its own (never cut).
TERMINAL_WIDTH = 100

#: The printed leaderboard's columns after rank and controller: (name, unit, width, format of a
#: leaderboard row); the other columns are in ``leaderboard.csv``.
TERMINAL_COLUMNS: tuple[tuple[str, str, int, Callable[[Any], str]], ...] = (
    ("coll.", "/eps", 6, lambda r: f"{int(r['collisions'])}/{int(r['n_episodes'])}"),
    ("reward [95% CI]", "per step", 27, _ci("reward")),
    ("energy", "kWh", 6, _mean("energy_kwh", 3)),
    ("gap RMSE", "m", 8, _mean("gap_rmse_m", 2)),
    ("time-dom.", "str. gain", 9, _mean("string_gain", 3)),
    ("compute", "ms/veh/step", 11, _mean("compute_ms_p50", 3)),
)
#: The printed column of the frequency sweep (where the leaderboard has one): the peak and
#: whether it marks the row string stable.
TERMINAL_SWEEP_COLUMN: tuple[str, str, int, Callable[[Any], str]] = (
    "sweep peak", "str.stable", 11,
    lambda r: f"{sweep_peak_text(r)} {string_stable_mark(r).strip('*')}")


def format_leaderboard(lb: Any, width: int = TERMINAL_WIDTH) -> str:
    """The leaderboard as a plain-text table within ``width`` columns, one block per scenario,
    platoon size and V2V setting, with units and a note on what the intervals mean; a
    ``failed`` column only where some run failed. The other columns (tracking reward, jerk,
    V2V bits, ...) are in ``leaderboard.csv``."""
    import textwrap

    from benchmark.sweep import SWEEP_TOL

    if len(lb) == 0:
        return "(no runs)"
    cols = list(TERMINAL_COLUMNS)
    if "sweep_peak_gain" in lb:
        cols.insert(len(cols) - 1, TERMINAL_SWEEP_COLUMN)
    if (lb["failed"] > 0).any():
        cols.insert(1, ("failed", "runs", 6, lambda r: str(int(r["failed"]))))
    rest = sum(w + 1 for _, _, w, _ in cols)
    labels = [str(c) + ("" if d in (True, None) else "*")
              for c, d in zip(lb["controller"], lb.get("deterministic", [None] * len(lb)))]
    cw = max(len("controller"), min(max(len(x) for x in labels), width - 5 - rest))
    head = f"{'rank':>4} {'controller':<{cw}}" + "".join(f" {n:>{w}}" for n, _, w, _ in cols)
    units = f"{'':>4} {'':<{cw}}" + "".join(f" {u:>{w}}" for _, u, w, _ in cols)
    lines = []
    group = ["scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s"]
    lb = lb.assign(_label=labels)
    for (scenario, n, d, loss, lag), grp in lb.groupby(group, sort=False, dropna=False):
        lines.append(f"\n{scenario}, N = {int(n)}; V2V delay {d:g} s, packet loss {loss:g}, "
                     f"actuator lag {lag:g} s")
        lines += [head.rstrip(), units.rstrip()]
        for _, r in grp.iterrows():
            cells = "".join(f" {fmt(r):>{w}}" for _, _, w, fmt in cols)
            label = r["_label"]
            if len(label) > cw:  # a long label on a line of its own, never cut
                lines.append(f"{int(r['rank']):>4} {label}")
                lines.append(f"{'':>4} {'':<{cw}}{cells}")
            else:
                lines.append(f"{int(r['rank']):>4} {label:<{cw}}{cells}")
    string_first = lb.attrs.get("rank_by") == "string-stability"
    note = ("reward: mean over steps of the sum over followers of the paper's reward (higher is "
            "better); rank: runs without collision or failure first, then "
            + ("the string-stable ones, then " if string_first else "") + "by reward. "
            "time-dom. str. gain: the acceleration ratio on the row's own scenario; sweep peak: "
            "the controller's peak |Gamma| over the standard frequency sweep at the row's N, "
            "V2V and lag, string stable (yes) when at most 1 + "
            f"{SWEEP_TOL:g} (benchmark.sweep). "
            "Deterministic controllers vary only through the scenario's perturbation, so their "
            "intervals are episode variation, not training variance; stochastic ones (sampled "
            "MARL policies) are marked *. A row over several training seeds (seeds=0+1+2) has a "
            "two-stage bootstrap interval: seeds, then episodes. More columns (tracking reward, "
            "jerk, V2V bit/s, ...) are in leaderboard.csv.")
    lines.append("")
    lines += textwrap.wrap(note, width)
    scen = set(lb["scenario"])
    if "openacc-m-v1" in scen:
        from envs.scenarios import make_scenario

        lines += textwrap.wrap(make_scenario("openacc-m-v1").note, width)
    return "\n".join(lines)
