"""Tables, figures and claim verdicts of the paper reproduction (``cacc-bench reproduce``).

Pure functions of the training curves and the stored runs; the command that makes them is
:mod:`benchmark.reproduce_cmd`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from analysis.paper import ENERGY_SAVING_CLAIM_PCT, TABLE_I_REWARD, TABLE_II
from analysis.statistics import paired_ci

#: Fraction of the last training episodes averaged for the "final" training reward.
FINAL_FRACTION = 0.1

#: A curve has converged once it is within this fraction of its rise (first to final value).
CONVERGENCE_TOLERANCE = 0.1

#: Table II's metrics: (paper key, our per-episode column of the mean, our label).
TABLE_II_METRICS: tuple[tuple[str, str, str], ...] = (
    ("ivs_m", "gap_mean_m", "IVS (m)"),
    ("speed_mps", "speed_mean_mps", "velocity (m/s)"),
    ("accel_mps2", "accel_mean_mps2", "acceleration (m/s^2)"),
    ("power_kw", "power_mean_kw", "platoon power (kW)"),
)

CurveKey = tuple[str, str, int]  # algo, scenario, training seed


def final_train_reward(curve: Any, fraction: float = FINAL_FRACTION) -> float:
    """Mean training reward (the learner's own) over the last ``fraction`` of the episodes."""
    r = curve["train_reward"].to_numpy(dtype=float)
    if r.size == 0:
        return math.nan
    k = max(1, int(math.ceil(fraction * r.size)))
    return float(r[-k:].mean())


def validation_points(curve: Any, mode: str = "sampled") -> tuple[np.ndarray, np.ndarray]:
    """Steps and validation reward (benchmark score on the validation seeds) of one curve."""
    col = f"eval_reward_{mode}"
    if col not in curve:  # a curve of an older format: no validation in this mode
        return np.array([]), np.array([])
    rows = curve[curve[col].notna()]
    return rows["steps"].to_numpy(dtype=float), rows[col].to_numpy(dtype=float)


def table_one(curves: Mapping[CurveKey, Any], algos: Sequence[str]) -> Any:
    """Table I: final training reward and final validation reward, mean and std over seeds.

    Returns a DataFrame with one row per algorithm and scenario: ``n_seeds``,
    ``train_reward_mean/std`` (the learner's own reward, comparable only between algorithms
    trained on the same reward), ``validation_reward_mean/std`` (benchmark score of the final
    weights, sampled, on the validation seeds: comparable across rows), ``paper_reward``.
    """
    import pandas as pd

    rows = []
    for algo in algos:
        for scenario in sorted({k[1] for k in curves}):
            per_seed = [c for (a, s, _), c in sorted(curves.items()) if a == algo and s == scenario]
            if not per_seed:
                continue
            train = np.array([final_train_reward(c) for c in per_seed])
            val = np.array([validation_points(c)[1][-1] if len(validation_points(c)[1]) else math.nan
                            for c in per_seed])
            rows.append({
                "algo": algo, "scenario": scenario, "n_seeds": len(per_seed),
                "train_reward_mean": float(np.mean(train)),
                "train_reward_std": float(np.std(train, ddof=1)) if len(train) > 1 else math.nan,
                "validation_reward_mean": float(np.mean(val)),
                "validation_reward_std": float(np.std(val, ddof=1)) if len(val) > 1 else math.nan,
                "paper_reward": TABLE_I_REWARD.get(algo, math.nan),
            })
    return pd.DataFrame(rows)


def table_two(runs: Any, labels: Mapping[str, str]) -> Any:
    """Table II in the paper's columns, with the paper's values beside.

    Parameters
    ----------
    runs : DataFrame
        ``runs.csv`` rows (status ok).
    labels : mapping
        Leaderboard label -> name shown (``bdc``, ``ovm``, ...); runs of other labels are left
        out. Several labels may map to one name (training seeds pooled).

    Returns
    -------
    DataFrame with one row per name and scenario: per metric ``<m>_avg`` (mean over episodes
    of the episode mean over vehicles and steps), ``<m>_std`` (standard deviation of those
    episode means across episodes, our reading of the paper's "Std"), ``<m>_within_std`` (mean
    within-episode std), ``paper_<m>_avg/std``; ``collisions``, ``n_episodes``, ``reward_mean``.
    """
    import pandas as pd

    sub = runs[runs["controller"].isin(list(labels))].copy()
    sub["name"] = sub["controller"].map(labels)
    within = {"gap_mean_m": "gap_std_m", "speed_mean_mps": "speed_std_mps",
              "accel_mean_mps2": "accel_std_mps2", "power_mean_kw": None}
    rows = []
    order = list(dict.fromkeys(labels.values()))
    for scenario, grp in sub.groupby("scenario", sort=True):
        for name in order:
            g = grp[grp["name"] == name]
            if g.empty:
                continue
            row: dict[str, Any] = {"name": name, "scenario": scenario,
                                   "n_episodes": len(g), "collisions": int(g["collision"].sum()),
                                   "reward_mean": float(g["reward"].mean())}
            paper = TABLE_II.get(name, {})
            for key, col, _ in TABLE_II_METRICS:
                x = g[col].to_numpy(dtype=float)
                row[f"{key}_avg"] = float(np.mean(x))
                row[f"{key}_std"] = float(np.std(x, ddof=1)) if len(x) > 1 else math.nan
                w = within[col]
                row[f"{key}_within_std"] = float(g[w].mean()) if w else math.nan
                row[f"paper_{key}_avg"], row[f"paper_{key}_std"] = paper.get(key, (math.nan, math.nan))
            rows.append(row)
    return pd.DataFrame(rows)


def _mean_curve(per_seed: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray,
                                                                             np.ndarray, np.ndarray]:
    """Seed curves interpolated onto the steps of the shortest one: steps, mean, min, max."""
    usable = [(s, v) for s, v in per_seed if len(s)]
    if not usable:
        empty = np.array([])
        return empty, empty, empty, empty
    grid = min((s for s, _ in usable), key=lambda s: s[-1])
    ys = np.array([np.interp(grid, s, v) for s, v in usable])
    return grid, ys.mean(axis=0), ys.min(axis=0), ys.max(axis=0)


def convergence_step(steps: np.ndarray, values: np.ndarray,
                     tolerance: float = CONVERGENCE_TOLERANCE) -> float:
    """First step after which a validation curve stays within ``tolerance`` of its rise.

    The rise is ``final - first`` with ``final`` the mean of the last three points; a curve that
    does not rise converges at its first point. The answer is the first step from which every
    later point is at least ``final - tolerance * |final - first|``.
    """
    if len(values) == 0:
        return math.nan
    final = float(np.mean(values[-3:]))
    rise = final - float(values[0])
    if rise <= 0:
        return float(steps[0])
    floor = final - tolerance * abs(rise)
    ok = values >= floor
    # the first index from which all later points are ok
    bad = np.flatnonzero(~ok)
    first = 0 if bad.size == 0 else int(bad[-1]) + 1
    return float(steps[min(first, len(steps) - 1)])


def learning_curve_figure(curves: Mapping[CurveKey, Any], algos: Sequence[str], scenario: str,
                          out_dir: Path, stem: str, title: str) -> list[Path]:
    """Validation reward (sampled, mean and min-max band over seeds) against training steps."""
    from analysis.plots import _plt, _save

    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    cmap = plt.get_cmap("tab10")
    missing: list[str] = []
    for j, algo in enumerate(algos):
        per_seed = [validation_points(c) for (a, s, _), c in sorted(curves.items())
                    if a == algo and s == scenario]
        grid, mean, lo, hi = _mean_curve(per_seed)
        if not len(grid):
            missing.append(algo)
            continue
        n = sum(1 for s, _ in per_seed if len(s))
        ax.plot(grid, mean, color=cmap(j % 10), label=f"{algo} ({n} seed{'s' if n > 1 else ''})")
        ax.fill_between(grid, lo, hi, color=cmap(j % 10), alpha=0.15)
    ax.set_xlabel("training environment steps")
    ax.set_ylabel("validation reward (sampled)")
    if missing:
        title += f"\nno sampled validation in the curves of: {', '.join(missing)}"
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, out_dir, stem)


