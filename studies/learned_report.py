"""The answer to "MARL or MPC?": paired comparisons of learned and model-based controllers.

:func:`episodes_frame` reduces a results folder's ``runs.csv`` to one row per policy, training
seed, V2V setting and episode; :func:`comparisons_frame` computes every comparison of
:data:`COMPARISONS` (and, per controller, degraded against ideal V2V) as a paired difference of
rewards over training seeds and episodes (:func:`benchmark.statistics.paired_ci`); and
:func:`write_report` writes ``report.md`` from them. The verdict of a comparison puts collisions
first, as the leaderboard ranks: a side with fewer colliding episodes is better whatever its
reward; otherwise the reward difference decides when its 95 % interval excludes zero, and the
comparison is "inconclusive" when it does not.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from analysis.tables import num, table_lines
from benchmark.statistics import paired_ci

#: Report name -> (registered controller, options other than the training seed).
POLICIES: dict[str, tuple[str, dict[str, str]]] = {
    "cacc": ("cacc", {}),
    "mpc": ("mpc", {}),
    "bdc": ("bdc", {}),
    "ippo (OVM-gain)": ("ippo", {"variant": "ovm-gain"}),
    "ippo": ("ippo", {}),
    "mappo": ("mappo", {}),
    "ippo (residual on cacc)": ("ippo", {"variant": "residual-cacc"}),
    "ippo (residual, time-aware critic)": ("ippo", {"variant": "residual-timed"}),
    "ippo-bdc": ("ippo-bdc", {}),
    "distill": ("distill", {}),
}

#: Ideal V2V and the degraded setting of the communication question: (delay s, loss).
IDEAL: tuple[float, float] = (0.0, 0.0)
DEGRADED: tuple[float, float] = (0.2, 0.3)


@dataclass(frozen=True)
class Comparison:
    """``ours`` against ``other`` (names of :data:`POLICIES`) and what the difference measures."""

    question: str
    ours: str
    other: str
    meaning: str


#: The decomposition of the gap between the paper's learned control and ``mpc``:
#: ``ippo (OVM-gain) - mpc = [OVM-gain - accel] + [ippo - distill] + [distill - mpc]``.
COMPARISONS: tuple[Comparison, ...] = (
    Comparison("the gap", "ippo (OVM-gain)", "mpc",
               "a learned policy on the published action set against mpc: the whole gap"),
    Comparison("action set and information", "ippo (OVM-gain)", "ippo",
               "the same learner with the published OVM-gain actions instead of acceleration "
               "commands with V2V"),
    Comparison("action set and information", "bdc", "ippo (OVM-gain)",
               "the paper's method (per-agent networks, consensus) against one shared policy, "
               "both on OVM-gain actions"),
    Comparison("action set and information", "bdc", "ippo-bdc",
               "the paper's consensus scheme on OVM-gain actions against the same scheme (an "
               "actor and critic per agent, binary differential consensus on the critics, QSGD) "
               "on acceleration actions with V2V"),
    Comparison("learning", "ippo-bdc", "ippo",
               "networks per agent agreeing by BDC consensus against one policy shared by all"),
    Comparison("learning", "ippo", "distill",
               "reinforcement learning against imitation of mpc, same network and information"),
    Comparison("learning", "distill", "mpc", "the imitation against the solver it copies"),
    Comparison("learning", "ippo", "mpc", "reinforcement learning against mpc"),
    Comparison("learning", "mappo", "ippo", "a centralised critic against a local one"),
    Comparison("learning", "ippo (residual on cacc)", "cacc",
               "a learned residual on top of cacc against cacc alone"),
    Comparison("learning", "ippo (residual, time-aware critic)", "cacc",
               "the residual on cacc learned with a critic that knows the episode's time, "
               "against cacc alone"),
    Comparison("learning", "ippo (residual, time-aware critic)", "ippo (residual on cacc)",
               "what the time-aware critic (and the exact prior) changes in the residual"),
    Comparison("learning", "ippo (residual, time-aware critic)", "mpc",
               "the best learned residual against mpc"),
    Comparison("learning", "cacc", "mpc", "the linear controller against mpc"),
)

#: Verdict words.
HIGHER, LOWER, INCONCLUSIVE = "higher", "lower", "inconclusive"


def policy_name(controller: str, options: dict[str, Any]) -> str | None:
    """The :data:`POLICIES` name of a run's controller and options (its seed dropped), or None."""
    opts = {k: str(v) for k, v in options.items() if k != "seed"}
    for name, (ctrl, want) in POLICIES.items():
        if ctrl == controller and opts == want:
            return name
    return None


