"""Metrics of one run, from its trajectory (see ``docs/spec/benchmark.md`` for the definitions).

Statistics are over followers and steps (rows 1..T, the states after each step) unless named
otherwise. The reward columns are the environment's own per-step rewards, so the reward is
computed in one place only.
"""

from __future__ import annotations

import math

import numpy as np

from benchmark.rollout import Trajectory
from benchmark.string_gain import is_string_stable, spacing_string_gain, time_domain_string_gain
from controllers.base import SpacingPolicy

#: Columns of runs.csv that hold measured times (they differ between identical reruns).
TIMING_COLUMNS: tuple[str, ...] = (
    "compute_ms_p50",
    "compute_ms_p95",
    "compute_ms_p99",
    "compute_ms_first",
    "wall_s",
)

#: Steps of the start-up transient: the first step carries the initial-condition transient
#: (slowdown-v1's published speed clip "decelerates" every follower at about -10.6 m/s^2 at
#: step 1: its initial speeds above ``speed_max`` are clipped), which says nothing about how the
#: controller propagates disturbances or how smoothly it drives. It is left out of the string
#: gains and of ``jerk_rms_after_start_mps3`` (``jerk_rms_mps3`` keeps it, as published), and
#: ``plot`` shades it (``docs/concepts/metrics.md``).
START_TRANSIENT_STEPS = 1
#: The first step is left out of the string gains (:data:`START_TRANSIENT_STEPS`).
STRING_GAIN_SKIP_STEPS = START_TRANSIENT_STEPS

#: A braking event begins where a vehicle's applied acceleration falls below minus this
#: (m/s^2). Ours (Stern et al. 2018 count braking events on their ring but the threshold they
#: used could not be checked here): the IDM humans' maximum acceleration, two thirds of their
#: comfortable deceleration b = 1.5 m/s^2 (``docs/concepts/metrics.md#mixed-traffic``).
BRAKING_THRESHOLD_MPS2 = 1.0
#: After an event a vehicle must come back to an acceleration of at least
#: ``-(BRAKING_THRESHOLD_MPS2 - BRAKING_REARM_MPS2)`` before its next event counts: 2.5 standard
#: deviations of the humans' per-step acceleration noise (0.2 m/s^2), so that noise around the
#: threshold does not count one braking as several.
BRAKING_REARM_MPS2 = 0.5
#: A head whose speed swings less than this (std, m/s) has no swing to compare the tail's with:
#: ``head_to_tail_gain`` is NaN there (a constant-speed leader).
HEAD_TO_TAIL_MIN_STD_MPS = 1e-6


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
    return float(_cruise_kwh(float(traj.speed_mps[1:].sum() * traj.dt_s), v_bar_mps))


def _cruise_kwh(distance_m: float | np.ndarray, v_bar_mps: float) -> float | np.ndarray:
    """Battery energy (kWh) of ``distance_m`` driven at steady cruise at ``v_bar_mps`` > 0:
    ``P(v_bar, 0) d / v_bar`` (the one formula of the controllable energy, whole string or per
    seat)."""
    from envs.energy import battery_power_kw

    cruise_kw = float(battery_power_kw(v_bar_mps, 0.0))
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


def braking_onsets(accel_mps2: np.ndarray, threshold_mps2: float = BRAKING_THRESHOLD_MPS2,
                   rearm_mps2: float = BRAKING_REARM_MPS2) -> np.ndarray:
    """Braking events of each vehicle: onsets of braking harder than ``threshold_mps2``.

    A row ``t >= 1`` is an onset where ``a[t] < -threshold_mps2`` and the vehicle was not braking
    after row ``t - 1``. A vehicle is braking from an onset until its acceleration comes back to
    ``a >= -threshold_mps2 + rearm_mps2`` (hysteresis; with ``rearm_mps2 = 0`` every crossing of
    the threshold from above is an onset). Row 0 is the row before the window: the vehicle starts
    braking there if ``a[0] < -threshold_mps2`` (that braking is no onset of the window).

    Parameters
    ----------
    accel_mps2 : (R, N) array
        Applied accelerations, row 0 the row before the counted rows ``1 .. R-1``.
    threshold_mps2, rearm_mps2 : float
        Non-negative (m/s^2), ``rearm_mps2 <= threshold_mps2``.

    Returns
    -------
    (N,) int array
        Onsets of each vehicle in rows ``1 .. R-1`` (0 for ``R <= 1``).
    """
    a = np.asarray(accel_mps2, dtype=np.float64)
    if a.shape[0] <= 1:
        return np.zeros(a.shape[1:], dtype=np.int64)
    below = a < -threshold_mps2
    above = a >= -threshold_mps2 + rearm_mps2
    above[0] = ~below[0]  # row 0 decides the state the window starts in
    rows = np.arange(a.shape[0]).reshape(-1, *([1] * (a.ndim - 1)))
    last_below = np.maximum.accumulate(np.where(below, rows, -1), axis=0)
    last_above = np.maximum.accumulate(np.where(above, rows, -1), axis=0)
    braking = last_below > last_above  # the state after each row
    return np.asarray((below[1:] & ~braking[:-1]).sum(axis=0), dtype=np.int64)