@dataclass(frozen=True)
class Verdict:
    """One claim of the paper, our measurement and the verdict."""

    claim: str
    measured: str
    verdict: str  # "holds", "does not hold", "inconclusive" or "not testable here"
    reason: str


def energy_claim(runs: Any, labels: Mapping[str, str], scenario: str,
                 others: Sequence[str] = ("ia2c", "fprint", "commnet", "dial")) -> Verdict:
    """"BDC has the highest energy saving, up to 5.8 %": BDC's platoon power against each other
    MARL algorithm's on the same episodes (paired by episode, training seeds averaged per
    episode), with a two-stage interval over training seeds and episodes
    (:func:`analysis.statistics.paired_ci`): each controller label is one training
    seed, so a verdict covers the variation between trainings, not only between episodes."""
    claim = (f"BDC-MARL saves the most energy among the five MARL algorithms, up to "
             f"{ENERGY_SAVING_CLAIM_PCT} % (Table II, platoon power)")
    table = _seeds_by_episodes(runs, labels, scenario, "power_mean_kw")
    names = set(table.index.get_level_values("name"))
    if "bdc" not in names or not any(o in names for o in others):
        return Verdict(claim, "BDC or the other algorithms were not run", "not testable here",
                       "no runs")
    parts, lower_all, savings = [], True, []
    for o in others:
        if o not in names:
            continue
        pair = table.loc[["bdc", o]].dropna(axis=1)
        m, lo, hi = paired_ci(pair.loc["bdc"].to_numpy(), pair.loc[o].to_numpy(), "saving")
        savings.append((m, lo, hi, o))
        lower_all &= lo > 0
        parts.append(f"vs {o} {m:+.2f} % [{lo:+.2f}, {hi:+.2f}]")
    best = max(savings)
    measured = (f"{scenario}: BDC's power saving " + "; ".join(parts)
                + f" (largest {best[0]:.2f} % vs {best[3]})")
    if lower_all:
        return Verdict(claim, measured, "holds", "BDC's platoon power is below every other "
                       "algorithm's, each interval above 0")
    if all(hi < 0 for _, _, hi, _ in savings):
        return Verdict(claim, measured, "does not hold",
                       "BDC uses more power than every other algorithm")
    return Verdict(claim, measured, "does not hold" if any(hi < 0 for _, _, hi, _ in savings)
                   else "inconclusive",
                   "at least one algorithm uses less power than BDC, or an interval covers 0")