def episodes_frame(runs: Any) -> Any:
    """One row per policy, training seed, V2V setting, scenario and episode of ``runs.csv``
    (finished runs of :data:`POLICIES` only): the columns this report reads."""
    import pandas as pd

    rows = []
    for _, r in runs.iterrows():
        if r["status"] != "ok":
            continue
        opts = json.loads(r["options"] or "{}")
        name = policy_name(str(r["controller_name"]), opts)
        if name is None:
            continue
        rows.append({
            "policy": name, "train_seed": int(opts.get("seed", 0)), "scenario": r["scenario"],
            "n_vehicles": int(r["n_vehicles"]), "comm_delay_s": float(r["comm_delay_s"]),
            "packet_loss": float(r["packet_loss"]), "seed": int(r["seed"]),
            "reward": float(r["reward"]), "collision": bool(r["collision"] in (True, "True")),
            "energy_kwh_per_100km": float(r["energy_kwh_per_100km"]),
            "gap_rmse_m": float(r["gap_rmse_m"]), "compute_ms_p50": float(r["compute_ms_p50"]),
        })
    cols = ["policy", "train_seed", "scenario", "n_vehicles", "comm_delay_s", "packet_loss",
            "seed", "reward", "collision", "energy_kwh_per_100km", "gap_rmse_m",
            "compute_ms_p50"]
    df = pd.DataFrame(rows, columns=cols)
    return df.sort_values(cols[:7], kind="mergesort").reset_index(drop=True)


def side(sel: Any) -> Any:
    """One side of a comparison: the rewards of the episode rows ``sel`` as a table (training
    seeds x episodes) and their colliding episodes; None when ``sel`` is empty."""
    if sel.empty:
        return None
    return sel.pivot(index="train_seed", columns="seed", values="reward"), int(sel["collision"].sum())


def _side(ep: Any, policy: str, scenario: str, setting: tuple[float, float]) -> Any:
    return side(ep[(ep["policy"] == policy) & (ep["scenario"] == scenario)
                   & np.isclose(ep["comm_delay_s"], setting[0])
                   & np.isclose(ep["packet_loss"], setting[1])])


def compare(ours: Any, other: Any, same_policy: bool = False) -> dict[str, Any]:
    """The paired comparison of two sides of :func:`side` (same episodes), collisions first.

    Two policies: the training seeds of each side are drawn apart, the episodes together. The
    same policy in two settings (``same_policy``): the differences per training seed and
    episode are resampled (seeds, then episodes), which keeps both pairings.
    """
    (a, ca), (b, cb) = ours, other
    seeds = sorted(set(a.columns) & set(b.columns))
    if same_policy:
        train = sorted(set(a.index) & set(b.index))
        diff = a.loc[train, seeds].to_numpy() - b.loc[train, seeds].to_numpy()
        mean, lo, hi = paired_ci(diff, np.zeros((1, len(seeds))))
    else:
        mean, lo, hi = paired_ci(a[seeds].to_numpy(), b[seeds].to_numpy())
    if ca != cb:
        verdict = HIGHER if ca < cb else LOWER
        basis = "collisions"
    else:
        verdict = HIGHER if lo > 0 else LOWER if hi < 0 else INCONCLUSIVE
        basis = "reward"
    return {"episodes": len(seeds), "train_seeds_ours": len(a), "train_seeds_other": len(b),
            "collisions_ours": ca, "collisions_other": cb, "reward_ours": float(a[seeds].mean().mean()),
            "reward_other": float(b[seeds].mean().mean()), "difference": mean,
            "ci_low": lo, "ci_high": hi, "verdict": verdict, "basis": basis}


def comparisons_frame(ep: Any) -> Any:
    """Every comparison of :data:`COMPARISONS` under ideal V2V, then each policy under
    :data:`DEGRADED` against itself under :data:`IDEAL` ("communication"), per scenario; pairs
    with a side that did not run are left out."""
    import pandas as pd

    rows = []
    for scenario in sorted(ep["scenario"].unique()):
        for c in COMPARISONS:
            ours, other = _side(ep, c.ours, scenario, IDEAL), _side(ep, c.other, scenario, IDEAL)
            if ours is not None and other is not None:
                rows.append({"question": c.question, "scenario": scenario, "ours": c.ours,
                             "other": c.other, "setting": "ideal V2V", **compare(ours, other),
                             "meaning": c.meaning})
        for policy in POLICIES:
            bad, good = _side(ep, policy, scenario, DEGRADED), _side(ep, policy, scenario, IDEAL)
            if bad is not None and good is not None:
                rows.append({"question": "communication", "scenario": scenario, "ours": policy,
                             "other": policy, "setting": "0.2 s delay, 30 % loss vs ideal",
                             **compare(bad, good, same_policy=True),
                             "meaning": "degraded V2V against ideal V2V, same policy"})
    return pd.DataFrame(rows)


