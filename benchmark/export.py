"""CSV files of a results folder, rebuilt from the store: runs.csv, leaderboard.csv, trajectories."""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np

from benchmark.rollout import Trajectory
from benchmark.statistics import bootstrap_ci, hierarchical_bootstrap_ci
from benchmark.suite import KEY_COLUMNS
from infra.errors import ConfigError

#: The mixed-traffic columns of runs.csv (:func:`benchmark.metrics.mixed_traffic_metrics`).
MIXED_COLUMNS: tuple[str, ...] = (
    "cav_share", "head_to_tail_gain", "speed_std_last_mps", "speed_std_humans_mps",
    "braking_events", "braking_events_humans", "braking_events_cavs", "braking_events_per_veh_h",
    "energy_humans_kwh", "energy_cavs_kwh", "controllable_energy_humans_kwh",
    "controllable_energy_cavs_kwh",
)

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
)

GROUP_COLUMNS: tuple[str, ...] = (
    "controller", "scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s",
)

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


def leaderboard_frame(runs: Any, pool_seeds: bool = False) -> Any:
    """leaderboard.csv: one row per controller x scenario x vehicles (x V2V and lag settings).

    Means with 95 % seeded bootstrap intervals over the episodes that finished (status ok);
    ``rank`` within each scenario x vehicles x settings: controllers with no collision and no
    failure first, then by mean reward (higher is better). With ``pool_seeds`` the runs of one
    MARL policy trained with several seeds form one row (:func:`pool_training_seeds`) whose
    interval is a two-stage bootstrap over training seeds, then episodes
    (:func:`benchmark.statistics.hierarchical_bootstrap_ci`); ``n_train_seeds`` says how many.
    """
    import pandas as pd

    out = []
    if len(runs) == 0:
        return pd.DataFrame(columns=["rank", *GROUP_COLUMNS])
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
            row[f"{metric}_mean"] = mean
            row[f"{metric}_ci_low"] = lo
            row[f"{metric}_ci_high"] = hi
        out.append(row)
    lb = pd.DataFrame(out)
    clean = (lb["collisions"] == 0) & (lb["failed"] == 0)
    lb["_clean"] = (~clean).astype(int)
    lb["_reward"] = -lb["reward_mean"].fillna(-np.inf)
    setting = ["scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s"]
    lb = lb.sort_values([*setting, "_clean", "_reward", "controller"], kind="mergesort")
    lb["rank"] = lb.groupby(setting, dropna=False).cumcount() + 1
    lb = lb.drop(columns=["_clean", "_reward"])
    first = ["rank", "controller", "family", "scenario", "n_vehicles", "n_episodes", "collisions",
             "failed"]
    return lb[first + [c for c in lb.columns if c not in first]].reset_index(drop=True)


def write_csvs(
    folder: Path, records: list[dict[str, Any]], pool_seeds: bool = False
) -> tuple[Path, Path, Any]:
    """Write runs.csv and leaderboard.csv into ``folder``; returns the paths and the leaderboard.

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
    runs = runs_frame(records)
    lb = leaderboard_frame(runs, pool_seeds)
    write_csv(runs, runs_path, float_format="%.10g")
    write_csv(lb, lb_path, float_format="%.10g")
    return runs_path, lb_path, lb


def check_csv_targets(folder: Path) -> tuple[Path, Path]:
    """The paths of runs.csv and leaderboard.csv in ``folder``, refused (ConfigError) where a
    folder of that name stands or runs.csv is damaged: checked before a sweep runs, so no work
    is done that the CSVs cannot then hold."""
    runs_path = folder / "runs.csv"
    lb_path = folder / "leaderboard.csv"
    for path in (runs_path, lb_path):
        _check_file_target(path)
    _csv_rows(runs_path)
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
    """The arrays of a trajectory that the store keeps for figures and CSVs."""
    return {
        "gap_m": traj.gap_m,
        "speed_mps": traj.speed_mps,
        "accel_mps2": traj.accel_mps2,
        "power_kw": traj.power_kw,
        "leader_speed_mps": traj.leader_speed_mps,
        "leader_accel_mps2": traj.leader_accel_mps2,
        "dt_s": np.array(traj.dt_s),
    }


def write_trajectory_csv(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Long-format trajectory CSV: ``step, time_s, vehicle, gap_m, speed_mps, accel_mps2, power_kw``.

    Vehicle 0 is the leader (gap empty; its power from the same polynomial); ``accel_mps2`` is the
    applied acceleration of the step that led to the row (0 at step 0).
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
    steps = np.arange(t1)
    frames = [
        pd.DataFrame({
            "step": steps, "time_s": steps * dt, "vehicle": 0, "gap_m": np.nan,
            "speed_mps": lead_v, "accel_mps2": lead_a, "power_kw": lead_p,
        })
    ]
    for i in range(n):
        frames.append(pd.DataFrame({
            "step": steps, "time_s": steps * dt, "vehicle": i + 1, "gap_m": gap[:, i],
            "speed_mps": arrays["speed_mps"][:, i], "accel_mps2": arrays["accel_mps2"][:, i],
            "power_kw": arrays["power_kw"][:, i],
        }))
    df = pd.concat(frames).sort_values(["step", "vehicle"], kind="mergesort")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_csv(df, path, float_format="%.6f")