def convergence_claim(curves: Mapping[CurveKey, Any], scenario: str,
                      algos: Sequence[str] = ("wac", "dcea", "bdc")) -> Verdict:
    """"BDC converges fastest among WAC, DCEA and BDC" (Fig. 4), per training seed."""
    claim = "BDC-MARL converges fastest among WAC, DCEA and BDC (Fig. 4)"
    steps: dict[str, list[float]] = {}
    for (a, s, _), c in sorted(curves.items()):
        if a in algos and s == scenario:
            x, y = validation_points(c)
            steps.setdefault(a, []).append(convergence_step(x, y))
    if "bdc" not in steps or len(steps) < 2:
        return Verdict(claim, "curves missing", "not testable here", "WAC/DCEA/BDC not all trained")
    measured = f"{scenario}: steps to converge (per seed) " + "; ".join(
        f"{a} {', '.join(f'{v:.0f}' for v in steps[a])}" for a in algos if a in steps)
    means = {a: float(np.mean(v)) for a, v in steps.items()}
    rivals = [a for a in steps if a != "bdc"]
    if all(max(steps["bdc"]) < min(steps[a]) for a in rivals):
        return Verdict(claim, measured, "holds", "every BDC seed converges before every seed of "
                       "the others")
    if means["bdc"] > min(means[a] for a in rivals):
        return Verdict(claim, measured, "does not hold", "another scheme converges sooner on "
                       "average over seeds")
    return Verdict(claim, measured, "inconclusive", "BDC is fastest on average but the seeds "
                   "overlap")


def _seeds_by_episodes(runs: Any, labels: Mapping[str, str], scenario: str, column: str) -> Any:
    """``column`` of the runs of ``scenario`` as a table indexed by (name, controller), one row
    per controller label (a training seed), one column per episode seed."""
    sub = runs[(runs["scenario"] == scenario) & runs["controller"].isin(list(labels))].copy()
    sub["name"] = sub["controller"].map(labels)
    return sub.pivot_table(index=["name", "controller"], columns="seed", values=column,
                           aggfunc="mean")


def reward_claim(runs: Any, labels: Mapping[str, str], t2: Any, scenario: str) -> Verdict:
    """"BDC reaches the highest reward" (Tables I and II) on the evaluation episodes: BDC's
    reward against each rival's on the same episodes, with a two-stage interval over training
    seeds and episodes (:func:`analysis.statistics.paired_ci`)."""
    claim = "BDC-MARL reaches a higher test reward than IA2C, FPrint, CommNet and DIAL (Table II)"
    sub = t2[t2["scenario"] == scenario].set_index("name")
    rivals = [a for a in ("ia2c", "fprint", "commnet", "dial") if a in sub.index]
    if "bdc" not in sub.index or not rivals:
        return Verdict(claim, "runs missing", "not testable here", "no runs")
    table = _seeds_by_episodes(runs, labels, scenario, "reward")
    diffs = {}
    for a in rivals:
        pair = table.loc[["bdc", a]].dropna(axis=1)
        diffs[a] = paired_ci(pair.loc["bdc"].to_numpy(), pair.loc[a].to_numpy())
    measured = f"{scenario}: mean reward " + "; ".join(
        f"{a} {sub.loc[a, 'reward_mean']:.1f} ({int(sub.loc[a, 'collisions'])} coll.)"
        for a in ["bdc", *rivals]) + "; BDC minus " + "; ".join(
        f"{a} {m:+.1f} [{lo:+.1f}, {hi:+.1f}]" for a, (m, lo, hi) in diffs.items())
    if all(lo > 0 for _, lo, _ in diffs.values()):
        return Verdict(claim, measured, "holds", "BDC's reward is above every rival's, each "
                       "interval (training seeds and episodes) above 0")
    below = [a for a, (_, _, hi) in diffs.items() if hi < 0]
    if below:
        return Verdict(claim, measured, "does not hold", f"{', '.join(below)} scores higher")
    return Verdict(claim, measured, "inconclusive", "an interval of BDC's margin covers 0")