def policy_sweeps(ep: Any, cache: Any = None, executor: str = "serial",
                  workers: int = 1) -> Any:
    """Per policy, scenario and V2V setting of ``ep`` (:func:`episodes_frame`): the standard
    frequency sweep's peak ``|Gamma|`` (:func:`benchmark.sweep.sweep_peak` at the setting's N
    and channel; a learned policy with the checkpoint it ran on the scenario), the largest over
    its training seeds, and whether it is string stable (every seed's peak at most 1 +
    tolerance). ``cache``: a :class:`benchmark.sweep.SweepCache` read first and added to."""
    import pandas as pd

    from benchmark.sweep import SWEEP_TOL, row_sweeps
    from controllers.registry import controller_label

    configs = ep[["policy", "train_seed", "scenario", "n_vehicles", "comm_delay_s",
                  "packet_loss"]].drop_duplicates()
    records, of = [], []
    for _, r in configs.iterrows():
        ctrl, opts = POLICIES[r["policy"]]
        options = {**opts, "seed": str(int(r["train_seed"]))} if r["train_seed"] else dict(opts)
        records.append({"controller": controller_label(ctrl, options), "name": ctrl,
                        "options": json.dumps(options, sort_keys=True),
                        "scenario": r["scenario"], "n_vehicles": int(r["n_vehicles"]),
                        "comm_delay_s": float(r["comm_delay_s"]),
                        "packet_loss": float(r["packet_loss"]), "lag_s": 0.0, "status": "ok"})
        of.append((r["policy"], r["scenario"], float(r["comm_delay_s"]),
                   float(r["packet_loss"])))
    found = row_sweeps(records, cache, executor=executor, workers=workers)
    peaks: dict[tuple[str, str, float, float], list[float]] = {}
    for rec, key in zip(records, of, strict=True):
        res = found.get((rec["controller"], rec["scenario"], rec["n_vehicles"],
                         rec["comm_delay_s"], rec["packet_loss"], 0.0))
        peaks.setdefault(key, []).append(math.nan if res is None else res.peak_gain)
    rows = []
    for (policy, scenario, delay, loss), values in peaks.items():
        peak = math.nan if any(math.isnan(v) for v in values) else max(values)
        rows.append({"scenario": scenario, "comm_delay_s": delay, "packet_loss": loss,
                     "policy": policy, "sweep_peak_gain": peak,
                     "sweep_string_stable": (None if math.isnan(peak)
                                             else bool(peak <= 1.0 + SWEEP_TOL))})
    cols = ["scenario", "comm_delay_s", "packet_loss", "policy", "sweep_peak_gain",
            "sweep_string_stable"]
    return pd.DataFrame(rows, columns=cols).sort_values(cols[:4]).reset_index(drop=True)


def policy_table(ep: Any) -> Any:
    """Per policy, scenario and V2V setting: episodes, training seeds, collisions and the means
    of reward, energy, gap RMSE and compute per step."""
    keys = ["scenario", "comm_delay_s", "packet_loss", "policy"]
    g = ep.groupby(keys, sort=True)
    out = g.agg(episodes=("seed", "nunique"), train_seeds=("train_seed", "nunique"),
                collisions=("collision", "sum"), reward=("reward", "mean"),
                energy_kwh_per_100km=("energy_kwh_per_100km", "mean"),
                gap_rmse_m=("gap_rmse_m", "mean"), compute_ms_p50=("compute_ms_p50", "mean"))
    order = {p: i for i, p in enumerate(POLICIES)}
    return out.reset_index().sort_values(
        ["scenario", "comm_delay_s", "policy"],
        key=lambda c: c.map(order) if c.name == "policy" else c).reset_index(drop=True)


def _sentence(row: Any) -> str:
    """One comparison as a sentence with its numbers."""
    diff = (f"{num(row['difference'])} [{num(row['ci_low'])}, {num(row['ci_high'])}]")
    if row["basis"] == "collisions":
        return (f"`{row['ours']}` {row['collisions_ours']} colliding episodes against "
                f"`{row['other']}` {row['collisions_other']}: **{row['verdict']}** on collisions "
                f"(reward difference {diff}).")
    return (f"`{row['ours']}` {num(row['reward_ours'])} against `{row['other']}` "
            f"{num(row['reward_other'])}: difference {diff}, **{row['verdict']}**.")


#: The terms of the gap ``ippo (OVM-gain) - mpc``: (name, ours, other).
DECOMPOSITION: tuple[tuple[str, str, str], ...] = (
    ("action set and information", "ippo (OVM-gain)", "ippo"),
    ("reinforcement learning against imitation", "ippo", "distill"),
    ("imitation against its expert", "distill", "mpc"),
)


