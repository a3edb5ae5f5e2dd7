"""String stability against reward, for every controller: the study of ``cacc-bench
string-stability`` (its report: ``docs/string-stability/report.md``).

What it measures, each from the code that defines it:

- **the certificate** of every gain-scheduled policy (``ippo-gains``, :mod:`marl.ippo_gains`):
  ``||Gamma||_inf`` of Ploeg's loop at points of the segment its checkpoint records, for the
  V2V delays :data:`CERT_DELAYS_S` and actuator lags :data:`CERT_LAGS_S`, by the continuous
  loop and the simulator's exact discrete loop (:mod:`analysis.stability`);
- **the design grid** the segment was read from: ``cacc`` with fixed gains and time gaps
  (:data:`DESIGN_GRIDS`) on the validation seeds (a decision: the test seeds are refused), each
  point with its certified peak; the **trade-off**: the best validation reward among the points
  whose peak is at most a bound, for each bound of :data:`TRADEOFF_BOUNDS`;
- **reward** of every entry of :data:`ENTRIES` on the test seeds, N = 8, learned ones pooled
  over their training seeds, under ideal V2V, no V2V (every packet lost) and a degraded channel
  (0.2 s delay, 30 % loss): the runs go through the results store (``cacc-bench run``'s), and
  this module reads their ``runs.csv``;
- **the standard frequency sweep** of every entry (:func:`benchmark.sweep.sweep_peak`) at N =
  4, 8 and 12 under ideal and degraded V2V and at N = 8 without V2V, learned ones per training
  seed (pooled: the largest peak);
- **the goal** of issue 54, point 4, per learned entry and scenario (:func:`goal_frame`).
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from analysis.tables import num, table_lines
from studies.learned_report import HIGHER, compare, side

#: V2V settings of the study, by name: (delay s, loss).
CHANNELS: dict[str, tuple[float, float]] = {
    "ideal": (0.0, 0.0), "none": (0.0, 1.0), "degraded": (0.2, 0.3)}
#: Platoon sizes of the sweeps, and the size of the reward runs (the shipped policies' N).
SWEEP_SIZES: tuple[int, ...] = (4, 8, 12)
REWARD_N = 8
#: Training seeds of the shipped learned policies.
TRAIN_SEEDS: tuple[int, ...] = (0, 1, 2)
#: V2V delays (s) and actuator lags (s) every point of a certified segment is checked at.
CERT_DELAYS_S: tuple[float, ...] = (0.0, 0.1, 0.2)
CERT_LAGS_S: tuple[float, ...] = (0.0, 0.1)
#: Points of a segment the certificate evaluates (``s = 0, 1/(K-1), ..., 1``).
CERT_POINTS = 41
#: The fixed-gain grids of ``cacc`` the design reads (kp 1/s^2, kd 1/s, time gap s): the full
#: one of the committed report, and a small one for a quick look.
DESIGN_GRIDS: dict[str, tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]] = {
    "full": ((0.05, 0.1, 0.2, 0.3, 0.4, 0.6), (0.7, 1.5, 2.0, 2.5, 3.0), (0.4, 0.5, 0.65, 0.8,
                                                                           1.0)),
    "small": ((0.2, 0.6), (0.7, 3.0), (0.5, 0.8)),
}
#: Peak bounds of the trade-off (``inf``: no bound).
TRADEOFF_BOUNDS: tuple[float, ...] = (1.0, 1.01, 1.02, 1.05, 1.1, 1.2, math.inf)
#: The setting the design grid's peaks are certified at: the worst of :data:`CERT_DELAYS_S`
#: and :data:`CERT_LAGS_S`.
DESIGN_DELAY_S, DESIGN_LAG_S = 0.2, 0.1


@dataclass(frozen=True)
class Entry:
    """One controller of the study.

    Attributes
    ----------
    name : str
        Its name in the report.
    controller : str
        The registered controller.
    options : tuple of (str, str)
        Its options (a learned one: without the training seed).
    learned : bool
        Trained (three shipped training seeds, pooled).
    stage : str
        ``model-based``; ``before`` (learned without string stability in view) or ``after``
        (trained to keep it, issue 54).
    """

    name: str
    controller: str
    options: tuple[tuple[str, str], ...]
    learned: bool
    stage: str

    def runs(self) -> list[dict[str, str]]:
        """The options of each run: one per training seed for a learned entry."""
        base = dict(self.options)
        return [{**base, "seed": str(s)} for s in TRAIN_SEEDS] if self.learned else [base]


def _fixed(name: str, point: tuple[float, float, float]) -> Entry:
    kp, kd, h = point
    return Entry(name, "cacc", (("kp", f"{kp:g}"), ("kd", f"{kd:g}"), ("time_gap_s", f"{h:g}")),
                 False, "model-based")


def default_entries() -> tuple[Entry, ...]:
    """Every controller of the report: the model-based ones (``cacc``, ``acc``, ``mpc`` and
    ``cacc`` fixed at each end of ``ippo-gains``' default segment), the learned ones shipped
    before issue 54, and those trained to keep string stability."""
    from marl.ippo_gains import GainScheduleConfig

    soft, stiff = GainScheduleConfig().segment
    return (
        Entry("cacc", "cacc", (), False, "model-based"),
        Entry("acc", "acc", (), False, "model-based"),
        Entry("mpc", "mpc", (), False, "model-based"),
        _fixed("cacc (segment's soft end)", soft),
        _fixed("cacc (segment's stiff end)", stiff),
        Entry("ippo", "ippo", (), True, "before"),
        Entry("mappo", "mappo", (), True, "before"),
        Entry("distill", "distill", (), True, "before"),
        Entry("ippo-bdc", "ippo-bdc", (), True, "before"),
        Entry("ippo (residual, time-aware critic)", "ippo", (("variant", "residual-timed"),),
              True, "before"),
        Entry("ippo-gains", "ippo-gains", (), True, "after"),
    )


def available(entries: Sequence[Entry], scenarios: Sequence[str]) -> tuple[list[Entry],
                                                                             list[str]]:
    """The entries whose every run has its policy for every scenario (shipped checkpoints), and
    a line for each left out."""
    from controllers.policy import VARIANT_DIR, checkpoint_path

    kept, notes = [], []
    n = REWARD_N  # every learner of the report is shipped at N = 8
    for e in entries:
        folder = VARIANT_DIR / dict(e.options)["variant"] if "variant" in dict(e.options) else None
        missing = [(sc, s) for sc in scenarios for s in TRAIN_SEEDS if e.learned
                   and not checkpoint_path(e.controller, sc, n, s, folder).exists()]
        if missing:
            notes.append(f"{e.name} left out: no shipped checkpoint for {missing[0][0]}, "
                         f"N = {n}, seed {missing[0][1]}")
        else:
            kept.append(e)
    return kept, notes


def channel_name(delay_s: float, loss: float) -> str | None:
    """The :data:`CHANNELS` name of a V2V setting, or None."""
    for name, (d, p) in CHANNELS.items():
        if math.isclose(delay_s, d, abs_tol=1e-12) and math.isclose(loss, p, abs_tol=1e-12):
            return name
    return None


# ------------------------------------------------------------------------------ certificate
def certificate(segment: Any, points: int = CERT_POINTS,
                delays_s: Sequence[float] = CERT_DELAYS_S,
                lags_s: Sequence[float] = CERT_LAGS_S) -> Any:
    """``||Gamma||_inf`` of Ploeg's loop at ``points`` points of ``segment`` (``((kp, kd, h)
    at s = 0, (kp, kd, h) at s = 1)``) for every delay and lag: one row per point and setting
    with ``kp, kd, time_gap_s``, the continuous peak (exact delay), the discrete peak (the
    simulator's loop) and whether the loop is internally stable."""
    import pandas as pd

    from analysis.stability import (
        PloegLoop,
        discrete_hinf_norm,
        discrete_internally_stable,
        hinf_norm,
        internally_stable,
    )

    (a, b) = segment
    rows = []
    for s in np.linspace(0.0, 1.0, points):
        kp, kd, h = (float(x + s * (y - x)) for x, y in zip(a, b, strict=True))
        for d in delays_s:
            for lag in lags_s:
                loop = PloegLoop(kp, kd, h, float(d), float(lag))
                rows.append({"s": float(s), "kp": kp, "kd": kd, "time_gap_s": h,
                             "delay_s": float(d), "lag_s": float(lag),
                             "peak_continuous": hinf_norm(loop).gain,
                             "peak_discrete": discrete_hinf_norm(loop).gain,
                             "internally_stable": bool(internally_stable(loop)
                                                       and discrete_internally_stable(loop))})
    return pd.DataFrame(rows)


@functools.cache
def _certificate_of(segment: Any) -> Any:
    """:func:`certificate` of ``segment`` with the default points and settings, once per
    segment (the shipped checkpoints share one)."""
    return certificate(segment)


def certified(cert: Any) -> bool:
    """Whether every row of :func:`certificate` is internally stable with both peaks at most 1
    (the analytic tolerance, :data:`analysis.stability.ANALYTIC_TOL`)."""
    from analysis.stability import ANALYTIC_TOL

    return bool(cert["internally_stable"].all()
                and (cert[["peak_continuous", "peak_discrete"]].to_numpy()
                     <= 1.0 + ANALYTIC_TOL).all())


def checkpoint_segments(scenarios: Sequence[str]) -> Any:
    """The segment every shipped ``ippo-gains`` checkpoint records, with its certificate's
    worst peak: one row per scenario and training seed."""
    import pandas as pd

    from controllers.policy import checkpoint_path
    from marl.checkpoint import load_checkpoint
    from marl.ippo_gains import load_gain_actor

    rows = []
    for sc in scenarios:
        for seed in TRAIN_SEEDS:
            path = checkpoint_path("ippo-gains", sc, REWARD_N, seed)
            if not path.exists():
                continue
            actor = load_gain_actor(load_checkpoint(path, algo="ippo-gains"))
            cert = _certificate_of(actor.segment)
            (a, b) = actor.segment
            rows.append({"scenario": sc, "train_seed": seed, "start": " ".join(f"{x:g}" for x in a),
                         "end": " ".join(f"{x:g}" for x in b),
                         "worst_peak": float(cert[["peak_continuous", "peak_discrete"]].max().max()),
                         "certified": certified(cert)})
    return pd.DataFrame(rows, columns=["scenario", "train_seed", "start", "end", "worst_peak",
                                       "certified"])


# ---------------------------------------------------------------------------- the design grid
def design_grid(grid: str, scenarios: Sequence[str], seeds: Sequence[int]) -> Any:
    """``cacc`` at every fixed ``(kp, kd, h)`` of :data:`DESIGN_GRIDS` ``[grid]`` on the
    validation ``seeds`` (N = 8): mean reward and collisions per scenario, and the point's
    certified peak (the worst of continuous and discrete at :data:`DESIGN_DELAY_S` and
    :data:`DESIGN_LAG_S`) and ideal-V2V discrete peak."""
    import pandas as pd

    from analysis.stability import PloegLoop, discrete_hinf_norm, hinf_norm
    from benchmark.rollout import rollout_batch
    from controllers.registry import make_controller
    from envs.params import check_decision_seeds
    from envs.scenarios import make_scenario
    from infra.errors import ConfigError
    from infra.interrupt import raise_if_interrupted

    if grid not in DESIGN_GRIDS:
        raise ConfigError(f"unknown design grid {grid!r}; valid: {', '.join(DESIGN_GRIDS)}")
    check_decision_seeds(seeds, "the design grid of cacc-bench string-stability")
    kps, kds, hs = DESIGN_GRIDS[grid]
    built = {sc: make_scenario(sc) for sc in scenarios}
    rows = []
    for kp in kps:
        for kd in kds:
            for h in hs:
                raise_if_interrupted()
                worst = PloegLoop(kp, kd, h, DESIGN_DELAY_S, DESIGN_LAG_S)
                row: dict[str, Any] = {
                    "kp": kp, "kd": kd, "time_gap_s": h, "validation_episodes": len(seeds),
                    "peak_certified": max(hinf_norm(worst).gain, discrete_hinf_norm(worst).gain),
                    "peak_ideal": discrete_hinf_norm(PloegLoop(kp, kd, h)).gain}
                for sc, scenario in built.items():
                    ctrl = make_controller("cacc", kp=kp, kd=kd, time_gap_s=h)
                    trajs = rollout_batch(ctrl, scenario, REWARD_N, list(seeds))
                    row[f"reward_{sc}"] = float(np.mean([t.reward.mean() for t in trajs]))
                    row[f"collisions_{sc}"] = int(sum(t.collided for t in trajs))
                rows.append(row)
    return pd.DataFrame(rows)


def tradeoff(design: Any, scenarios: Sequence[str]) -> Any:
    """Per scenario and bound of :data:`TRADEOFF_BOUNDS`: the best validation reward of the
    design grid's collision-free points whose certified peak is at most the bound, and that
    point."""
    import pandas as pd

    rows = []
    for sc in scenarios:
        ok = design[design[f"collisions_{sc}"] == 0]
        for bound in TRADEOFF_BOUNDS:
            sub = ok[ok["peak_certified"] <= bound + 1e-9]
            if sub.empty:
                rows.append({"scenario": sc, "peak_bound": bound, "points": 0})
                continue
            best = sub.loc[sub[f"reward_{sc}"].idxmax()]
            rows.append({"scenario": sc, "peak_bound": bound, "points": len(sub),
                         "best_reward": float(best[f"reward_{sc}"]), "kp": float(best["kp"]),
                         "kd": float(best["kd"]), "time_gap_s": float(best["time_gap_s"]),
                         "peak_certified": float(best["peak_certified"])})
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------- rewards
def run_specs(entries: Sequence[Entry]) -> list[tuple[str, dict[str, str]]]:
    """``(controller, options)`` of every run of ``entries`` (the sweep's controllers)."""
    return [(e.controller, opts) for e in entries for opts in e.runs()]


def entry_of(entries: Sequence[Entry], controller: str, options: dict[str, Any]) -> Entry | None:
    """The entry a run of ``controller`` with ``options`` belongs to (its seed aside; options
    compared by their canonical label, so a default given or left out is the same)."""
    from controllers.registry import controller_label

    label = controller_label(controller, {k: v for k, v in options.items() if k != "seed"})
    for e in entries:
        if e.controller == controller and controller_label(e.controller,
                                                           dict(e.options)) == label:
            return e
    return None


def episodes_frame(runs: Any, entries: Sequence[Entry]) -> Any:
    """One row per entry, training seed, scenario, V2V setting and episode of ``runs.csv``
    (finished runs of ``entries`` at N = :data:`REWARD_N`)."""
    import pandas as pd

    rows = []
    for _, r in runs.iterrows():
        if r["status"] != "ok" or int(r["n_vehicles"]) != REWARD_N:
            continue
        opts = json.loads(r["options"] or "{}")
        e = entry_of(entries, str(r["controller_name"]), opts)
        channel = channel_name(float(r["comm_delay_s"]), float(r["packet_loss"]))
        if e is None or channel is None:
            continue
        rows.append({"entry": e.name, "train_seed": int(opts.get("seed", 0)),
                     "scenario": r["scenario"], "channel": channel, "seed": int(r["seed"]),
                     "reward": float(r["reward"]),
                     "collision": bool(r["collision"] in (True, "True"))})
    cols = ["entry", "train_seed", "scenario", "channel", "seed", "reward", "collision"]
    df = pd.DataFrame(rows, columns=cols)
    return df.sort_values(cols[:5], kind="mergesort").reset_index(drop=True)


def _side(ep: Any, entry: str, scenario: str, channel: str) -> Any:
    return side(ep[(ep["entry"] == entry) & (ep["scenario"] == scenario) & (ep["channel"] == channel)])


def reward_table(ep: Any, entries: Sequence[Entry]) -> Any:
    """Per entry, scenario and V2V setting: training seeds, episodes, colliding episodes and the
    mean reward with its two-stage interval (training seeds, then episodes)."""
    import pandas as pd

    from benchmark.statistics import hierarchical_bootstrap_ci

    rows = []
    for e in entries:
        for (sc, ch), grp in ep[ep["entry"] == e.name].groupby(["scenario", "channel"], sort=True):
            groups = [g["reward"].to_numpy() for _, g in grp.groupby("train_seed", sort=True)]
            mean, lo, hi = hierarchical_bootstrap_ci(groups)
            rows.append({"entry": e.name, "stage": e.stage, "scenario": sc, "channel": ch,
                         "train_seeds": len(groups), "episodes": int(grp["seed"].nunique()),
                         "collisions": int(grp["collision"].sum()), "reward": mean,
                         "ci_low": lo, "ci_high": hi})
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------------- sweeps
def sweep_settings(sizes: Sequence[int]) -> list[tuple[int, str]]:
    """``(N, channel)`` of every sweep: each size under ideal and degraded V2V, and N = 8 (or
    the middle size) without V2V."""
    middle = REWARD_N if REWARD_N in sizes else sorted(sizes)[len(sizes) // 2]
    return [(n, ch) for n in sizes for ch in ("ideal", "degraded")] + [(middle, "none")]


def sweeps_frame(entries: Sequence[Entry], scenarios: Sequence[str], sizes: Sequence[int],
                 cache: Any = None) -> Any:
    """The standard sweep (:func:`benchmark.sweep.sweep_peak`) of every run of every entry,
    as it acts on each scenario, at every setting of :func:`sweep_settings` (a policy with one
    network per follower, ``ippo-bdc``, at its trained N only): peak, where, and whether it is
    string stable, collided or saturated."""
    import pandas as pd

    from benchmark.sweep import sweep_peak
    from marl.learners import LEARNERS

    rows = []
    for e in entries:
        per_agent = e.learned and LEARNERS[e.controller].per_agent
        settings = [(n, ch) for n, ch in sweep_settings(sizes)
                    if not per_agent or n == REWARD_N]
        for sc in scenarios:
            for opts in e.runs():
                for n, ch in settings:
                    delay, loss = CHANNELS[ch]
                    res = sweep_peak(e.controller, opts, n_vehicles=n, comm_delay_s=delay,
                                     packet_loss=loss, scenario=sc, cache=cache)
                    rows.append({"entry": e.name, "stage": e.stage, "scenario": sc,
                                 "train_seed": int(opts.get("seed", 0)), "n_vehicles": n,
                                 "channel": ch, "peak_gain": res.peak_gain,
                                 "omega_at_peak_rad_s": res.omega_at_peak_rad_s,
                                 "string_stable": res.string_stable, "collided": res.collided,
                                 "saturated": res.saturated})
    return pd.DataFrame(rows)


def pooled_peaks(sweeps: Any) -> Any:
    """The largest peak over an entry's training seeds per scenario, N and channel."""
    keys = ["entry", "stage", "scenario", "n_vehicles", "channel"]
    return (sweeps.groupby(keys, sort=False)
            .agg(peak_gain=("peak_gain", "max"), collided=("collided", "any"))
            .reset_index())


def _peak_of(peaks: Any) -> dict[tuple[str, str, str, int], float]:
    """A :func:`pooled_peaks` table as a mapping (entry, scenario, channel, N) -> peak."""
    cols = ["entry", "scenario", "channel", "n_vehicles", "peak_gain"]
    return {(e, sc, ch, int(n)): float(p) for e, sc, ch, n, p in peaks[cols].itertuples(index=False)}


# ------------------------------------------------------------------------------------- goal
def goal_frame(ep: Any, sweeps: Any, entries: Sequence[Entry], reference: str = "cacc") -> Any:
    """Issue 54's goal, per learned entry and scenario, against ``reference``: its pooled sweep
    peak at most the reference's at every size, under ideal and degraded V2V; at most
    ``1 + SWEEP_TOL`` under ideal V2V; no colliding test episode (ideal and degraded); a test
    reward above the reference's with a paired interval above 0; and a smaller loss than the
    reference's under degraded V2V (the paired intervals of both losses given)."""
    import pandas as pd

    from benchmark.sweep import SWEEP_TOL

    peaks = pooled_peaks(sweeps)
    peak, sizes = _peak_of(peaks), sorted(peaks["n_vehicles"].unique())
    rows = []
    for e in entries:
        if not e.learned:
            continue
        for sc in sorted(ep["scenario"].unique()):
            ours, ref = _side(ep, e.name, sc, "ideal"), _side(ep, reference, sc, "ideal")
            ours_d, ref_d = _side(ep, e.name, sc, "degraded"), _side(ep, reference, sc, "degraded")
            if ours is None or ref is None:
                continue
            row: dict[str, Any] = {"entry": e.name, "scenario": sc}
            worst = 0.0
            above_ref = []
            for ch in ("ideal", "degraded"):
                for n in sizes:
                    mine, theirs = peak.get((e.name, sc, ch, n)), peak.get((reference, sc, ch, n))
                    if mine is None or theirs is None:
                        continue
                    row[f"peak_{ch}_n{n}"], row[f"{reference}_peak_{ch}_n{n}"] = mine, theirs
                    above_ref.append(mine - theirs)
                    if ch == "ideal":
                        worst = max(worst, mine)
            row["peak_at_most_reference"] = bool(above_ref) and max(above_ref) <= 0.0
            row["largest_excess_over_reference"] = max(above_ref) if above_ref else math.nan
            row["peak_ideal_worst"] = worst
            row["string_stable_ideal"] = worst <= 1.0 + SWEEP_TOL
            cmp = compare(ours, ref)
            row.update(reward=cmp["reward_ours"], reference_reward=cmp["reward_other"],
                       difference=cmp["difference"], ci_low=cmp["ci_low"],
                       ci_high=cmp["ci_high"], collisions=cmp["collisions_ours"])
            row["above_reference"] = cmp["verdict"] == HIGHER and cmp["basis"] == "reward"
            if ours_d is not None and ref_d is not None:
                row["collisions"] += ours_d[1]
                losses = {"": compare(ours, ours_d, same_policy=True),
                          "reference_": compare(ref, ref_d, same_policy=True)}
                for who, c in losses.items():
                    row.update({f"{who}loss_degraded": c["difference"],
                                f"{who}loss_ci_low": c["ci_low"], f"{who}loss_ci_high": c["ci_high"]})
                row["loses_less"] = row["loss_degraded"] < row["reference_loss_degraded"]
            row["collision_free"] = row["collisions"] == 0
            row["goal_met"] = bool(row["peak_at_most_reference"] and row["string_stable_ideal"]
                                   and row["collision_free"] and row["above_reference"]
                                   and row.get("loses_less", False))
            rows.append(row)
    # no learned entry: the table is empty but keeps its header (a reader of goal.csv, and the
    # report read back from it, see "no goal to check", not a damaged file)
    return pd.DataFrame(rows) if rows else pd.DataFrame(columns=["entry", "scenario", "goal_met"])


def v2v_worth(table: Any) -> Any:
    """Per entry and scenario: the mean test reward under each V2V setting, what V2V is worth
    (ideal minus none) and what the degraded channel costs (ideal minus degraded)."""
    wide = table.pivot_table(index=["entry", "stage", "scenario"], columns="channel",
                             values="reward", sort=False).reset_index()
    for ch in CHANNELS:
        if ch not in wide:
            wide[ch] = math.nan
    wide["worth_ideal_over_none"] = wide["ideal"] - wide["none"]
    wide["cost_of_degraded"] = wide["ideal"] - wide["degraded"]
    wide.columns.name = None
    return wide[["entry", "stage", "scenario", "ideal", "none", "degraded",
                 "worth_ideal_over_none", "cost_of_degraded"]]


# ----------------------------------------------------------------------------------- report
def _num(x: Any, digits: int = 2) -> str:
    return "inf (collided)" if isinstance(x, float) and math.isinf(x) else num(x, f",.{digits}f")


def _mark(ok: Any) -> str:
    return "yes" if bool(ok) else "**no**"


def render_report(tables: dict[str, Any], command: str) -> str:
    """``report.md`` from the study's tables (``rewards``, ``sweeps``, ``goal``, ``v2v``,
    ``certificate``, ``segments``, ``design``, ``tradeoff``): a function of the tables alone, so
    the committed report can be checked against its CSVs."""
    from benchmark.sweep import SWEEP_TOL

    rewards, goal, v2v = tables["rewards"], tables["goal"], tables["v2v"]
    peaks = pooled_peaks(tables["sweeps"])
    peak, sizes = _peak_of(peaks), sorted(peaks["n_vehicles"].unique())

    def peak_text(r: Any, channel: str, n: int) -> str:
        key = (r["entry"], r["scenario"], channel, n)
        return _num(peak[key], 3) if key in peak else "n/a"

    lines = [
        "# String stability against reward, for every controller",
        "",
        f"Made by `{command} --out FOLDER`. Rewards: the test seeds (`--seed-set test`), "
        f"N = {REWARD_N}, learned policies pooled over their three training seeds (actions "
        "sampled as trained), mean episode reward with its 95 % two-stage bootstrap interval. "
        "Sweep peaks: the standard frequency sweep of `benchmark.sweep` (the grid, leader "
        "amplitude and fit every leaderboard row uses), the largest over a learned policy's "
        f"three training seeds, each seed's policy as it acts on the scenario named; string "
        f"stable when at most 1 + {SWEEP_TOL:g}. V2V: ideal, none (every packet lost) and "
        "degraded (0.2 s delay, 30 % loss). Tables: `rewards.csv`, `sweeps.csv`, `goal.csv`, "
        "`v2v.csv`, `certificate.csv`, `segments.csv`, `design.csv`, `tradeoff.csv`, "
        "`episodes.csv`.",
        "",
        "## Reward against sweep peak",
        "",
        "Ideal V2V; the peak at N = " + ", ".join(str(n) for n in sizes) + ".",
        "",
        *table_lines(["scenario", "stage", "controller", "collisions", "reward [95 % CI]",
                      *(f"peak N = {n}" for n in sizes)],
                     ([r["scenario"], r["stage"], f"`{r['entry']}`",
                       f"{r['collisions']}/{r['episodes'] * r['train_seeds']}",
                       f"{_num(r['reward'])} [{_num(r['ci_low'])}, {_num(r['ci_high'])}]",
                       *(peak_text(r, "ideal", n) for n in sizes)]
                      for _, r in rewards[rewards["channel"] == "ideal"].iterrows())),
        "", "## The goal (issue 54, point 4), against `cacc`", "",
    ]
    if goal.empty:
        lines.append("No learned controller ran.")
    else:
        def loss(g: Any) -> str:
            ours = _num(g.get("loss_degraded"))
            return "n/a" if ours == "n/a" else f"{ours} ({_num(g.get('reference_loss_degraded'))})"

        lines += table_lines(
            ["controller", "scenario", "peak <= cacc's (N, V2V ideal and degraded)",
             "largest excess", "peak, ideal, worst N", "stable (ideal)", "collision-free",
             "reward - cacc's [95 % CI]", "loss under degraded V2V (cacc's)", "goal met"],
            ([f"`{g['entry']}`", g["scenario"], _mark(g["peak_at_most_reference"]),
              _num(g["largest_excess_over_reference"], 3), _num(g["peak_ideal_worst"], 3),
              _mark(g["string_stable_ideal"]), _mark(g["collision_free"]),
              f"{_num(g['difference'])} [{_num(g['ci_low'])}, {_num(g['ci_high'])}]", loss(g),
              _mark(g["goal_met"])] for _, g in goal.iterrows()))
    lines += ["", "## What V2V is worth", "",
              "Mean test reward under each V2V setting; worth = ideal - none, cost = ideal - "
              "degraded; and the sweep peak at N = 8 under each.", "",
              *table_lines(["scenario", "controller", "ideal", "none", "degraded", "worth",
                            "cost", "peak ideal", "peak none", "peak degraded"],
                           ([r["scenario"], f"`{r['entry']}`",
                             *(_num(r[c]) for c in ("ideal", "none", "degraded",
                                                    "worth_ideal_over_none", "cost_of_degraded")),
                             *(peak_text(r, ch, REWARD_N) for ch in ("ideal", "none", "degraded"))]
                            for _, r in v2v.iterrows()))]
    cert, segs = tables["certificate"], tables["segments"]
    lines += ["", "## The certificate of `ippo-gains`", "",
              f"Ploeg's `||Gamma||_inf` at {cert['s'].nunique()} points of the default segment, "
              f"V2V delays {', '.join(f'{d:g}' for d in sorted(cert['delay_s'].unique()))} s and "
              f"lags {', '.join(f'{x:g}' for x in sorted(cert['lag_s'].unique()))} s "
              "(continuous loop with the exact delay, and the simulator's discrete loop): "
              f"worst {_num(float(cert['peak_continuous'].max()), 6)} and "
              f"{_num(float(cert['peak_discrete'].max()), 6)}; internally stable everywhere: "
              f"{_mark(cert['internally_stable'].all())}.", ""]
    if len(segs):
        lines += table_lines(["scenario", "seed", "segment start (kp kd h)", "end", "worst peak",
                              "certified"],
                             ([r["scenario"], r["train_seed"], r["start"], r["end"],
                               _num(r["worst_peak"], 6), _mark(r["certified"])]
                              for _, r in segs.iterrows()))
    trade, design = tables["tradeoff"], tables["design"]
    lines += ["", "## The trade-off: reward against the certified peak", "",
              f"`cacc` with fixed gains on the design grid ({len(design)} points of kp, kd and "
              "h), on the validation seeds: for each bound, the best validation reward among "
              f"the collision-free points whose peak (continuous and discrete, {DESIGN_DELAY_S:g} "
              f"s delay, {DESIGN_LAG_S:g} s lag) is at most the bound.", "",
              *table_lines(["scenario", "peak bound", "points", "best validation reward", "kp",
                            "kd", "h", "peak"], [])]
    for _, r in trade.iterrows():
        bound = "none" if math.isinf(r["peak_bound"]) else f"{r['peak_bound']:g}"
        if not r["points"]:
            lines.append(f"| {r['scenario']} | {bound} | 0 | n/a | | | | |")
            continue
        lines.append(f"| {r['scenario']} | {bound} | {int(r['points'])} | "
                     f"{_num(r['best_reward'])} | {r['kp']:g} | {r['kd']:g} | "
                     f"{r['time_gap_s']:g} | {_num(r['peak_certified'], 4)} |")
    return "\n".join(lines).rstrip() + "\n"


#: The tables of the study, by name: the CSV file each is written to.
TABLES: tuple[str, ...] = ("rewards", "sweeps", "goal", "v2v", "certificate", "segments",
                           "design", "tradeoff")


def write_tables(tables: dict[str, Any], episodes: Any, out: Path, command: str) -> Path:
    """Write every table as ``<name>.csv``, ``episodes.csv`` and ``report.md`` into ``out``;
    the report is rendered from the tables read back from their files (what a reader of the
    folder can check it against)."""
    from benchmark.export import write_csv
    from infra.atomic import write_text

    for name in TABLES:
        write_csv(tables[name], out / f"{name}.csv")
    write_csv(episodes, out / "episodes.csv")
    path = out / "report.md"
    write_text(path, render_report(read_tables(out), command))
    return path


def read_tables(folder: Path) -> dict[str, Any]:
    """The tables a folder holds (what :func:`write_tables` wrote)."""
    from infra.files import read_csv

    return {name: read_csv(folder / f"{name}.csv", f"the {name} table") for name in TABLES}
