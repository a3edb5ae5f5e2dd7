"""CSV files of a results folder, rebuilt from the store: runs.csv, leaderboard.csv, trajectories."""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from benchmark.metrics import class_energy_columns
from benchmark.rollout import Trajectory
from benchmark.statistics import bootstrap_ci, hierarchical_bootstrap_ci
from benchmark.string_gain import is_string_stable
from benchmark.suite import KEY_COLUMNS
from infra.errors import ConfigError

#: The mixed-traffic columns of runs.csv (:func:`benchmark.metrics.mixed_traffic_metrics`).
MIXED_COLUMNS: tuple[str, ...] = (
    "cav_share", "head_to_tail_gain", "speed_std_last_mps", "speed_std_humans_mps",
    "braking_events", "braking_events_humans", "braking_events_cavs", "braking_events_per_veh_h",
    "energy_humans_kwh", "energy_cavs_kwh", "controllable_energy_humans_kwh",
    "controllable_energy_cavs_kwh",
)

#: The gap RMSE against the controller's own spacing policy and the jerk without the start-up
#: transient (:func:`benchmark.metrics.run_metrics`; ``gap_rmse_m`` and ``jerk_rms_mps3`` stay
#: as published).
SPACING_JERK_COLUMNS: tuple[str, ...] = ("gap_rmse_own_policy_m", "jerk_rms_after_start_mps3")

#: Energy per vehicle class and the drag-saving model used (:mod:`envs.vehicle_classes`;
#: :func:`benchmark.metrics.class_energy_metrics`): empty for the homogeneous platoon's classes.
CLASS_ENERGY_COLUMNS: tuple[str, ...] = class_energy_columns()

RUN_COLUMNS: tuple[str, ...] = (
    "controller", "family", "scenario", "n_vehicles", "seed", "status", "error", "steps",
    "collision", "min_gap_m", "gap_mean_m", "gap_std_m", "gap_rmse_m", "speed_mean_mps",
    "speed_std_mps", "speed_rmse_mps", "accel_mean_mps2", "accel_std_mps2", "accel_rms_mps2",
    "jerk_rms_mps3", "energy_kwh", "power_mean_kw", "energy_kwh_per_100km", "reward",
    "tracking_reward", "string_gain", "string_stable", "compute_ms_p50", "compute_ms_p95",
    "compute_ms_p99", "compute_ms_first", "solver_failures", "comm_bits_per_s", "comm_delay_s",
    "packet_loss", "lag_s", "wall_s", "version", "git_sha",
    # additions
    "controller_name", "options", "deterministic", "spacing_string_gain",
    "safety_interventions", "safety_correction_mps2",
    "controllable_energy_kwh", "controllable_energy_kwh_per_100km",
    # mixed traffic (benchmark.metrics.mixed_traffic_metrics)
    *MIXED_COLUMNS,
    # the gap against the controller's own spacing policy; jerk without the start-up transient
    *SPACING_JERK_COLUMNS,
    # energy per vehicle class, the drag-saving model (benchmark.metrics.class_energy_metrics)
    *CLASS_ENERGY_COLUMNS,
)

#: Columns a store written before they existed lacks; a finished run there had no safety filter.
ZERO_WHEN_ABSENT: tuple[str, ...] = ("safety_interventions", "safety_correction_mps2")

#: Columns a store written before they existed lacks and that cannot be recomputed without the
#: trajectory: empty (NaN) in runs.csv for such a run, never 0. A leaderboard mean of one of them
#: is NaN unless every finished run of its row has the value (a mean over part of the episodes
#: would not be comparable with the other columns' means over all of them).
UNKNOWN_WHEN_ABSENT: tuple[str, ...] = (
    "controllable_energy_kwh", "controllable_energy_kwh_per_100km",
    *(c for c in MIXED_COLUMNS if c != "cav_share"),
    *SPACING_JERK_COLUMNS,
    *CLASS_ENERGY_COLUMNS,
)

#: Mixed-traffic metrics the leaderboard averages over episodes (``cav_share`` is a plain
#: column: one arrangement per row).
MIXED_LEADERBOARD_METRICS: tuple[str, ...] = (
    "head_to_tail_gain", "speed_std_last_mps", "speed_std_humans_mps",
    "braking_events_per_veh_h", "energy_humans_kwh", "energy_cavs_kwh",
)

