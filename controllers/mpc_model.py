"""The prediction model of the MPC family (pure numpy): what a follower predicts, and from what.

The vehicle
-----------
State ``x = [gap, v, (a), u_last]`` (gap to the predecessor in m, speed in m/s, realised
acceleration only with an actuator lag, and the last command so that the input-rate cost is
stage-wise), input ``u`` (command in m/s^2). The model is the environment's own, step for step
(``envs.dynamics.physics_step``)::

    a'   = a + g (u - a)                 (g = 1 - exp(-dt/tau); without lag a' = u)
    v'   = v + dt a'
    gap' = gap + dt/2 (vp_k + vp_{k+1} - v - v')      (trapezoidal, as the env)

where ``vp`` is the predecessor's *assumed* speed trajectory. What one follower's problem
(:mod:`controllers.mpc_optimiser`) reads is a parameter vector (:class:`ParamLayout`,
:func:`make_parameters`): the measured state, the targets, ``vp``, the follower's own assumed
trajectory ``v^`` (its previous plan shifted by one step, extended with a hold) with the gaps
``gap^`` it would give, and the speed reference ``vr`` (``vp`` clipped to the speed bounds: a
speed the follower may not reach is no reference, e.g. behind the slowdown-v1 leader above
30 m/s). The measured speed is clipped to the bounds (the env clips it at the next step anyway)
and, with an actuator lag, so is the realised acceleration's remaining effect
(:func:`feasible_lag_accel`), so that ``u = 0`` keeps the speed within the bounds and the
problem is always feasible.

Assumed trajectories and V2V
----------------------------
Every vehicle broadcasts ``[t, v_0, ..., v_H]``: its planned speeds and the step at which it
made the plan (width ``H + 2``, :func:`encode_plans`); the leader (not controlled) sends its
current speed held. The receiver holds the last message that got through (delay, loss:
``envs.channel``), computes its age ``t - stamp``, shifts the plan by that age and extends it
with a hold, and finally offsets it so that it starts at the predecessor speed measured by the
radar now (own sensors are not V2V; :func:`assumed_predecessor_speeds`). Before any message
arrives, the predecessor's measured speed is held.

Human drivers
-------------
A human sends nothing over V2V (``envs.channel``: its links are silent), so an automated
follower behind a human never receives a plan. It predicts the human from its own sensors only
(radar: the human's speed now, and the speed one step ago), with the stated model of the option
``human_prediction`` (:func:`human_predecessor_speeds`):

``"constant-speed"`` (the default): the measured speed held over the horizon. This is what
the V2V rule above already gives for a predecessor that never sends (its message stays
``NaN``), so homogeneous strings are untouched.

``"idm"``: the nominal IDM (:class:`envs.humans.IDMParams`, Flow's parameters, whatever human
model the scenario drives its humans with) rolled forward over the horizon. The IDM needs
the human's own gap and its predecessor's speed, which no automated vehicle senses; they are
replaced by a stated assumption: the human follows an unseen vehicle that keeps the human's
current speed (speed difference 0 now, that vehicle's speed held), at the gap at which the
IDM gives exactly the acceleration the follower measured (the difference of its last two
radar speeds over ``dt``; 0 on the first step). The gap is capped at ten times the IDM's
desired gap (``r >= IDM_MIN_INTERACTION``) so that a measured acceleration at or above the
free-road one does not become an infinite gap. Under this assumption a human measured at
constant speed is predicted at constant speed; a braking human is predicted to brake less
and less as its gap to the unseen vehicle opens, and to recover its speed.

Automated predecessors still send plans, received as above (a lost or late plan is aged, a
missing one is the measured speed held, whatever ``human_prediction`` says). On the ring
(``ring-v1``, no leader) follower 1's predecessor is follower N, by the same rules.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.humans import IDMParams, idm_accel_mps2
from envs.params import PlatoonParams

#: How a follower predicts a human predecessor (module docstring, "Human drivers").
HUMAN_PREDICTIONS = ("constant-speed", "idm")
#: Smallest IDM interaction term ``(s*/s)^2`` inferred for a human predecessor: its unseen gap is
#: at most ``s* / sqrt(0.01)`` = ten times its desired gap (``human_prediction="idm"``).
IDM_MIN_INTERACTION = 0.01


@dataclass(frozen=True)
class VehicleModel:
    """The env's longitudinal model of one follower as used by the MPC.

    Attributes
    ----------
    dt_s : float
        Step.
    lag_gain : float
        ``g = 1 - exp(-dt/tau)`` (1 without lag).
    has_lag : bool
        Whether the realised acceleration is a state (``tau > 0``).
    nx : int
        State size: ``[gap, v, u_last]`` or ``[gap, v, a, u_last]``.
    """

    dt_s: float
    lag_gain: float
    has_lag: bool

    @classmethod
    def from_params(cls, params: PlatoonParams) -> VehicleModel:
        """The model of the env with these physics."""
        return cls(params.dt_s, params.lag_gain, params.lag_s > 0)

    @property
    def nx(self) -> int:
        """State dimension."""
        return 4 if self.has_lag else 3

    def step(self, x: Any, u: Any, vp_now: Any, vp_next: Any) -> tuple[Any, Any, Any]:
        """Next ``(gap, v, a)`` from state ``x`` (indexable) and command ``u``.

        Works with floats, numpy arrays and CasADi symbols alike.
        """
        dt = self.dt_s
        if self.has_lag:
            a_next = x[2] + self.lag_gain * (u - x[2])
        else:
            a_next = u
        v_next = x[1] + dt * a_next
        gap_next = x[0] + dt / 2 * (vp_now + vp_next - x[1] - v_next)
        return gap_next, v_next, a_next

    def linear_error_model(self) -> tuple[np.ndarray, np.ndarray]:
        """``A, B`` of the augmented error state ``[gap - d*, v - vp, (a), u_last]``.

        For a predecessor at constant speed (the setting of the LQR terminal cost and of the
        ``control.dlqr`` check).
        """
        dt, g = self.dt_s, self.lag_gain
        if not self.has_lag:
            return (np.array([[1.0, -dt, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]),
                    np.array([[-dt * dt / 2], [dt], [1.0]]))
        # a' = (1-g) a + g u ; v' = v + dt a' ; gap' = gap - dt v - dt/2 dt a'
        A = np.array([[1.0, -dt, -dt * dt / 2 * (1 - g), 0.0], [0.0, 1.0, dt * (1 - g), 0.0],
                      [0.0, 0.0, 1 - g, 0.0], [0.0, 0.0, 0.0, 0.0]])
        return A, np.array([[-dt * dt / 2 * g], [dt * g], [g], [1.0]])


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class ParamLayout:
    """Layout of the numeric parameter vector of one follower's problem.

    ``[x0 (nx), d*, v*, vp_0..vp_H, vhat_0..vhat_H, gaphat_0..gaphat_H, vref_0..vref_H]``:
    measured state (with the last command), targets, the predecessor's assumed speeds, the own
    assumed speeds and gaps, and the speed reference of the cost (module docstring).
    """

    nx: int
    horizon: int

    @property
    def x0(self) -> slice:
        return slice(0, self.nx)

    @property
    def gap_target(self) -> int:
        return self.nx

    @property
    def speed_target(self) -> int:
        return self.nx + 1

    def _trajectory(self, i: int) -> slice:
        s = self.nx + 2 + i * (self.horizon + 1)
        return slice(s, s + self.horizon + 1)

    @property
    def vp(self) -> slice:
        return self._trajectory(0)

    @property
    def vhat(self) -> slice:
        return self._trajectory(1)

    @property
    def gaphat(self) -> slice:
        return self._trajectory(2)

    @property
    def vref(self) -> slice:
        return self._trajectory(3)

    @property
    def size(self) -> int:
        return self.nx + 2 + 4 * (self.horizon + 1)


def trapezoid_gaps(gap0: np.ndarray, vp: np.ndarray, v: np.ndarray, dt_s: float) -> np.ndarray:
    """Gaps ``(..., H+1)`` from ``gap0 (...)`` and speed trajectories ``vp, v (..., H+1)``."""
    rel = vp - v
    inc = dt_s / 2 * (rel[..., :-1] + rel[..., 1:])
    out = np.empty_like(vp)
    out[..., 0] = gap0
    np.cumsum(inc, axis=-1, out=out[..., 1:])
    out[..., 1:] += gap0[..., None]
    return out


def feasible_lag_accel(speed_mps: np.ndarray, realised_accel_mps2: np.ndarray,
                       model: VehicleModel, params: PlatoonParams) -> np.ndarray:
    """Realised acceleration clipped so that ``v + dt a (1-g)/g`` lies in the speed bounds.

    With an actuator lag, ``u = 0`` takes the speed to ``v + dt a (1-g)/g``; keeping that
    within ``[0, speed_max]`` keeps the hard speed bounds feasible. Near a bound the env's speed
    clipping voids the rest of the lag's effect anyway.
    """
    if not model.has_lag:
        return np.asarray(realised_accel_mps2, dtype=np.float64)
    reach = model.dt_s * (1 - model.lag_gain) / model.lag_gain
    v = np.asarray(speed_mps, dtype=np.float64)
    return np.clip(realised_accel_mps2, -v / reach, (params.speed_max_mps - v) / reach)


def make_parameters(layout: ParamLayout, model: VehicleModel, params: PlatoonParams,
                    gap_m: np.ndarray, speed_mps: np.ndarray, realised_accel_mps2: np.ndarray,
                    last_command_mps2: np.ndarray, vp_assumed: np.ndarray, vhat: np.ndarray,
                    target_gap_m: float, target_speed_mps: float) -> np.ndarray:
    """Parameter vectors of every follower's problem, ``(B, N, layout.size)``.

    Parameters
    ----------
    gap_m, speed_mps, realised_accel_mps2, last_command_mps2 : (B, N)
        Measured state and the follower's last command. Speeds are clipped to the speed bounds
        (the env clips them at the next step anyway: the slowdown-v1 start above 30 m/s).
    vp_assumed : (B, N, H+1)
        Predecessor's assumed speed trajectory (see :func:`assumed_predecessor_speeds`).
    vhat : (B, N, H+1)
        Own assumed speed trajectory (previous plan shifted, held); ``vhat[..., 0]`` is replaced
        by the measured speed.
    """
    b, n = gap_m.shape
    out = np.empty((b, n, layout.size))
    v0 = np.clip(speed_mps, 0.0, params.speed_max_mps)
    out[..., 0] = gap_m
    out[..., 1] = v0
    if model.has_lag:
        out[..., 2] = feasible_lag_accel(v0, realised_accel_mps2, model, params)
    out[..., layout.nx - 1] = last_command_mps2
    out[..., layout.gap_target] = target_gap_m
    out[..., layout.speed_target] = target_speed_mps
    out[..., layout.vp] = vp_assumed
    vh = vhat.copy()
    vh[..., 0] = v0
    out[..., layout.vhat] = vh
    out[..., layout.gaphat] = trapezoid_gaps(gap_m, vp_assumed, vh, model.dt_s)
    out[..., layout.vref] = np.clip(vp_assumed, 0.0, params.speed_max_mps)
    return out


# --------------------------------------------------------------------------- assumed trajectories


def shift_and_hold(plan: np.ndarray, age: np.ndarray | int) -> np.ndarray:
    """Shift plans ``(..., H+1)`` forward by ``age`` steps and extend with a hold.

    ``out[..., k] = plan[..., min(k + age, H)]``; ``age`` broadcast over the leading axes.
    """
    h1 = plan.shape[-1]
    age_arr = np.clip(np.asarray(age, dtype=np.int64), 0, h1 - 1)
    idx = np.minimum(np.arange(h1) + age_arr[..., None], h1 - 1)
    idx = np.broadcast_to(idx, plan.shape)
    return np.take_along_axis(plan, idx, axis=-1)


def encode_plans(step: int, leader_speed_mps: np.ndarray, plans: np.ndarray) -> np.ndarray:
    """V2V payload ``(B, N+1, H+2)``: ``[stamp, v_0..v_H]`` for the leader (held) and followers.

    Parameters
    ----------
    step : int
        Current step (the stamp).
    leader_speed_mps : (B,)
        Leader's current speed (its assumed trajectory is this speed held).
    plans : (B, N, H+1)
        Followers' planned speeds from now.
    """
    b, n, h1 = plans.shape
    out = np.empty((b, n + 1, h1 + 1))
    out[:, :, 0] = step
    out[:, 0, 1:] = leader_speed_mps[:, None]
    out[:, 1:, 1:] = plans
    return out


def assumed_predecessor_speeds(received: np.ndarray, step: int,
                               measured_pred_speed_mps: np.ndarray) -> np.ndarray:
    """Predecessor's assumed speeds ``(B, N, H+1)`` from the messages held by each follower.

    Parameters
    ----------
    received : (B, N, H+2)
        ``[stamp, v_0..v_H]`` held by each follower's receiver (NaN before the first message).
    step : int
        Current step.
    measured_pred_speed_mps : (B, N)
        Radar: predecessor's speed now.

    Returns
    -------
    (B, N, H+1)
        The last plan shifted by its age ``step - stamp`` and held, offset to start at the
        measured speed; the measured speed held where no message has arrived yet.
    """
    stamp = received[..., 0]
    plan = received[..., 1:]
    have = np.isfinite(stamp)
    age = np.where(have, step - np.where(have, stamp, 0), 0).astype(np.int64)
    shifted = shift_and_hold(np.where(have[..., None], plan, 0.0), age)
    shifted += (measured_pred_speed_mps - shifted[..., 0])[..., None]
    shifted[~have] = measured_pred_speed_mps[~have][:, None]
    return shifted


# --------------------------------------------------------------------------- human predecessors


def human_predecessor_mask(automated: np.ndarray, ring: bool) -> np.ndarray:
    """``(N,)`` booleans: follower ``i``'s predecessor is a human driver.

    The leader (vehicle 0) is never human; on a ring follower 1's predecessor is follower N.
    """
    automated = np.asarray(automated, dtype=bool)
    out = np.zeros(automated.shape, dtype=bool)
    out[1:] = ~automated[:-1]
    if ring:
        out[0] = not automated[-1]
    return out


def idm_prediction_mps(speed_mps: np.ndarray, accel_mps2: np.ndarray, horizon: int,
                       params: PlatoonParams, idm: IDMParams | None = None) -> np.ndarray:
    """A human predecessor's speeds ``(..., H+1)`` by the nominal IDM from what a follower senses.

    The unsensed inputs of the IDM (the human's gap and its predecessor's speed) follow the
    assumption of the module docstring ("Human drivers"): an unseen vehicle ahead of the human
    keeps the human's current speed ``v_0``, at the gap ``s_0`` at which the IDM gives the
    measured acceleration ``a_0``, i.e. ``(s*(v_0)/s_0)^2 = r = 1 - (v_0/v0)^delta - a_0/a``
    with ``r >= IDM_MIN_INTERACTION``. Then, for ``k = 0..H-1`` (the env's bounds and trapezoid
    rule, no actuator lag)::

        a_k     = clip(IDM(s_k, v_k, v_0), accel_min, accel_max)
        v_{k+1} = clip(v_k + dt a_k, 0, speed_max)
        s_{k+1} = s_k + dt/2 (2 v_0 - v_k - v_{k+1})

    Parameters
    ----------
    speed_mps, accel_mps2 : arrays of one shape
        The human's speed and acceleration as measured by the follower's radar.
    horizon : int
        ``H``.
    params : PlatoonParams
        Step and bounds.
    idm : IDMParams, optional
        The nominal IDM (default: Flow's parameters).

    Returns
    -------
    array (..., H+1)
        Predicted speeds, starting at the (clipped) measured speed.
    """
    p = IDMParams() if idm is None else idm
    dt = params.dt_s
    v0 = np.clip(np.asarray(speed_mps, dtype=np.float64), 0.0, params.speed_max_mps)
    a0 = np.asarray(accel_mps2, dtype=np.float64)
    r = 1.0 - (v0 / p.desired_speed_mps) ** p.delta - a0 / p.accel_max_mps2
    r = np.maximum(r, IDM_MIN_INTERACTION)
    s = (p.standstill_m + v0 * p.time_gap_s) / np.sqrt(r)
    out = np.empty(v0.shape + (horizon + 1,))
    out[..., 0] = v0
    v = v0
    for k in range(horizon):
        a = np.clip(idm_accel_mps2(s, v, v0, p), params.accel_min_mps2, params.accel_max_mps2)
        v_next = np.clip(v + dt * a, 0.0, params.speed_max_mps)
        s = s + dt / 2 * (2 * v0 - v - v_next)
        v = v_next
        out[..., k + 1] = v
    return out


def human_predecessor_speeds(vp_assumed: np.ndarray, human_pred: np.ndarray,
                             measured_pred_speed_mps: np.ndarray,
                             measured_pred_accel_mps2: np.ndarray, prediction: str,
                             params: PlatoonParams) -> np.ndarray:
    """``vp_assumed (B, N, H+1)`` with the columns of human predecessors set by ``prediction``.

    ``"constant-speed"``: the measured speed held (what :func:`assumed_predecessor_speeds`
    already gives for a predecessor that never sent a plan; set again here so that the rule does
    not hang on the channel's ``initial``); ``"idm"``: :func:`idm_prediction_mps` from the
    measured speed and acceleration. Automated predecessors' columns are returned unchanged.
    """
    if not human_pred.any():
        return vp_assumed
    out = vp_assumed.copy()
    h1 = out.shape[-1]
    vm = measured_pred_speed_mps[:, human_pred]
    if prediction == "idm":
        out[:, human_pred] = idm_prediction_mps(vm, measured_pred_accel_mps2[:, human_pred],
                                                h1 - 1, params)
    else:
        out[:, human_pred] = vm[..., None]
    return out
