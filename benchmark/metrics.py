"""Metrics of one run, from its trajectory (see ``docs/spec/benchmark.md`` for the definitions).

Statistics are over followers and steps (rows 1..T, the states after each step) unless named
otherwise. The reward columns are the environment's own per-step rewards, so the reward is
computed in one place only.
"""

from __future__ import annotations

import math

import numpy as np

from analysis.stability import STRING_GAIN_TOL, spacing_string_gain, time_domain_string_gain
from benchmark.rollout import Trajectory

#: Columns of runs.csv that hold measured times (they differ between identical reruns).
TIMING_COLUMNS: tuple[str, ...] = (
    "compute_ms_p50",
    "compute_ms_p95",
    "compute_ms_p99",
    "compute_ms_first",
    "wall_s",
)

#: The first step is left out of the string gains: it carries the initial-condition transient
#: (slowdown-v1's published speed clip "decelerates" every follower at tens of m/s^2 at step 1),
#: which says nothing about how the controller propagates disturbances.
STRING_GAIN_SKIP_STEPS = 1


def _percentiles(x: np.ndarray, qs: tuple[float, ...]) -> list[float]:
    """Percentiles ``qs`` of ``x`` (one sort; NaN for an empty ``x``)."""
    if not x.size:
        return [math.nan] * len(qs)
    return [float(v) for v in np.percentile(x, qs)]


def run_metrics(
    traj: Trajectory, target_gap_m: float, target_speed_mps: float
) -> dict[str, float | int | bool]:
    """All per-run metrics of ``runs.csv`` that come from the trajectory."""
    n = traj.gap_m.shape[1]
    dt = traj.dt_s
    steps = traj.steps
    gap = traj.gap_m[1:]
    v = traj.speed_mps[1:]
    a = traj.accel_mps2[1:]
    p = traj.power_kw[1:]
    if steps == 0:
        gap, v, a, p = traj.gap_m, traj.speed_mps, traj.accel_mps2, traj.power_kw
    jerk = np.diff(traj.accel_mps2, axis=0)[1:] / dt if steps > 1 else np.zeros((1, n))
    energy_kwh = float(p.sum() * dt / 3600.0)
    distance_km = float(traj.speed_mps[1:].sum() * dt / 1000.0) / n if steps else 0.0
    per_step_ms = traj.compute_s * 1000.0 / n
    rest = per_step_ms[1:]
    skip = 1 + STRING_GAIN_SKIP_STEPS
    all_accel = np.concatenate([traj.leader_accel_mps2[:, None], traj.accel_mps2], axis=1)
    gain = float(time_domain_string_gain(all_accel[skip:]))
    spacing_gain = float(spacing_string_gain(traj.gap_m[skip:] - target_gap_m))
    return {
        "steps": steps,
        "collision": bool(traj.collided),
        "min_gap_m": float(traj.gap_m.min()),
        "gap_mean_m": float(gap.mean()),
        "gap_std_m": float(gap.std()),
        "gap_rmse_m": float(np.sqrt(np.mean(np.square(gap - target_gap_m)))),
        "speed_mean_mps": float(v.mean()),
        "speed_std_mps": float(v.std()),
        "speed_rmse_mps": float(np.sqrt(np.mean(np.square(v - target_speed_mps)))),
        "accel_mean_mps2": float(a.mean()),
        "accel_std_mps2": float(a.std()),
        "accel_rms_mps2": float(np.sqrt(np.mean(np.square(a)))),
        "jerk_rms_mps3": float(np.sqrt(np.mean(np.square(jerk)))),
        "energy_kwh": energy_kwh,
        "power_mean_kw": float(p.sum(axis=1).mean()),
        "energy_kwh_per_100km": (energy_kwh / n) / distance_km * 100.0 if distance_km > 0 else math.nan,
        "reward": float(traj.reward.mean()) if steps else math.nan,
        "tracking_reward": float(traj.tracking_reward.mean()) if steps else math.nan,
        "string_gain": gain,
        "string_stable": bool(gain <= 1.0 + STRING_GAIN_TOL) if math.isfinite(gain) else False,
        "spacing_string_gain": spacing_gain,
        **dict(zip(("compute_ms_p50", "compute_ms_p95", "compute_ms_p99"),
                   _percentiles(rest, (50, 95, 99)), strict=True)),
        "compute_ms_first": float(per_step_ms[0]) if steps else math.nan,
        "solver_failures": int(traj.solver_failures),
        "comm_bits_per_s": float(traj.bits_sent / (n * steps * dt)) if steps else 0.0,
        # the safety filter (safe:<controller>): fraction of follower-steps it changed, and its
        # mean correction over all follower-steps (m/s^2); 0 for an unfiltered controller
        "safety_interventions": traj.safety_interventions / (n * steps) if steps else 0.0,
        "safety_correction_mps2": traj.safety_correction_mps2 / (n * steps) if steps else 0.0,
    }