LEADERBOARD_METRICS: tuple[str, ...] = (
    "reward", "tracking_reward", "energy_kwh", "power_mean_kw", "gap_mean_m", "gap_std_m",
    "gap_rmse_m", "speed_mean_mps", "speed_std_mps", "accel_std_mps2", "jerk_rms_mps3",
    "string_gain", "compute_ms_p50", "comm_bits_per_s", "energy_kwh_per_100km", "min_gap_m",
    "controllable_energy_kwh", "controllable_energy_kwh_per_100km",
    *MIXED_LEADERBOARD_METRICS,
    *SPACING_JERK_COLUMNS,
)

GROUP_COLUMNS: tuple[str, ...] = (
    "controller", "scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s",
)

#: The leaderboard's columns from the standard frequency sweep (:mod:`benchmark.sweep`), the
#: controller's property at the row's N, channel and lag (beside ``string_gain_*``, the
#: time-domain ratio on the row's own scenario): the sweep's peak ``|Gamma(jw)|`` (``inf``: an
#: episode of the sweep collided; the max over the training seeds of a pooled row), the
#: frequency of that peak, and the mark: True when the peak is at most ``1 +
#: benchmark.sweep.SWEEP_TOL``, empty when the row has no sweep (a recorded platoon, a policy
#: that is gone or has changed since its runs).
SWEEP_COLUMNS: tuple[str, ...] = ("sweep_peak_gain", "sweep_peak_omega_rad_s",
                                  "sweep_string_stable")

#: How ``rank`` orders the rows of one setting (``--rank-by``). Both put the rows without a
#: collision or a failed run first. ``reward``: then by mean reward. ``string-stability``: then
#: the rows the sweep marks string stable, then by mean reward (a row without a sweep counts as
#: not string stable).
RANK_BY: tuple[str, ...] = ("reward", "string-stability")

BOOTSTRAP_SEED = 20240601


def runs_frame(records: list[dict[str, Any]]) -> Any:
    """runs.csv as a DataFrame, one row per run, sorted by the run key."""
    import pandas as pd

    rows = []
    for rec in records:
        row = {c: rec.get(c) for c in RUN_COLUMNS}
        row["controller_name"] = rec.get("name", rec.get("controller"))
        row["options"] = rec.get("options", "{}")
        if rec.get("status") == "ok":
            for c in ZERO_WHEN_ABSENT:
                if c not in rec:
                    row[c] = 0.0
        if row["cav_share"] is None:  # a failed run, or one stored before the column
            row["cav_share"] = _cav_share(str(rec.get("scenario")), rec.get("n_vehicles"))
        rows.append(row)
    df = pd.DataFrame(rows, columns=list(RUN_COLUMNS))
    if len(df):
        df = df.sort_values(list(KEY_COLUMNS), kind="mergesort").reset_index(drop=True)
    return df


@functools.lru_cache(maxsize=256)
def _cav_share(scenario: str, n_vehicles: Any) -> float:
    """The share of automated followers of the scenario label's arrangement for ``n_vehicles``
    (NaN where the label or the size cannot be built: a scenario this version does not know)."""
    from envs.scenarios import as_scenario

    try:
        return as_scenario(scenario).arrangement(int(n_vehicles)).cav_share
    except (ConfigError, KeyError, TypeError, ValueError):  # UnknownNameError is a KeyError
        return math.nan


def pool_training_seeds(runs: Any) -> Any:
    """Runs of one policy trained with several seeds under one label.

    Rows of the ``marl`` family whose options differ only by ``seed`` (the training seed; 0 when
    absent) get the label ``NAME[...,seeds=0+1+2]`` when more than one seed is present, and the
    column ``train_seed``; other rows are unchanged (``train_seed`` empty).
    """
    import json

    from controllers.registry import controller_label

    runs = runs.copy()
    runs["train_seed"] = np.nan
    if len(runs) == 0:
        return runs
    base_labels: dict[int, str] = {}
    seeds_of: dict[str, set[int]] = {}
    parts: dict[int, tuple[str, dict[str, Any]]] = {}
    for i, r in runs.iterrows():
        if r["family"] != "marl":
            continue
        opts = json.loads(r["options"] or "{}")
        seed = int(opts.pop("seed", 0))
        base = controller_label(r["controller_name"], opts)
        base_labels[i] = base
        parts[i] = (r["controller_name"], opts)
        seeds_of.setdefault(base, set()).add(seed)
        runs.at[i, "train_seed"] = seed
    for i, base in base_labels.items():
        seeds = sorted(seeds_of[base])
        if len(seeds) > 1:
            name, opts = parts[i]
            runs.at[i, "controller"] = controller_label(
                name, {**opts, "seeds": "+".join(str(s) for s in seeds)}
            )
    return runs