def mixed_traffic_metrics(traj: Trajectory) -> dict[str, float | int]:
    """The mixed-traffic columns of ``runs.csv``: over the whole string, humans included.

    Every statistic is over the rows after the settle time, ``k + 1 .. T`` with ``k =
    traj.settle_steps`` (rows ``1 .. T``, those of the other metrics, where ``k = 0``). A sum
    over an empty group (no human seat, no automated seat) is 0; a mean or a ratio over one, or
    a statistic over no row, is NaN. Definitions and sources: ``docs/concepts/metrics.md``.

    Parameters
    ----------
    traj : Trajectory
        One run; ``traj.automated`` None reads as every seat automated.

    Returns
    -------
    dict
        ``cav_share``; ``head_to_tail_gain`` (std over time of the last follower's speed over
        the first vehicle's: the leader, or follower 1 on a ring); ``speed_std_last_mps``,
        ``speed_std_humans_mps`` (mean over human seats of the std over time of each one's
        speed); ``braking_events`` and its split ``braking_events_humans``,
        ``braking_events_cavs`` (counts of :func:`braking_onsets`), ``braking_events_per_veh_h``
        (all followers, per vehicle per hour of the window); ``energy_humans_kwh``,
        ``energy_cavs_kwh`` (battery energy of each group over the window),
        ``controllable_energy_humans_kwh``, ``controllable_energy_cavs_kwh`` (each group's
        energy above steady cruise at the mean of ``leader_speed_mps`` over the window).
    """
    n = traj.speed_mps.shape[1]
    auto = (np.ones(n, dtype=bool) if traj.automated is None
            else np.asarray(traj.automated, dtype=bool).reshape(n))
    human = ~auto
    k = max(int(traj.settle_steps), 0)
    rows = slice(k + 1, traj.steps + 1)
    v = traj.speed_mps[rows]
    t_rows = v.shape[0]
    dt = traj.dt_s
    nan = math.nan
    head = traj.speed_mps[rows, 0] if traj.ring else traj.leader_speed_mps[rows]
    if t_rows:
        std_each = v.std(axis=0)
        std_head = float(np.std(head))
        std_last = float(std_each[-1])
        gain = std_last / std_head if std_head >= HEAD_TO_TAIL_MIN_STD_MPS else nan
        std_humans = float(std_each[human].mean()) if human.any() else nan
    else:
        std_last = gain = std_humans = nan
    events = braking_onsets(traj.accel_mps2[min(k, traj.steps) : traj.steps + 1])
    hours = t_rows * dt / 3600.0
    energy_each = traj.power_kw[rows].sum(axis=0) * dt / 3600.0  # (N,) kWh
    lead_mean = float(np.mean(traj.leader_speed_mps[rows])) if t_rows else nan
    if t_rows and lead_mean > 0.0:
        controllable_each = energy_each - _cruise_kwh(v.sum(axis=0) * dt, lead_mean)
    else:  # no row (a sum of nothing) or a still leader (steady cruise costs nothing per metre)
        controllable_each = np.full(n, 0.0 if not t_rows else nan)

    def group_sum(x: np.ndarray, seats: np.ndarray) -> float:
        return float(x[seats].sum()) if seats.any() else 0.0

    return {
        "cav_share": float(auto.mean()),
        "head_to_tail_gain": gain,
        "speed_std_last_mps": std_last,
        "speed_std_humans_mps": std_humans,
        "braking_events": int(events.sum()),
        "braking_events_humans": int(events[human].sum()),
        "braking_events_cavs": int(events[auto].sum()),
        "braking_events_per_veh_h": float(events.sum()) / (n * hours) if hours > 0 else nan,
        "energy_humans_kwh": group_sum(energy_each, human),
        "energy_cavs_kwh": group_sum(energy_each, auto),
        "controllable_energy_humans_kwh": group_sum(controllable_each, human),
        "controllable_energy_cavs_kwh": group_sum(controllable_each, auto),
    }


