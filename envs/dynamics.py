"""Pure, batched step functions of the platoon (no RNG, no I/O).

Shapes: ``B`` parallel episodes, ``N`` followers. Index 0 of the platoon is the leader, which is
not part of the follower arrays: follower arrays are ``(B, N)``, per-episode arrays ``(B,)``.
Every function here follows ``docs/spec/environment.md`` exactly, quirks included.
"""

from __future__ import annotations

import numpy as np

from envs.params import OVM_ACTIONS, PlatoonParams, RewardWeights
from envs.vehicle_classes import VehicleArrays

FloatArray = np.ndarray


#: Floats in one vehicle's observation block (published).
BLOCK_DIM: int = 5
#: Floats in an agent's observation: its own block, its front and rear neighbours' blocks.
OBS_DIM: int = 3 * BLOCK_DIM


def ovm_speed_mps(gap_m: FloatArray, params: PlatoonParams = PlatoonParams()) -> FloatArray:
    """Optimal velocity ``V(gap)`` of the OVM, in m/s.

    ``0`` below ``gap_stop``, ``v_max/2 (1 - cos(pi (gap - gap_stop) / (gap_go - gap_stop)))`` in
    between, ``v_max`` above ``gap_go`` (``v_max`` = 30 m/s). ``V(20) = 15``.
    """
    span = params.gap_go_m - params.gap_stop_m
    g = np.clip(gap_m, params.gap_stop_m, params.gap_go_m)
    if np.ndim(g) == 0:
        return params.ovm_speed_max_mps / 2 * (1 - np.cos(np.pi * (g - params.gap_stop_m) / span))
    g -= params.gap_stop_m
    g *= np.pi / span
    np.cos(g, out=g)
    # v_max/2 * (1 - cos)
    g *= -params.ovm_speed_max_mps / 2
    g += params.ovm_speed_max_mps / 2
    return g


def ovm_command_mps2(
    gap_m: FloatArray,
    speed_mps: FloatArray,
    pred_speed_mps: FloatArray,
    alpha: FloatArray | float,
    beta: FloatArray | float,
    params: PlatoonParams = PlatoonParams(),
) -> FloatArray:
    """OVM car-following command ``alpha (V(gap) - v) + beta (v_pred - v)`` (unclipped), m/s^2."""
    u = ovm_speed_mps(gap_m, params)
    u -= speed_mps
    u *= alpha
    u += beta * (pred_speed_mps - speed_mps)
    return u


_ALPHA = np.array([a for a, _ in OVM_ACTIONS])
_BETA = np.array([b for _, b in OVM_ACTIONS])


def action_to_command_mps2(
    action: np.ndarray,
    gap_m: FloatArray,
    speed_mps: FloatArray,
    pred_speed_mps: FloatArray,
    params: PlatoonParams = PlatoonParams(),
) -> FloatArray:
    """Map discrete MARL actions ``(B, N)`` in {0, 1, 2, 3} to OVM commands (published)."""
    action = np.asarray(action)
    if action.size and (action.min() < 0 or action.max() >= len(OVM_ACTIONS)):
        raise ValueError(f"actions must be in 0..{len(OVM_ACTIONS) - 1}")
    return ovm_command_mps2(gap_m, speed_mps, pred_speed_mps, _ALPHA[action], _BETA[action], params)


def predecessor_speed_mps(leader_speed_mps: FloatArray, speed_mps: FloatArray,
                          ring: bool = False) -> FloatArray:
    """Speed of each follower's predecessor ``(B, N)``: the leader for follower 1 (on a ring,
    follower N)."""
    out = np.empty_like(speed_mps)
    out[:, 0] = speed_mps[:, -1] if ring else leader_speed_mps
    out[:, 1:] = speed_mps[:, :-1]
    return out