def leaderboard_frame(runs: Any, pool_seeds: bool = False, sweeps: Mapping[Any, Any] | None = None,
                      rank_by: str = "reward") -> Any:
    """leaderboard.csv: one row per controller x scenario x vehicles (x V2V and lag settings).

    Means with 95 % seeded bootstrap intervals over the episodes that finished (status ok);
    ``rank`` within each scenario x vehicles x settings: controllers with no collision and no
    failure first, then by mean reward (higher is better), or, with ``rank_by``
    ``string-stability``, first the string-stable ones among them (:data:`RANK_BY`). With
    ``pool_seeds`` the runs of one MARL policy trained with several seeds form one row
    (:func:`pool_training_seeds`) whose interval is a two-stage bootstrap over training seeds,
    then episodes (:func:`benchmark.statistics.hierarchical_bootstrap_ci`); ``n_train_seeds``
    says how many.

    Parameters
    ----------
    sweeps : mapping, optional
        The standard sweep of each run setting (:func:`benchmark.sweep.row_sweeps`: keyed by
        :func:`benchmark.sweep.row_key`, a :class:`benchmark.sweep.SweepResult` or None): adds
        :data:`SWEEP_COLUMNS`. None: no sweep columns.
    rank_by : str
        One of :data:`RANK_BY`.
    """
    import pandas as pd

    if rank_by not in RANK_BY:
        raise ConfigError(f"unknown ranking {rank_by!r}; rank by one of: {', '.join(RANK_BY)}")
    out = []
    if len(runs) == 0:
        return pd.DataFrame(columns=["rank", *GROUP_COLUMNS])
    if sweeps is not None:
        runs = _with_sweeps(runs, sweeps)
    runs = pool_training_seeds(runs) if pool_seeds else runs.assign(train_seed=np.nan)
    for key, grp in runs.groupby(list(GROUP_COLUMNS), sort=True, dropna=False):
        ok = grp[grp["status"] == "ok"]
        row: dict[str, Any] = dict(zip(GROUP_COLUMNS, key, strict=True))
        row["family"] = grp["family"].iloc[0]
        det = ok["deterministic"].dropna()
        row["deterministic"] = bool(det.all()) if len(det) else None
        row["n_episodes"] = int(len(grp))
        row["collisions"] = int(ok["collision"].astype(bool).sum())
        row["failed"] = int((grp["status"] != "ok").sum())
        row["solver_failures"] = int(ok["solver_failures"].fillna(0).sum())
        row["string_stable_frac"] = float(ok["string_stable"].astype(float).mean()) if len(ok) else math.nan
        train_seeds = sorted(set(ok["train_seed"].dropna().astype(int)))
        row["n_train_seeds"] = len(train_seeds) if train_seeds else None
        # one arrangement per row (the label carries it): the share of its automated followers
        shares = (pd.to_numeric(grp["cav_share"], errors="coerce").dropna().tolist()
                  if "cav_share" in grp else [])
        row["cav_share"] = float(shares[0]) if shares else math.nan
        if sweeps is not None:
            row.update(_row_sweep(grp))
        for metric in LEADERBOARD_METRICS:
            if metric not in ok:  # a frame of runs from before the column existed
                vals = np.full(len(ok), np.nan)
            else:
                vals = pd.to_numeric(ok[metric], errors="coerce").to_numpy(dtype=float)
            if metric in UNKNOWN_WHEN_ABSENT and not np.isfinite(vals).all():
                vals = np.full(len(ok), np.nan)  # unknown for some episodes: no mean
            if len(train_seeds) > 1:
                groups = [vals[(ok["train_seed"] == s).to_numpy()] for s in train_seeds]
                mean, lo, hi = hierarchical_bootstrap_ci(groups, seed=BOOTSTRAP_SEED)
            else:
                mean, lo, hi = bootstrap_ci(vals, seed=BOOTSTRAP_SEED)
            row.update({f"{metric}_mean": mean, f"{metric}_ci_low": lo, f"{metric}_ci_high": hi})
        out.append(row)
    lb = pd.DataFrame(out)
    clean = (lb["collisions"] == 0) & (lb["failed"] == 0)
    lb["_clean"] = (~clean).astype(int)
    lb["_reward"] = -lb["reward_mean"].fillna(-np.inf)
    stable = lb["sweep_string_stable"] if "sweep_string_stable" in lb else pd.Series(False, lb.index)
    lb["_unstable"] = (stable != True).astype(int) if rank_by == "string-stability" else 0  # noqa: E712
    setting = ["scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s"]
    lb = lb.sort_values([*setting, "_clean", "_unstable", "_reward", "controller"],
                        kind="mergesort")
    lb["rank"] = lb.groupby(setting, dropna=False).cumcount() + 1
    lb = lb.drop(columns=["_clean", "_unstable", "_reward"])
    lb.attrs["rank_by"] = rank_by
    first = ["rank", "controller", "family", "scenario", "n_vehicles", "n_episodes", "collisions",
             "failed"]
    return lb[first + [c for c in lb.columns if c not in first]].reset_index(drop=True)