def _decomposition(comp: Any) -> list[str]:
    """The gap of one scenario as the sum of :data:`DECOMPOSITION`'s terms (their means add up
    exactly; each keeps its own interval), or nothing when a term did not run."""
    diff = {(r["ours"], r["other"]): r for _, r in comp.iterrows() if r["setting"] == "ideal V2V"}
    total = diff.get(("ippo (OVM-gain)", "mpc"))
    found = [(name, diff.get((a, b))) for name, a, b in DECOMPOSITION]
    terms = [(name, t) for name, t in found if t is not None]
    if total is None or len(terms) < len(found):
        return []
    parts = " + ".join(f"{num(t['difference'])} ({name}, [{num(t['ci_low'])}, "
                       f"{num(t['ci_high'])}])" for name, t in terms)
    return [f"The gap, {num(total['difference'])}, is {parts}.", ""]


def write_report(ep: Any, comp: Any, out: Path, command: str, sweeps: Any = None) -> Path:
    """Write ``report.md`` (policy table, the three questions with every comparison) in ``out``;
    with ``sweeps`` (:func:`policy_sweeps`) the policy table shows each row's sweep peak and
    string-stability mark."""
    from analysis.tables import string_stable_mark, sweep_peak_text
    from benchmark.sweep import SWEEP_TOL
    from infra.atomic import write_text

    table, swept = policy_table(ep), sweeps is not None
    if swept:
        keys = ["scenario", "policy", "comm_delay_s", "packet_loss"]
        table = table.merge(sweeps[[*keys, "sweep_peak_gain", "sweep_string_stable"]],
                            how="left", on=keys)
    n = sorted(ep["n_vehicles"].unique())
    lines = [
        "# MARL or MPC: what the gap is made of",
        "",
        f"Made by `{command} --out FOLDER` (N = {', '.join(str(x) for x in n)}; "
        f"{ep['seed'].nunique()} evaluation episodes per policy and training seed; learned "
        "policies pooled over their training seeds, actions sampled as trained). Every "
        "difference is ours minus other in mean episode reward (higher is better) with its 95 % "
        "paired two-stage bootstrap interval over training seeds and episodes; collisions "
        "decide first, then the reward when its interval excludes zero, otherwise "
        "\"inconclusive\". Tables: `policies.csv`, `comparisons.csv`, `episodes.csv`"
        + (", `sweeps.csv`" if swept else "") + ".",
        "",
        *([("Sweep peak: the largest over the training seeds of the peak |Gamma| of the "
            "standard frequency sweep (`benchmark.sweep`: a sinusoidal leader at 0.05 to 0.4 Hz, "
            "the row's N and V2V); string stable (yes) when it is at most 1 + "
            f"{SWEEP_TOL:g}; the reward is measured on the scenario, the sweep on the sweep's "
            "leader."), ""] if swept else []),
        "## The policies",
        "",
        *table_lines(["scenario", "V2V", "policy", "seeds", "episodes", "collisions", "reward",
                      "energy kWh/100 km", "gap RMSE m", "compute ms/step (median)",
                      *(["sweep peak", "string stable"] if swept else [])],
                     ([r["scenario"], "ideal" if r["comm_delay_s"] == 0 and r["packet_loss"] == 0
                       else f"{r['comm_delay_s']:g} s, {100 * r['packet_loss']:g} % loss",
                       f"`{r['policy']}`", r["train_seeds"], r["episodes"], r["collisions"],
                       num(r["reward"]), num(r["energy_kwh_per_100km"]), num(r["gap_rmse_m"]),
                       num(r["compute_ms_p50"], ",.3f"),
                       *([sweep_peak_text(r), string_stable_mark(r)] if swept else [])]
                      for _, r in table.iterrows())),
    ]
    titles = {
        "the gap": "The gap between learned control on the published action set and mpc",
        "action set and information": ("1. How much of the gap is the action set and "
                                       "information?"),
        "learning": "2. How much is learning?",
        "communication": "3. Does communication now matter?",
    }
    for question, title in titles.items():
        lines += ["", f"## {title}", ""]
        sub = comp[comp["question"] == question] if len(comp) else comp
        if not len(sub):
            lines.append("Not measured in this run (a side did not run).")
            continue
        for scenario, grp in sub.groupby("scenario", sort=True):
            lines += [f"**{scenario}**", "", *(f"- {_sentence(r)} ({r['meaning']})"
                                               for _, r in grp.iterrows()), ""]
            if question == "the gap":
                lines += _decomposition(comp[comp["scenario"] == scenario])
    return write_text(out / "report.md", "\n".join(lines).rstrip() + "\n")