def class_energy_columns() -> tuple[str, ...]:
    """The per-class energy columns of ``runs.csv``: ``energy_kwh_per_100km_<class>`` for every
    registered class (:data:`envs.vehicle_classes.VEHICLE_CLASSES`), then
    ``energy_drag_saving``, the drag-saving model the power used."""
    from envs.vehicle_classes import VEHICLE_CLASSES

    return (*(f"energy_kwh_per_100km_{c}" for c in VEHICLE_CLASSES), "energy_drag_saving")


def class_energy_metrics(traj: Trajectory) -> dict[str, float | str]:
    """Energy per vehicle class (:func:`class_energy_columns`): each class's battery energy over
    its vehicles' distance, kWh/100 km, over rows 1..T as ``energy_kwh_per_100km`` (the
    string's: every follower's energy over every follower's distance, per vehicle). NaN for a
    class not in the string, and for every class in the homogeneous platoon (no classes)."""
    out: dict[str, float | str] = {c: math.nan for c in class_energy_columns()}
    out["energy_drag_saving"] = traj.drag_saving
    if traj.vehicle_classes is None or traj.steps == 0:
        return out
    names = np.array(traj.vehicle_classes)
    energy_kwh = traj.power_kw[1:].sum(axis=0) * traj.dt_s / 3600.0  # (N,)
    distance_km = traj.speed_mps[1:].sum(axis=0) * traj.dt_s / 1000.0
    for name in dict.fromkeys(traj.vehicle_classes):
        seats = names == name
        km = float(distance_km[seats].sum())
        out[f"energy_kwh_per_100km_{name}"] = (float(energy_kwh[seats].sum()) / km * 100.0
                                               if km > 0 else math.nan)
    return out


def jerk_rms_after_start_mps3(traj: Trajectory) -> float:
    """RMS jerk (m/s^3) of the accelerations after the start-up transient: the jerks between
    rows ``1 + START_TRANSIENT_STEPS .. T`` (``jerk_rms_mps3`` starts one row earlier, at row 1,
    whose acceleration is the transient's). 0 when fewer than two such rows exist."""
    first = 1 + START_TRANSIENT_STEPS
    a = traj.accel_mps2[first : traj.steps + 1]
    if a.shape[0] < 2:
        return 0.0
    jerk = np.diff(a, axis=0) / traj.dt_s
    return float(np.sqrt(np.mean(np.square(jerk))))


def gap_rmse_own_policy_m(traj: Trajectory, target_gap_m: float,
                          spacing: SpacingPolicy | None) -> float:
    """Gap RMSE (m) against the gap the controller aims at: its own constant time-gap policy
    ``r + h v`` (each follower's own speed, row by row) where it has one, else the scenario's
    constant ``target_gap_m`` (then it equals ``gap_rmse_m``). Rows 1..T as ``gap_rmse_m``."""
    rows = slice(1, None) if traj.steps else slice(None)
    gap = traj.gap_m[rows]
    target = target_gap_m if spacing is None else spacing.target_gap_m(traj.speed_mps[rows])
    return float(np.sqrt(np.mean(np.square(gap - target))))


def run_metrics(
    traj: Trajectory, target_gap_m: float, target_speed_mps: float,
    spacing: SpacingPolicy | None = None,
) -> dict[str, float | int | bool | str]:
    """All per-run metrics of ``runs.csv`` that come from the trajectory (the mixed-traffic ones
    from :func:`mixed_traffic_metrics`, after the trajectory's ``settle_steps``); ``spacing``:
    the controller's own spacing policy (:meth:`controllers.base.Controller.spacing_policy`),
    for ``gap_rmse_own_policy_m``."""
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
        "string_stable": is_string_stable(gain),
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
        # the gap against the controller's own spacing policy (gap_rmse_m: the reward's target)
        "gap_rmse_own_policy_m": gap_rmse_own_policy_m(traj, target_gap_m, spacing),
        # jerk without the start-up transient (jerk_rms_mps3 keeps it, as published)
        "jerk_rms_after_start_mps3": jerk_rms_after_start_mps3(traj),
        # mixed traffic: the whole string, humans included, after the settle time
        **mixed_traffic_metrics(traj),
        # energy per vehicle class, and the drag-saving model used (docs/vehicle-classes.md)
        **class_energy_metrics(traj),
    }