def qsgd_claim(t2: Any, scenario: str, ablation: str = "bdc-noqsgd") -> Verdict:
    """"QSGD keeps performance at lower bandwidth": BDC with and without QSGD."""
    claim = "QSGD on the critic gradients keeps BDC's performance at a lower bandwidth"
    sub = t2[t2["scenario"] == scenario].set_index("name")
    if "bdc" not in sub.index or ablation not in sub.index:
        return Verdict(claim, "ablation missing", "not testable here", "no BDC without QSGD")
    a, b = sub.loc["bdc"], sub.loc[ablation]
    measured = (f"{scenario}: reward with QSGD {a['reward_mean']:.1f} ({int(a['collisions'])} "
                f"coll.), without {b['reward_mean']:.1f} ({int(b['collisions'])} coll.)")
    reason = ("in our reading the quantised gradients are applied locally and reach no agent, so "
              "QSGD saves no V2V bandwidth; only its effect on performance is measured")
    return Verdict(claim, measured, "not testable here", reason)


def size_table(runs: Any, labels: Mapping[str, str], scenario: str) -> Any:
    """Test metrics per algorithm and platoon size N (paper Fig. 8).

    Per row: ``power_per_vehicle_kw_avg/std`` (mean and across-episode std of the platoon power
    over N), ``ivs_m_avg``, ``ivs_within_std_m`` (mean within-episode gap std), ``speed_mps_avg``,
    ``energy_kwh_per_100km``, ``reward_mean``, ``collisions``, ``n_episodes``.
    """
    import pandas as pd

    sub = runs[(runs["scenario"] == scenario) & runs["controller"].isin(list(labels))].copy()
    sub["name"] = sub["controller"].map(labels)
    rows = []
    for (name, n), g in sub.groupby(["name", "n_vehicles"], sort=True):
        ppv = g["power_mean_kw"].to_numpy(dtype=float) / n
        rows.append({"name": name, "n_vehicles": int(n), "n_episodes": len(g),
                     "collisions": int(g["collision"].sum()),
                     "reward_mean": float(g["reward"].mean()),
                     "power_per_vehicle_kw_avg": float(ppv.mean()),
                     "power_per_vehicle_kw_std": float(ppv.std(ddof=1)) if len(ppv) > 1 else math.nan,
                     "ivs_m_avg": float(g["gap_mean_m"].mean()),
                     "ivs_within_std_m": float(g["gap_std_m"].mean()),
                     "speed_mps_avg": float(g["speed_mean_mps"].mean()),
                     "energy_kwh_per_100km": float(g["energy_kwh_per_100km"].mean())})
    return pd.DataFrame(rows)


def size_claim(sizes: Any, algo: str = "bdc", best: int = 6) -> Verdict:
    """"A platoon of 6 is the best balance" by the paper's own criteria (Figs. 7, 8): the lowest
    variation of power consumption and the most consistent IVS among the sizes."""
    claim = (f"A platoon of {best} vehicles is the best balance: lowest variation of power and "
             "the most consistent IVS (Figs. 7, 8)")
    sub = sizes[sizes["name"] == algo].set_index("n_vehicles")
    if best not in sub.index or len(sub) < 2:
        return Verdict(claim, "sizes missing", "not testable here", f"{algo} not run at N = {best}")
    p_std, ivs = sub["power_per_vehicle_kw_std"], sub["ivs_within_std_m"]
    measured = f"{algo}: " + "; ".join(
        f"N={n}: power/veh std {p_std[n]:.3f} kW, IVS std {ivs[n]:.2f} m, "
        f"{int(sub.loc[n, 'collisions'])} coll." for n in sub.index)
    wins = [int(p_std.idxmin()) == best, int(ivs.idxmin()) == best]
    if all(wins):
        return Verdict(claim, measured, "holds", f"N = {best} has the lowest of both")
    return Verdict(claim, measured, "does not hold",
                   f"lowest power variation at N = {int(p_std.idxmin())}, most consistent IVS at "
                   f"N = {int(ivs.idxmin())}")