def _with_sweeps(runs: Any, sweeps: Mapping[Any, Any]) -> Any:
    """``runs`` with each run's setting's sweep peak and its frequency (NaN: none)."""
    from benchmark.sweep import row_key

    found = [sweeps.get(row_key(r)) for r in runs.to_dict("records")]
    return runs.assign(
        _sweep_peak=[math.nan if f is None else f.peak_gain for f in found],
        _sweep_omega=[math.nan if f is None else f.omega_at_peak_rad_s for f in found])


def _row_sweep(grp: Any) -> dict[str, Any]:
    """A leaderboard row's :data:`SWEEP_COLUMNS`: the largest peak of its runs' settings (a
    pooled row: the worst training seed), unknown if one of them has none."""
    peaks = grp["_sweep_peak"].to_numpy(dtype=float)
    if len(peaks) == 0 or np.isnan(peaks).any():
        return {"sweep_peak_gain": math.nan, "sweep_peak_omega_rad_s": math.nan,
                "sweep_string_stable": None}
    i = int(np.argmax(peaks))
    peak = float(peaks[i])
    return {"sweep_peak_gain": peak,
            "sweep_peak_omega_rad_s": float(grp["_sweep_omega"].to_numpy(dtype=float)[i]),
            "sweep_string_stable": is_string_stable(peak)}


def write_csvs(
    folder: Path, records: list[dict[str, Any]], pool_seeds: bool = False, *,
    rank_by: str = "reward", sweeps: bool = True, executor: str = "serial", workers: int = 1,
    ray_address: str | None = None,
) -> tuple[Path, Path, Any]:
    """Write runs.csv and leaderboard.csv into ``folder``; returns the paths and the leaderboard.

    With ``sweeps`` every leaderboard row carries the standard frequency sweep of its
    configuration (:data:`SWEEP_COLUMNS`): read from the folder's cache
    (:class:`benchmark.sweep.SweepCache`, ``string_sweeps.json``) or measured on ``executor``
    and added to it; a setting without one is named on standard error.

    Refuses (ConfigError) to replace a runs.csv that holds more runs than ``records``: the
    store is the source of truth, and one with fewer runs than its CSV is not the same store.
    """
    runs_path, lb_path = check_csv_targets(folder)
    before = _csv_rows(runs_path)
    if before > len(records):
        raise ConfigError(
            f"{runs_path} lists {before} runs but the store beside it holds {len(records)}; "
            "nothing was overwritten: rerun the sweep with --resume to fill the store, or "
            "choose another --out"
        )
    if rank_by not in RANK_BY:
        raise ConfigError(f"unknown ranking {rank_by!r}; rank by one of: {', '.join(RANK_BY)}")
    found = None
    if sweeps:
        from benchmark.sweep import SweepCache, row_sweeps

        cache = SweepCache(folder)
        found = row_sweeps(records, cache, executor=executor, workers=workers,
                           ray_address=ray_address)
        cache.save()
    runs = runs_frame(records)
    lb = leaderboard_frame(runs, pool_seeds, found, rank_by)
    write_csv(runs, runs_path, float_format="%.10g")
    write_csv(lb, lb_path, float_format="%.10g")
    return runs_path, lb_path, lb


