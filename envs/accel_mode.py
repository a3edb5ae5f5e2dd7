"""The acceleration action mode: a continuous command per follower, and what V2V delivers.

Two action modes share one platoon (:data:`ACTION_MODES`):

- ``ovm-gain`` (published, the paper's): a discrete index per follower choosing the OVM gains
  ``(alpha, beta)`` of :data:`envs.params.OVM_ACTIONS`; the 15-number observation of
  :func:`envs.dynamics.agent_observations`.
- ``accel``: an acceleration command per follower in ``[accel_min, accel_max]`` (the bounds of
  every controller's input, the MPC's included), through the same actuator lag, safety rules and
  energy model; the :data:`ACCEL_OBS_DIM`-number observation of :func:`accel_observations`,
  which adds what V2V delivers to ``cacc`` and ``mpc``.

V2V of the ``accel`` mode: every step, after choosing its command, each vehicle broadcasts it to
the follower behind (:data:`PRED_MESSAGE`, width 1; the leader sends its planned acceleration
``(v0[k+1] - v0[k]) / dt``), and the leader broadcasts its planned acceleration and its speed
deviation ``v0 - v*`` to every follower (:data:`LEADER_MESSAGE`, width 2). Both pass through
the run's :class:`envs.channel.V2VChannel` (delay in whole steps, loss with hold-last, bits
counted), with ``cacc``'s timing: a message sent at step ``k`` is observed from step
``k + 1 + delay`` on. Before the first message a receiver holds 0 (no acceleration, the leader
at the target speed).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from envs.channel import ChannelConfig, V2VChannel
from envs.dynamics import ovm_speed_mps
from envs.params import PlatoonParams
from infra.errors import ConfigError

#: The action modes, the published one first.
ACTION_MODES: tuple[str, ...] = ("ovm-gain", "accel")

#: Floats in an agent's observation in the ``accel`` mode (see :func:`accel_observations`).
ACCEL_OBS_DIM: int = 12

#: Names of the observation's columns in the ``accel`` mode, in order.
ACCEL_OBS_NAMES: tuple[str, ...] = (
    "speed_error",          # (v - v*) / v*
    "relative_speed",       # clip((v_pred - v) / 5, -2, 2), sensed
    "ovm_speed_error",      # clip((V(gap) - v) / 5, -2, 2), sensed
    "gap_error",            # (gap + (v_pred - v) dt - d*) / d*, sensed
    "applied_accel",        # u_last / accel_max
    "realised_accel",       # actuator state / accel_max
    "pred_command",         # predecessor's command / accel_max (V2V)
    "leader_accel",         # leader's planned acceleration / accel_max (V2V)
    "leader_speed_error",   # (v0 - v*) / v* (V2V)
    "is_first",             # 1 for follower 1 (its predecessor is the leader)
    "is_last",              # 1 for follower N
    "position",             # i / N
)

#: Name and width of the predecessor message (the command each vehicle applies).
PRED_MESSAGE: tuple[str, int] = ("accel-pred", 1)
#: Name and width of the leader's broadcast (planned acceleration, speed deviation from v*).
LEADER_MESSAGE: tuple[str, int] = ("accel-leader", 2)


def check_action_mode(mode: str) -> str:
    """Return ``mode`` if it is an action mode, else raise :class:`ConfigError`."""
    if mode not in ACTION_MODES:
        raise ConfigError(
            f"unknown action mode {mode!r}; the modes are: {', '.join(ACTION_MODES)}")
    return mode


def predecessor_links(n_vehicles: int, ring: bool = False) -> list[tuple[int, int]]:
    """Links ``i-1 -> i`` for followers ``i = 1..N`` (vehicle 0 is the leader; on a ring,
    follower 1's predecessor is follower N: ``N -> 1``)."""
    return [(n_vehicles if ring else 0, 1)] + [(i - 1, i) for i in range(2, n_vehicles + 1)]


def leader_links(n_vehicles: int) -> list[tuple[int, int]]:
    """Links ``0 -> i`` for followers ``i = 1..N`` (the leader's broadcast)."""
    return [(0, i) for i in range(1, n_vehicles + 1)]


def open_accel_channels(
    n_vehicles: int, seeds: Sequence[int] | np.ndarray, config: ChannelConfig = ChannelConfig(),
    silent: Sequence[int] = (), ring: bool = False,
) -> tuple[V2VChannel, V2VChannel]:
    """The two channels of the ``accel`` mode (predecessor, leader) for a batch of episodes;
    the vehicles ``silent`` (human seats, 1..N) send nothing. On a ring there is no leader: its
    broadcast never arrives (the followers hold 0, the leader at v* with no acceleration) and
    follower 1 hears follower N."""
    name, width = PRED_MESSAGE
    pred = V2VChannel(predecessor_links(n_vehicles, ring), width, seeds, config, name=name,
                      silent=silent)
    name, width = LEADER_MESSAGE
    lead = V2VChannel(leader_links(n_vehicles), width, seeds, config, name=name,
                      silent=(0,) if ring else ())
    return pred, lead


def transmit_accel_messages(
    pred_channel: V2VChannel,
    leader_channel: V2VChannel,
    command_mps2: np.ndarray,
    leader_accel_mps2: np.ndarray,
    leader_speed_mps: np.ndarray,
    target_speed_mps: float,
    params: PlatoonParams = PlatoonParams(),
) -> tuple[np.ndarray, np.ndarray]:
    """Send this step's messages; returns what the followers hold now.

    Parameters
    ----------
    pred_channel, leader_channel : V2VChannel
        The channels of :func:`open_accel_channels` (or the controller's own, same links).
    command_mps2 : (B, N)
        The followers' commands of this step (clipped to the bounds here, as the env applies
        them).
    leader_accel_mps2, leader_speed_mps : (B,)
        The leader's planned acceleration and current speed.
    target_speed_mps : float
        The scenario's v*.

    Returns
    -------
    pred_held : (B, N)
        The predecessor's command each follower holds (m/s^2).
    leader_held : (B, N, 2)
        The leader's planned acceleration (m/s^2) and speed deviation (m/s) each follower holds.
    """
    b, n = command_mps2.shape
    payload = np.empty((b, n + 1))
    payload[:, 0] = leader_accel_mps2
    np.clip(command_mps2, params.accel_min_mps2, params.accel_max_mps2, out=payload[:, 1:])
    pred_held = pred_channel.transmit(payload)[:, :, 0]
    lead = np.zeros((b, 1, 2))
    lead[:, 0, 0] = leader_accel_mps2
    lead[:, 0, 1] = leader_speed_mps - target_speed_mps
    leader_held = leader_channel.transmit(lead)
    return pred_held, leader_held


def accel_observations(
    gap_m: np.ndarray,
    speed_mps: np.ndarray,
    pred_speed_mps: np.ndarray,
    applied_accel_mps2: np.ndarray,
    realised_accel_mps2: np.ndarray,
    pred_held_mps2: np.ndarray,
    leader_held: np.ndarray,
    target_gap_m: float,
    target_speed_mps: float,
    params: PlatoonParams = PlatoonParams(),
    dtype: type = np.float32,
) -> np.ndarray:
    """The ``accel`` mode's observation of every follower, ``(B, N, 12)``.

    Columns (:data:`ACCEL_OBS_NAMES`): the published own block (speed error, sensed relative
    speed and OVM speed error, predicted gap error, last applied acceleration), the actuator
    state, what V2V delivered (predecessor's command, leader's planned acceleration and speed
    deviation; accelerations over ``accel_max``, speeds over ``v*``) and the position
    (first, last, ``i / N``), so that one shared policy acts at any N.

    Parameters
    ----------
    gap_m, speed_mps, pred_speed_mps, applied_accel_mps2, realised_accel_mps2 : (B, N)
        Sensed state of each follower.
    pred_held_mps2 : (B, N)
        Predecessor's command as delivered by V2V.
    leader_held : (B, N, 2)
        Leader's planned acceleration and speed deviation as delivered by V2V.
    """
    b, n = gap_m.shape
    a_max = params.accel_max_mps2
    out: np.ndarray = np.empty((b, n, ACCEL_OBS_DIM), dtype=dtype)
    dv = pred_speed_mps - speed_mps
    out[..., 0] = (speed_mps - target_speed_mps) / target_speed_mps
    out[..., 1] = np.clip(dv / 5.0, -2.0, 2.0)
    vg = ovm_speed_mps(gap_m, params) - speed_mps
    out[..., 2] = np.clip(vg / 5.0, -2.0, 2.0)
    out[..., 3] = (gap_m + dv * params.dt_s - target_gap_m) / target_gap_m
    out[..., 4] = applied_accel_mps2 / a_max
    out[..., 5] = realised_accel_mps2 / a_max
    out[..., 6] = pred_held_mps2 / a_max
    out[..., 7] = leader_held[..., 0] / a_max
    out[..., 8] = leader_held[..., 1] / target_speed_mps
    out[..., 9:] = position_features(n)[None]
    return out


def position_features(n_vehicles: int) -> np.ndarray:
    """``(N, 3)`` position features: is first, is last, ``i / N``."""
    pos = np.zeros((n_vehicles, 3))
    pos[0, 0] = 1.0
    pos[-1, 1] = 1.0
    pos[:, 2] = np.arange(1, n_vehicles + 1) / n_vehicles
    return pos


def cacc_from_observation(
    obs: np.ndarray,
    target_gap_m: float,
    target_speed_mps: float,
    params: PlatoonParams = PlatoonParams(),
    time_gap_s: float = 0.5,
    kp: float = 0.2,
    kd: float = 0.7,
    relative_speed_mps: np.ndarray | None = None,
    last_command_mps2: np.ndarray | None = None,
) -> np.ndarray:
    """Ploeg's CACC (the registered ``cacc`` controller's law and default gains) computed from
    the ``accel`` observation ``(..., 12)``: the command ``(...)`` in m/s^2.

    The controller's filter state is its last command, which the observation carries (column 4,
    the last applied acceleration), so the law needs no memory: ``c = a c_prev + (1 - a) w``
    with ``a = exp(-dt / h)`` and ``w = kp (gap - r - h v) + kd (dv - h a_real) + u_pred``,
    ``r = d* - h v*``. Two things the observation only approximates: it clips the sensed
    relative speed ``dv`` to +-10 m/s, and its last applied acceleration differs from the last
    command where the speed bounds act (``slowdown-v1``'s initial speeds above the bound) or
    the actuator lags. ``relative_speed_mps`` (the sensed ``v_pred - v`` unclipped) and
    ``last_command_mps2`` (:attr:`envs.platoon.PlatoonState.command_mps2`), both ``(...)``, make
    the law the controller's everywhere (tested against its runs).
    """
    a_max = params.accel_max_mps2
    x = np.asarray(obs, dtype=np.float64)
    dv = x[..., 1] * 5.0 if relative_speed_mps is None else np.asarray(relative_speed_mps, np.float64)
    # gap - r - h v, with gap = d* (1 + col3) - dv dt and v = v* (1 + col0)
    spacing = x[..., 3] * target_gap_m - dv * params.dt_s - time_gap_s * target_speed_mps * x[..., 0]
    w = kp * spacing + kd * (dv - time_gap_s * x[..., 5] * a_max) + x[..., 6] * a_max
    alpha = np.exp(-params.dt_s / time_gap_s)
    last = x[..., 4] * a_max if last_command_mps2 is None else np.asarray(last_command_mps2)
    return np.clip(alpha * last + (1 - alpha) * w, params.accel_min_mps2, a_max)
