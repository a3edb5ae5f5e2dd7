"""Energy against spacing: the trade-off each controller family reaches (``cacc-bench pareto``).

Pure functions of ``runs.csv`` rows: one point per controller setting with bootstrap intervals
over episodes, the non-dominated set, and the figure.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmark.statistics import bootstrap_ci

#: The two objectives, both minimised: energy per vehicle and spacing error.
OBJECTIVES: tuple[str, str] = ("energy_kwh_per_100km", "gap_rmse_m")

#: The energy objective by the name ``cacc-bench pareto --energy`` takes: the total energy per
#: vehicle, or only its part above steady cruise at the leader's mean speed
#: (``docs/controllable-energy.md``).
ENERGY_METRICS: dict[str, str] = {
    "total": "energy_kwh_per_100km",
    "controllable": "controllable_energy_kwh_per_100km",
}

#: Axis label of each energy objective.
ENERGY_LABELS: dict[str, str] = {
    "total": "energy per vehicle (kWh/100 km)",
    "controllable": "controllable energy per vehicle (kWh/100 km above steady cruise)",
}


def _energy_metric(energy: str) -> str:
    """The runs.csv column of the energy objective ``energy``; UnknownNameError otherwise."""
    if energy not in ENERGY_METRICS:
        from infra.errors import UnknownNameError

        raise UnknownNameError("energy objective", energy, ENERGY_METRICS)
    return ENERGY_METRICS[energy]


def pareto_columns(energy: str = "total") -> tuple[str, ...]:
    """The columns of :func:`pareto_frame` for the energy objective ``energy`` (a key of
    :data:`ENERGY_METRICS`)."""
    e = _energy_metric(energy)
    return (
        "scenario", "family", "controller", "knob", "knob_value",
        f"{e}_mean", f"{e}_ci_low", f"{e}_ci_high",
        "gap_rmse_m_mean", "gap_rmse_m_ci_low", "gap_rmse_m_ci_high",
        "speed_rmse_mps_mean", "string_gain_mean", "collisions", "n_episodes", "non_dominated",
    )


PARETO_COLUMNS: tuple[str, ...] = pareto_columns("total")


def non_dominated(points: np.ndarray, eligible: np.ndarray | None = None) -> np.ndarray:
    """Which rows of ``points`` (k, 2), both columns minimised, no other eligible row dominates.

    A row dominates another when it is no worse in both columns and better in one. Rows not
    ``eligible`` (e.g. settings that collided) are never marked and dominate nothing. NaN rows
    are not marked.
    """
    p = np.asarray(points, dtype=np.float64)
    ok = np.all(np.isfinite(p), axis=1)
    if eligible is not None:
        ok &= np.asarray(eligible, dtype=bool)
    out = np.zeros(len(p), dtype=bool)
    for i in np.flatnonzero(ok):
        others = p[ok]
        dominated = np.any(np.all(others <= p[i], axis=1) & np.any(others < p[i], axis=1))
        out[i] = not dominated
    return out


def pareto_frame(runs: Any, settings: Sequence[dict[str, Any]], energy: str = "total") -> Any:
    """One row per scenario and setting (see :func:`pareto_columns`).

    Parameters
    ----------
    runs : DataFrame
        ``runs.csv`` rows with status ok.
    settings : sequence of dict
        ``label`` (the leaderboard label), ``family``, ``controller``, ``knob``, ``knob_value``.
    energy : {"total", "controllable"}
        The energy objective (:data:`ENERGY_METRICS`). Controllable energy is unknown for runs
        stored before it was measured (empty in runs.csv): a setting with such a run gets no
        energy value (NaN) and stays off the front rather than a mean over part of its episodes.
    """
    import pandas as pd

    energy_col = _energy_metric(energy)
    objectives = (energy_col, OBJECTIVES[1])
    columns = pareto_columns(energy)
    if energy_col not in runs:  # runs.csv of a store from before the column existed
        runs = runs.assign(**{energy_col: np.nan})
    rows = []
    for scenario in sorted(runs["scenario"].unique()):
        sub = runs[runs["scenario"] == scenario]
        for s in settings:
            g = sub[sub["controller"] == s["label"]]
            if g.empty:
                continue
            row = {"scenario": scenario, "family": s["family"], "controller": s["label"],
                   "knob": s["knob"], "knob_value": s["knob_value"]}
            for metric in objectives:
                vals = g[metric].to_numpy(dtype=float)
                if energy != "total" and metric == energy_col and not np.isfinite(vals).all():
                    vals = np.full(len(vals), np.nan)  # unknown for some episodes: no point
                m, lo, hi = bootstrap_ci(vals)
                row.update({f"{metric}_mean": m, f"{metric}_ci_low": lo, f"{metric}_ci_high": hi})
            row["speed_rmse_mps_mean"] = float(g["speed_rmse_mps"].mean())
            row["string_gain_mean"] = float(g["string_gain"].mean())
            row["collisions"] = int(g["collision"].sum())
            row["n_episodes"] = len(g)
            rows.append(row)
    df = pd.DataFrame(rows, columns=[c for c in columns if c != "non_dominated"])
    df["non_dominated"] = False
    for _, idx in df.groupby("scenario").groups.items():
        part = df.loc[idx]
        pts = part[[f"{m}_mean" for m in objectives]].to_numpy()
        df.loc[idx, "non_dominated"] = non_dominated(pts, (part["collisions"] == 0).to_numpy())
    return df[list(columns)]


def plot_pareto(df: Any, scenario: str, out_dir: Path, stem: str,
                energy: str = "total") -> list[Path]:
    """Energy per vehicle (the objective ``energy`` of :data:`ENERGY_METRICS`) against gap RMSE,
    one curve per family (its knob in order), 95 % intervals as error bars, non-dominated points
    ringed, collided settings hollow."""
    import pandas as pd

    from analysis.plots import _plt, _save

    e = _energy_metric(energy)
    plt = _plt()
    sub = df[df["scenario"] == scenario]
    fig, ax = plt.subplots(figsize=(8, 5.5))
    families = list(dict.fromkeys(sub["family"]))
    cmap = plt.get_cmap("tab20")
    for j, fam in enumerate(families):
        g = sub[sub["family"] == fam].sort_values("knob_value",
                                                   key=lambda v: pd.to_numeric(v, errors="coerce"))
        color = cmap(j % 20)
        x, y = g["gap_rmse_m_mean"].to_numpy(), g[f"{e}_mean"].to_numpy()
        xerr = np.abs(np.vstack([x - g["gap_rmse_m_ci_low"], g["gap_rmse_m_ci_high"] - x]))
        yerr = np.abs(np.vstack([y - g[f"{e}_ci_low"], g[f"{e}_ci_high"] - y]))
        ax.errorbar(x, y, xerr=xerr, yerr=yerr, color=color, marker="o", ms=4, lw=1,
                    capsize=2, label=fam, linestyle="-" if len(g) > 1 else "none")
        collided = (g["collisions"] > 0).to_numpy()
        if collided.any():
            ax.scatter(x[collided], y[collided], s=60, facecolors="white", edgecolors=color,
                       zorder=3)
        if len(g) > 1:
            for xi, yi, k in zip(x, y, g["knob_value"], strict=True):
                ax.annotate(f"{k}", (xi, yi), fontsize=6, xytext=(3, 3),
                            textcoords="offset points", color=color)
    nd = sub[sub["non_dominated"]]
    ax.scatter(nd["gap_rmse_m_mean"], nd[f"{e}_mean"], s=140,
               facecolors="none", edgecolors="black", linewidths=1.2, zorder=4,
               label="non-dominated (no collision)")
    ax.set_xlabel("gap RMSE (m)")
    ax.set_ylabel(ENERGY_LABELS[energy])
    what = "energy" if energy == "total" else "controllable energy"
    ax.set_title(f"{what} against spacing on {scenario} (hollow: collided)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, out_dir, stem)