def physics_step(
    gap_m: FloatArray,
    speed_mps: FloatArray,
    realised_accel_mps2: FloatArray,
    command_mps2: FloatArray,
    leader_speed_mps: FloatArray,
    leader_speed_next_mps: FloatArray,
    params: PlatoonParams = PlatoonParams(),
    ring: bool = False,
    vehicles: VehicleArrays | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Advance all followers by one step ``dt`` from the current state (published rules).

    Parameters
    ----------
    gap_m, speed_mps, realised_accel_mps2 : (B, N)
        Current gaps, speeds and (with actuator lag) realised accelerations.
    command_mps2 : (B, N)
        Acceleration commands; clipped to the bounds here.
    leader_speed_mps, leader_speed_next_mps : (B,)
        Leader speed at steps t and t+1 (ignored on a ring).
    ring : bool
        A ring road: follower 1's predecessor is follower N (its speeds at t and t+1 take the
        leader's place), so the gaps sum to the same length at every step.
    vehicles : VehicleArrays, optional
        Per-vehicle lags and bounds of a heterogeneous string (:mod:`envs.vehicle_classes`);
        None (the default): the run-wide ones of ``params``, by the unchanged homogeneous code.

    Returns
    -------
    gap_next_m, speed_next_mps, realised_next_mps2, applied_accel_mps2 : (B, N)
        ``applied = (v_next - v)/dt`` is what the reward and metrics see (speed clipping can make
        it exceed the command bounds).
    """
    dt = params.dt_s
    if vehicles is not None:  # per vehicle: the same operations, (N,) rows broadcast over B
        u = np.clip(command_mps2, vehicles.accel_min_mps2, vehicles.accel_max_mps2)
        a = np.where(vehicles.has_lag,
                     realised_accel_mps2 + (u - realised_accel_mps2) * vehicles.lag_gain, u)
    elif params.lag_s > 0:
        u = np.clip(command_mps2, params.accel_min_mps2, params.accel_max_mps2)
        a = realised_accel_mps2 + (u - realised_accel_mps2) * params.lag_gain
    else:
        a = np.clip(command_mps2, params.accel_min_mps2, params.accel_max_mps2)
    v_next = a * dt
    v_next += speed_mps
    np.clip(v_next, 0.0, params.speed_max_mps, out=v_next)
    applied = v_next - speed_mps
    applied *= 1.0 / dt
    # trapezoidal gap update: gap += dt/2 (v_pred + v_pred_next - v - v_next)
    dv = np.empty_like(speed_mps)
    if ring:
        dv[:, 0] = speed_mps[:, -1] + v_next[:, -1]
    else:
        dv[:, 0] = leader_speed_mps + leader_speed_next_mps
    dv[:, 1:] = speed_mps[:, :-1]
    dv[:, 1:] += v_next[:, :-1]
    dv -= speed_mps
    dv -= v_next
    dv *= dt / 2
    gap_next = dv
    gap_next += gap_m
    return gap_next, v_next, a, applied


def vehicle_blocks(
    gap_m: FloatArray,
    speed_mps: FloatArray,
    pred_speed_mps: FloatArray,
    last_accel_mps2: FloatArray,
    target_gap_m: float,
    target_speed_mps: float,
    params: PlatoonParams = PlatoonParams(),
    out: FloatArray | None = None,
) -> FloatArray:
    """The 5-number observation block of every follower, ``(B, N, 5)`` (published).

    ``[(v - v*)/v*, clip((v_pred - v)/5, -2, 2), clip((V(gap) - v)/5, -2, 2),
    (gap + (v_pred - v) dt - d*)/d*, u_last/accel_max]``.
    """
    if out is None:
        out = np.empty(gap_m.shape + (5,), dtype=np.result_type(gap_m, np.float32))
    dv = pred_speed_mps - speed_mps
    out[..., 0] = (speed_mps - target_speed_mps) / target_speed_mps
    out[..., 1] = np.clip(dv / 5.0, -2.0, 2.0)
    # V(gap) in the observation's precision (float32 cos is several times faster)
    vg = ovm_speed_mps(gap_m.astype(out.dtype), params)
    vg -= speed_mps
    vg /= 5.0
    out[..., 2] = np.clip(vg, -2.0, 2.0, out=vg)
    dv *= params.dt_s
    dv += gap_m
    dv -= target_gap_m
    dv /= target_gap_m
    out[..., 3] = dv
    out[..., 4] = last_accel_mps2 / params.accel_max_mps2
    return out


def agent_observations(blocks: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """Agent observations ``(B, N, 15)``: own block, front neighbour's, rear neighbour's.

    The front block of follower 1 (whose predecessor is the leader, not an agent) and the rear
    block of follower N are zero; :func:`neighbour_mask` says which are real.
    """
    b, n, k = blocks.shape
    if out is None:
        out = np.zeros((b, n, 3 * k), dtype=blocks.dtype)
    if not np.shares_memory(out[:, :, :k], blocks):
        out[:, :, :k] = blocks
    out[:, 1:, k : 2 * k] = blocks[:, :-1]
    out[:, :-1, 2 * k :] = blocks[:, 1:]
    return out


def neighbour_mask(n_vehicles: int) -> np.ndarray:
    """``(N, 2)`` booleans: has a front agent neighbour, has a rear agent neighbour."""
    mask = np.ones((n_vehicles, 2), dtype=bool)
    mask[0, 0] = False
    mask[-1, 1] = False
    return mask


def reward_terms(
    gap_m: FloatArray,
    speed_mps: FloatArray,
    applied_accel_mps2: FloatArray,
    power_kw: FloatArray | None,
    target_gap_m: float,
    target_speed_mps: float,
    params: PlatoonParams = PlatoonParams(),
    weights: RewardWeights = RewardWeights(),
) -> dict[str, FloatArray]:
    """The weighted reward terms of every agent, each ``(B, N)``, after a step.

    Keys: ``gap``, ``speed``, ``accel`` (together the published tracking reward), ``safety``
    (training only, published), ``power`` (the paper's energy term, zero if ``power_kw`` is None).
    The benchmark metrics use this same function, so the reward is computed in one place.
    """
    e = gap_m - target_gap_m
    return {
        "gap": weights.gap * e * e,
        "speed": weights.speed * np.square(speed_mps - target_speed_mps),
        "accel": weights.accel * np.square(applied_accel_mps2),
        "safety": weights.safety * np.square(np.maximum(2 * params.gap_stop_m - gap_m, 0.0)),
        "power": np.zeros_like(e) if power_kw is None else weights.power * power_kw,
    }


def combine_reward(
    terms: dict[str, FloatArray],
    *,
    training: bool,
    include_power: bool = True,
) -> FloatArray:
    """Sum the terms of :func:`reward_terms` (safety only in training, as published)."""
    r = terms["gap"] + terms["speed"]
    r += terms["accel"]
    if training:
        r += terms["safety"]
    if include_power:
        r += terms["power"]
    return r