def check_csv_targets(folder: Path) -> tuple[Path, Path]:
    """The paths of runs.csv and leaderboard.csv in ``folder``, refused (ConfigError) where a
    folder of that name stands or runs.csv or the sweep cache is damaged: checked before a sweep runs, so no work
    is done that the CSVs cannot then hold."""
    from benchmark.sweep import SweepCache

    runs_path = folder / "runs.csv"
    lb_path = folder / "leaderboard.csv"
    for path in (runs_path, lb_path):
        _check_file_target(path)
    _csv_rows(runs_path)
    SweepCache(folder)  # a damaged sweep cache is refused now, not after the runs
    return runs_path, lb_path


def _csv_rows(path: Path) -> int:
    """Data rows of a runs.csv (0 if there is none); a damaged one is a ConfigError."""
    import csv

    from infra.files import damaged

    if not path.exists():
        return 0
    try:
        with path.open(newline="", encoding="utf-8") as f:
            return max(sum(1 for _ in csv.reader(f)) - 1, 0)
    except (OSError, ValueError, csv.Error) as exc:
        raise damaged(path, "the runs table", f"not CSV: {exc}",
                      f"remove it (`cacc-bench leaderboard {path.parent}` rebuilds it from "
                      "the store beside it) or restore it") from None


def write_csv(df: Any, path: Path, float_format: str | None = None) -> None:
    """Write a data frame as CSV atomically (a temporary file renamed over ``path``): the one
    CSV writer of every command, so a reader never sees half a file. ``float_format`` as in
    pandas (None: every digit)."""
    from infra.atomic import write_with

    path = Path(path)
    _check_file_target(path)
    write_with(path, lambda tmp: df.to_csv(tmp, index=False, float_format=float_format))


def _check_file_target(path: Path) -> None:
    """Refuse (ConfigError) to write a file where a folder of that name stands."""
    if path.is_dir():
        raise ConfigError(f"{path} is a folder, so the file cannot be written there; move that "
                          "folder away or write the results elsewhere")


def trajectory_arrays(traj: Trajectory) -> dict[str, np.ndarray]:
    """The arrays of a trajectory that the store keeps for figures and CSVs (``ring`` only for
    a ring road's run, so every other stored trajectory is as before it existed)."""
    arrays = {k: getattr(traj, k) for k in ("gap_m", "speed_mps", "accel_mps2", "power_kw",
                                            "leader_speed_mps", "leader_accel_mps2")}
    arrays["dt_s"] = np.array(traj.dt_s)
    if traj.ring:
        arrays["ring"] = np.array(True)
    return arrays


def positions_m(arrays: dict[str, np.ndarray], ring: bool | None = None) -> np.ndarray:
    """Positions along the road (m) of the leader and every follower, ``(T+1, N+1)``, column 0
    the leader: the leader's at row 0 is 0 m, its later ones the trapezoidal integral of its
    speed, and each follower stands its gap (plus the vehicle length on a ring, where gaps are
    bumper to bumper) behind its predecessor. The env moves gaps by the same trapezoid
    (:func:`envs.dynamics.physics_step`), so these positions are each vehicle's own trapezoidal
    integral of its speed too (to rounding).

    On a ring there is no leader: column 0 is follower N one lap ahead (``leader_speed_mps``
    holds its speed), so ``x_0 - x_N`` is the ring's length.

    Parameters
    ----------
    arrays : dict
        :func:`trajectory_arrays` (``gap_m``, ``leader_speed_mps``, ``dt_s``; ``ring`` read when
        ``ring`` is None).
    ring : bool or None
        Whether the run was on a ring road (None: the arrays' ``ring``, absent = False).
    """
    from envs.scenarios import RING_VEHICLE_LENGTH_M

    gap = np.asarray(arrays["gap_m"], dtype=np.float64)
    t1 = gap.shape[0]
    dt = float(arrays["dt_s"])
    lead = np.asarray(arrays["leader_speed_mps"], dtype=np.float64)[:t1]
    if ring is None:
        ring = bool(arrays.get("ring", False))
    x = np.empty((t1, gap.shape[1] + 1))
    x[0, 0] = 0.0
    x[1:, 0] = np.cumsum((lead[1:] + lead[:-1]) * (dt / 2))
    spacing = gap + (RING_VEHICLE_LENGTH_M if ring else 0.0)
    x[:, 1:] = x[:, :1] - np.cumsum(spacing, axis=1)
    return x


