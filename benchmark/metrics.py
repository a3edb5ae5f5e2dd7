"""Metrics of one run, from its trajectory (see ``docs/spec/benchmark.md`` for the definitions).

Statistics are over followers and steps (rows 1..T, the states after each step) unless named
otherwise. The reward columns are the environment's own per-step rewards, so the reward is
computed in one place only.
"""

from __future__ import annotations

import math

import numpy as np

from benchmark.rollout import Trajectory
from benchmark.string_gain import STRING_GAIN_TOL, spacing_string_gain, time_domain_string_gain

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


def cruise_energy_kwh(traj: Trajectory) -> float:
    """Battery energy (kWh) of the followers' distances driven at steady cruise at the leader's
    mean speed: ``P(v_bar, 0) * (sum_i d_i) / v_bar``.

    ``v_bar`` is the mean of the leader's speed over rows 1..T (the rows the other metrics use),
    ``d_i = sum_t v_i[t] dt`` the distance follower ``i`` drove over the same rows (the distance
    of ``energy_kwh_per_100km``), ``P`` the fitted power model of the environment (the shipped
    polynomial, :func:`envs.energy.battery_power_kw`). See ``docs/controllable-energy.md``.

    Parameters
    ----------
    traj : Trajectory
        One run.

    Returns
    -------
    float
        0 for a run of no step (no distance); NaN when the leader's mean speed is not positive
        (steady cruise has no cost per metre there).
    """
    if traj.steps == 0:
        return 0.0
    v_bar_mps = float(np.mean(traj.leader_speed_mps[1 : traj.steps + 1]))
    if not v_bar_mps > 0.0:
        return math.nan
    from envs.energy import battery_power_kw

    cruise_kw = float(battery_power_kw(v_bar_mps, 0.0))
    distance_m = float(traj.speed_mps[1:].sum() * traj.dt_s)
    return cruise_kw * (distance_m / v_bar_mps) / 3600.0


def controllable_energy_kwh(traj: Trajectory) -> float:
    """The followers' battery energy above :func:`cruise_energy_kwh` (kWh): what a controller can
    change. 0 for a platoon that cruises exactly at the leader's constant speed; negative when
    the followers used less than cruising their distances would cost (regeneration on a net
    descent in speed, or a distance driven below the leader's speed). See
    ``docs/controllable-energy.md``.

    Parameters
    ----------
    traj : Trajectory
        One run.

    Returns
    -------
    float
        NaN when :func:`cruise_energy_kwh` is.
    """
    p = traj.power_kw[1:] if traj.steps else traj.power_kw
    return float(p.sum() * traj.dt_s / 3600.0) - cruise_energy_kwh(traj)


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
    controllable_kwh = controllable_energy_kwh(traj)
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
        # the energy above steady cruise at the leader's mean speed (docs/controllable-energy.md)
        "controllable_energy_kwh": controllable_kwh,
        "controllable_energy_kwh_per_100km": ((controllable_kwh / n) / distance_km * 100.0
                                              if distance_km > 0 else math.nan),
    }