#: OpenACC test window -> the paper's group name in Table III.
OPENACC_GROUP_NAMES: dict[str, str] = {"openacc-s-v1": "S", "openacc-m-v1": "M",
                                       "openacc-l-v1": "L"}


def table_three(runs: Any, labels: Mapping[str, str]) -> Any:
    """Table III: per OpenACC group and controller, average and (within-run) std of velocity,
    IVS and acceleration over vehicles and steps, total energy of all vehicles (kWh), and the
    paper's values for the real ACC followers (``openacc-real``) and BDC."""
    import pandas as pd

    from analysis.paper import TABLE_III

    sub = runs[runs["scenario"].isin(list(OPENACC_GROUP_NAMES))
               & runs["controller"].isin(list(labels))].copy()
    sub["name"] = sub["controller"].map(labels)
    cols = {"speed_mps": ("speed_mean_mps", "speed_std_mps"), "ivs_m": ("gap_mean_m", "gap_std_m"),
            "accel_mps2": ("accel_mean_mps2", "accel_std_mps2")}
    rows = []
    for scenario in [sc for sc in OPENACC_GROUP_NAMES if sc in set(sub["scenario"])]:
        grp = sub[sub["scenario"] == scenario]
        group = OPENACC_GROUP_NAMES[scenario]
        for name in dict.fromkeys(labels.values()):
            g = grp[grp["name"] == name]
            if g.empty:
                continue
            paper = TABLE_III[group].get({"openacc-real": "openacc"}.get(name, name), {})
            row: dict[str, Any] = {"group": group, "scenario": scenario, "name": name,
                                   "n_episodes": len(g), "collisions": int(g["collision"].sum()),
                                   "energy_kwh": float(g["energy_kwh"].mean()),
                                   "paper_energy_kwh": paper.get("energy_kwh", (math.nan,))[0]}
            for key, (avg, std) in cols.items():
                row[f"{key}_avg"] = float(g[avg].mean())
                row[f"{key}_std"] = float(g[std].mean())
                p_avg, p_std = paper.get(key, (math.nan, math.nan))
                row[f"paper_{key}_avg"], row[f"paper_{key}_std"] = p_avg, p_std
            rows.append(row)
    return pd.DataFrame(rows)


def openacc_claim(t3: Any) -> Verdict:
    """"BDC's IVS varies less than real ACC" on every OpenACC group (Table III)."""
    claim = "BDC-MARL's IVS varies less than the real ACC followers' on the OpenACC windows (Table III)"
    parts, wins = [], []
    for group, g in t3.groupby("group", sort=False):
        g = g.set_index("name")
        if "bdc" not in g.index or "openacc-real" not in g.index:
            continue
        b, r = g.loc["bdc", "ivs_m_std"], g.loc["openacc-real", "ivs_m_std"]
        parts.append(f"{group}: BDC {b:.2f} m ({int(g.loc['bdc', 'collisions'])} coll.) vs real "
                     f"{r:.2f} m")
        wins.append(b < r and g.loc["bdc", "collisions"] == 0)
    if not parts:
        return Verdict(claim, "runs missing", "not testable here", "BDC or openacc-real not run")
    measured = "; ".join(parts)
    if all(wins):
        return Verdict(claim, measured, "holds", "smaller IVS std in every group, no collision")
    return Verdict(claim, measured, "does not hold",
                   "BDC's IVS std is not smaller (or it collides) in at least one group")


def not_testable(claim: str, reason: str) -> Verdict:
    """A claim this reproduction cannot test yet, with the reason."""
    return Verdict(claim, "-", "not testable here", reason)


def format_table(df: Any, columns: Sequence[tuple[str, str]], digits: int = 2) -> str:
    """A Markdown table of ``df``'s ``columns`` (key, header); NaN shows as a dash."""
    head = "| " + " | ".join(h for _, h in columns) + " |"
    sep = "| " + " | ".join("---" for _ in columns) + " |"
    lines = [head, sep]
    for _, r in df.iterrows():
        cells = []
        for key, _ in columns:
            v = r[key]
            if isinstance(v, float | np.floating):
                cells.append("-" if not math.isfinite(v) else f"{v:.{digits}f}")
            else:
                cells.append(str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