#: The columns of a trajectory CSV (:func:`write_trajectory_csv`), in order.
TRAJECTORY_CSV_COLUMNS: tuple[str, ...] = (
    "step", "time_s", "vehicle", "gap_m", "speed_mps", "accel_mps2", "power_kw", "position_m")


def read_trajectory_csv(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a trajectory CSV (:func:`write_trajectory_csv`), to its six decimals: what
    ``plot`` draws for the seeds whose trajectory the store does not keep.

    Raises
    ------
    ConfigError
        The file is not such a CSV (columns, a full step x vehicle grid, finite numbers).
    """
    import pandas as pd

    from infra.files import damaged

    fix = "write it again (`cacc-bench run --trajectories` into a new --out), or remove it"
    try:
        df = pd.read_csv(path)
    except (OSError, ValueError, pd.errors.ParserError) as exc:
        raise damaged(path, "the trajectory CSV", f"{type(exc).__name__}: {exc}", fix) from None
    need = [c for c in TRAJECTORY_CSV_COLUMNS if c != "position_m"]  # older files lack it
    missing = [c for c in need if c not in df.columns]
    if missing:
        raise damaged(path, "the trajectory CSV", f"no column {', '.join(missing)}", fix)
    steps = int(df["step"].max()) + 1 if len(df) else 0
    vehicles = int(df["vehicle"].max()) + 1 if len(df) else 0
    df = df.sort_values(["step", "vehicle"], kind="mergesort")
    grid = (df["step"].to_numpy() == np.repeat(np.arange(steps), vehicles)).all() if (
        len(df) == steps * vehicles) else False
    if steps < 2 or vehicles < 2 or not grid:
        raise damaged(path, "the trajectory CSV", "not one row per step and vehicle "
                      "(steps 0.., vehicle 0 the leader)", fix)

    def table(col: str) -> np.ndarray:
        return df[col].to_numpy(dtype=np.float64).reshape(steps, vehicles)

    arrays = {k: table(k)[:, 1:] for k in ("gap_m", "speed_mps", "accel_mps2", "power_kw")}
    if not all(np.isfinite(v).all() for v in arrays.values()):
        raise damaged(path, "the trajectory CSV", "a follower's value is empty or not finite", fix)
    arrays["leader_speed_mps"] = table("speed_mps")[:, 0]
    arrays["leader_accel_mps2"] = table("accel_mps2")[:, 0]
    arrays["dt_s"] = np.array(float(df["time_s"].iloc[vehicles] - df["time_s"].iloc[0]))
    return arrays


def write_trajectory_csv(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Long-format trajectory CSV: ``step, time_s, vehicle, gap_m, speed_mps, accel_mps2,
    power_kw, position_m``.

    Vehicle 0 is the leader (gap empty; its power from the same polynomial); ``accel_mps2`` is the
    applied acceleration of the step that led to the row (0 at step 0); ``position_m`` the
    position along the road (:func:`positions_m`: the leader at 0 m at step 0).
    """
    import pandas as pd

    from envs.energy import battery_power_kw

    gap = arrays["gap_m"]
    t1, n = gap.shape
    dt = float(arrays["dt_s"])
    lead_v = arrays["leader_speed_mps"][:t1]
    lead_a = arrays["leader_accel_mps2"][:t1]
    lead_p = np.asarray(battery_power_kw(lead_v, lead_a))
    lead_p = np.where(np.arange(t1) == 0, 0.0, lead_p)
    # (T+1, N+1) tables, column 0 the leader's
    cols = {"gap_m": np.column_stack([np.full(t1, np.nan), gap]),
            "speed_mps": np.column_stack([lead_v, arrays["speed_mps"]]),
            "accel_mps2": np.column_stack([lead_a, arrays["accel_mps2"]]),
            "power_kw": np.column_stack([lead_p, arrays["power_kw"]]),
            "position_m": positions_m(arrays)}
    steps = np.arange(t1)
    df = pd.concat(pd.DataFrame({"step": steps, "time_s": steps * dt, "vehicle": i,
                                 **{k: v[:, i] for k, v in cols.items()}})
                   for i in range(n + 1)).sort_values(["step", "vehicle"], kind="mergesort")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_csv(df, path, float_format="%.6f")
