"""The one distributed-MPC formulation that ``mpc``, ``mpc-qp`` (and the tests) share.

Everything that defines *what* a follower optimises lives here; the variant modules only choose
*how* it is solved (CasADi NLP solvers in :mod:`controllers.mpc`, OSQP in
:mod:`controllers.mpc_qp`). The centralised ``cmpc`` reuses the weights, model and terminal cost.

Problem of follower ``i`` at step ``t`` (horizon ``H``, step ``dt``)
-------------------------------------------------------------------
State ``x = [gap, v, (a), u_last]`` (gap to the predecessor in m, speed in m/s, realised
acceleration only with an actuator lag, and the last command so that the input-rate cost is
stage-wise), input ``w = [u, s]`` (command in m/s^2, slack ``s >= 0`` of the soft constraints).
The model is the environment's own, step for step (``envs.dynamics.physics_step``)::

    a'   = a + g (u - a)                 (g = 1 - exp(-dt/tau); without lag a' = u)
    v'   = v + dt a'
    gap' = gap + dt/2 (vp_k + vp_{k+1} - v - v')      (trapezoidal, as the env)

where ``vp`` is the predecessor's *assumed* speed trajectory (received over V2V, see
:func:`assumed_predecessor_speeds`). Stage cost of stage ``k = 0..H-1`` on the next state
``x' = f(x_k, w_k)`` (so every term depends on one stage only, as fatrop needs)::

      w_gap (gap' - d*)^2 + w_speed_pred (v' - vr_{k+1})^2 + w_speed_target (v' - v*)^2   [G]
    + F_gap (gap' - gap^_{k+1})^2 + F_v (v' - v^_{k+1})^2                                [F]
    + w_accel u^2 + w_jerk (u - u_last)^2 + w_slack s^2 + w_slack_l1 s
    + energy_weight [P(v', a') - c v' a' + c dt a'^2 / 2]                     (mpc only)

``G`` is what the follower puts on its predecessor (gap and relative speed to the predecessor's
assumed trajectory; ``vr`` is ``vp`` clipped to the speed bounds: a speed the follower may not
reach is no reference, e.g. behind the slowdown-v1 leader above 30 m/s); ``F`` is Zheng et al.'s self-deviation term (TCST 2017): the deviation from
the vehicle's own assumed trajectory ``v^`` (its previous plan shifted by one step, extended with
a hold) and from the gap ``gap^`` that plan would give. ``F = self_weight * G`` with
``self_weight >= 1`` (Zheng's sufficient condition for asymptotic stability of predecessor-
following DMPC, F_i >= G_{i+1}, with homogeneous weights), or 0 to switch it off.

Terminal cost (``terminal="lqr"``): on the last stage the ``G`` terms are replaced by
``z' P z`` with ``z = [gap_H - d*, v_H - v_c, (a_H), u_{H-1}]``, ``P`` the solution of the
discrete algebraic Riccati equation of the same model and weights (:func:`lqr_terminal_matrix`;
the cost-to-go after the horizon, including the rate term of the step after it; ``v_c`` the
weighted mean of ``vr_H`` and ``v*``). With no active
constraint, no self-deviation and a predecessor at constant speed the problem is then the
infinite-horizon LQR for any ``H`` (tested against ``control.dlqr``).

Constraints (per stage, on ``x'``): ``u`` in ``[accel_min, accel_max]`` and ``v'`` in
``[0, speed_max]`` (hard), ``gap' + s >= gap_safe_m`` with ``s >= 0`` (soft minimum gap). The
problem is always feasible: the measured speed is clipped to the bounds (the env clips it at the
next step anyway) and, with an actuator lag, so is the realised acceleration's remaining effect
(``v + dt a (1-g)/g`` in the bounds; at a speed bound the env's clipping makes it void), so
``u = 0`` keeps the speed within the bounds. (Softened speed bounds sharing the slack made the
interior-point solvers stall when the bound was active.)

Energy term (``mpc``): ``P(v, u)`` is the fitted battery-power model (kW) of
:func:`envs.energy.load_power_polynomial`, the one the reward and the metrics use, evaluated at
the next speed and the applied acceleration as the env does; its maximum of polynomial and
regeneration floor is smoothed (``max(a, b) ~ (a + b + sqrt((a - b)^2 + e^2)) / 2``,
``e`` = the option ``smooth_max_kw``, 3 kW) so that the problem stays twice differentiable.
A finite-horizon MPC that minimises battery energy alone would "earn" energy by braking inside the horizon (regeneration) and leave
the kinetic energy it lost to the next horizon. So the horizon's energy is charged net of the
change of kinetic energy valued at the drive's reversible rate ``c`` (kJ per (m/s)^2, fitted
from the model, :func:`kinetic_energy_rate`); summed over the horizon,
``sum_k [P - c v' a' + c dt a'^2/2] dt = E_battery - c (v_H^2 - v_0^2)/2`` exactly. What remains
is the drive's loss (motor, regeneration limits, drag, rolling, auxiliaries), which is what the
controller can actually save.

Assumed trajectories and V2V
----------------------------
Every vehicle broadcasts ``[t, v_0, ..., v_H]``: its planned speeds and the step at which it
made the plan (width ``H + 2``); the leader (not controlled) sends its current speed held. The
receiver holds the last message that got through (delay, loss: ``envs.channel``), computes its
age ``t - stamp``, shifts the plan by that age and extends it with a hold, and finally offsets it
so that it starts at the predecessor speed measured by the radar now (own sensors are not V2V).
Before any message arrives, the predecessor's measured speed is held.

Human drivers
-------------
On a mixed string (``humans=2+5``, ``cav_fraction=0.5``, ``ring-v1``) the controller commands
the automated seats only (``EpisodeContext.automated``, ``PlatoonState.automated_mask``):

- no problem is solved for a human seat (none is counted in ``solve_count``); its command is 0,
  which the env ignores (the human model drives it), and its "plan" row is never delivered: a
  human sends nothing over V2V (``envs.channel``: its links are silent).
- An automated follower behind a human therefore never receives a plan. It predicts the human
  from its own sensors only (radar: the human's speed now, and the speed one step ago), with
  the stated model of the option ``human_prediction`` (:func:`human_predecessor_speeds`):

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

- Automated predecessors still send plans, received as above (a lost or late plan is aged, a
  missing one is the measured speed held, whatever ``human_prediction`` says). On the ring
  (``ring-v1``, no leader) follower 1's predecessor is follower N, by the same rules.

Fallback
--------
A solver failure (status not successful, non-finite solution, exception) never ends a run: the
follower applies ``min(shifted previous plan, ACC law)`` (the ACC law alone when no previous plan
is left), clipped to the bounds, keeps the shifted plan as its plan, and the failure is counted
in ``solver_failures``.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers.base import Controller, EpisodeContext, Message
from controllers.registry import build_config
from envs.channel import V2VChannel
from envs.humans import IDMParams
from envs.params import PlatoonParams
from envs.platoon import PlatoonState
from infra.errors import ConfigError
from infra.interrupt import raise_if_interrupted

if TYPE_CHECKING:
    from envs.energy import PowerPolynomial

TERMINAL_CHOICES = ("lqr", "stage")
#: How a follower predicts a human predecessor (module docstring, "Human drivers").
HUMAN_PREDICTIONS = ("constant-speed", "idm")
#: Smallest IDM interaction term ``(s*/s)^2`` inferred for a human predecessor: its unseen gap is
#: at most ``s* / sqrt(0.01)`` = ten times its desired gap (``human_prediction="idm"``).
IDM_MIN_INTERACTION = 0.01

#: Gains of the ACC law used by the fallback: ``u = k_gap (gap - d*) + k_speed (v_pred - v)``.
FALLBACK_GAIN_GAP = 0.2
FALLBACK_GAIN_SPEED = 0.7


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class MPCConfig:
    """Options common to every MPC variant (command line: ``mpc:horizon=30,w_gap=2``).

    Attributes
    ----------
    horizon : int
        Prediction horizon ``H`` in steps (20 steps = 2 s).
    w_gap : float
        Weight on the spacing error ``(gap - d*)^2`` (per m^2 per step).
    w_speed_pred : float
        Weight on the speed difference to the predecessor's assumed speed (per (m/s)^2).
    w_speed_target : float
        Weight on the speed error to the scenario target ``v*``.
    w_accel : float
        Weight on the command ``u^2`` (per (m/s^2)^2).
    w_jerk : float
        Weight on the command change ``(u_k - u_{k-1})^2``.
    self_weight : float
        Zheng's self-deviation weight as a multiple of the predecessor weights (gap and speed):
        must be >= 1 (dominating, as Zheng's stability condition asks), or 0 to switch it off.
    gap_safe_m : float
        Soft minimum gap (m); collisions happen below ``gap_min_m`` = 1 m.
    w_slack, w_slack_l1 : float
        Quadratic and linear penalties of the slack of the soft constraints.
    terminal : {"lqr", "stage"}
        Terminal cost: the Riccati (LQR) cost-to-go of the same model and weights, or just the
        stage cost.
    human_prediction : {"constant-speed", "idm"}
        How a follower behind a human driver (who sends no plan) predicts it: its measured
        speed held, or the nominal IDM under the stated assumption of the module docstring
        ("Human drivers"). Automated predecessors are never predicted: they send plans.
    """

    horizon: int = 20
    w_gap: float = 1.0
    w_speed_pred: float = 1.0
    w_speed_target: float = 0.1
    w_accel: float = 0.1
    w_jerk: float = 1.0
    self_weight: float = 1.0
    gap_safe_m: float = 5.0
    w_slack: float = 1000.0
    w_slack_l1: float = 100.0
    terminal: str = "lqr"
    human_prediction: str = "constant-speed"

    def __post_init__(self) -> None:
        if not 1 <= self.horizon <= 500:
            raise ConfigError(f"horizon must be an integer in 1..500 steps, got {self.horizon}")
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f"MPC option {f.name} must be finite, got {value}")
        for name in (
            "w_gap",
            "w_speed_pred",
            "w_speed_target",
            "w_accel",
            "w_jerk",
            "w_slack",
            "w_slack_l1",
        ):
            if getattr(self, name) < 0:
                raise ConfigError(f"MPC weight {name} must be >= 0, got {getattr(self, name)}")
        if self.w_accel + self.w_jerk <= 0:
            raise ConfigError("MPC needs w_accel + w_jerk > 0 (a positive input weight)")
        if self.w_gap <= 0:
            raise ConfigError("MPC needs w_gap > 0 (the spacing error must be penalised)")
        if self.w_slack <= 0:
            raise ConfigError("w_slack must be > 0 (the slack must be penalised)")
        if self.self_weight != 0 and self.self_weight < 1:
            raise ConfigError(
                "self_weight must be 0 (off) or >= 1: Zheng's stability condition needs the "
                f"self-deviation weight to dominate the predecessor weight, got {self.self_weight}"
            )
        if self.terminal not in TERMINAL_CHOICES:
            raise ConfigError(
                f"terminal must be one of {', '.join(TERMINAL_CHOICES)}, got {self.terminal!r}"
            )
        if self.human_prediction not in HUMAN_PREDICTIONS:
            raise ConfigError(
                f"human_prediction must be one of {', '.join(HUMAN_PREDICTIONS)}, got "
                f"{self.human_prediction!r}"
            )


# --------------------------------------------------------------------------- model


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

    @property
    def i_ulast(self) -> int:
        """Index of ``u_last`` in the state."""
        return self.nx - 1

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
        if self.has_lag:
            # a' = (1-g) a + g u ; v' = v + dt a' ; gap' = gap - dt v - dt/2 dt a'
            a_row = np.array([0.0, 0.0, 1 - g, 0.0])
            b_a = g
            v_row = np.array([0.0, 1.0, dt * (1 - g), 0.0])
            b_v = dt * g
            gap_row = np.array([1.0, -dt, -dt * dt / 2 * (1 - g), 0.0])
            b_gap = -dt * dt / 2 * g
            A = np.vstack([gap_row, v_row, a_row, np.zeros(4)])
            B = np.array([[b_gap], [b_v], [b_a], [1.0]])
        else:
            A = np.array([[1.0, -dt, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
            B = np.array([[-dt * dt / 2], [dt], [1.0]])
        return A, B


def lqr_weights(
    config: MPCConfig, model: VehicleModel
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Q, R, N`` of the stage cost in the standard LQR form on the augmented error state.

    ``x' Q x + u' R u + 2 x' N u`` with ``x = [gap - d*, v - v_c, (a), u_last]``: the ``G`` and
    input terms of the stage cost (the self-deviation term has no LQR counterpart).
    """
    nx = model.nx
    Q = np.zeros((nx, nx))
    Q[0, 0] = config.w_gap
    Q[1, 1] = config.w_speed_pred + config.w_speed_target
    Q[-1, -1] = config.w_jerk
    R = np.array([[config.w_accel + config.w_jerk]])
    N = np.zeros((nx, 1))
    N[-1, 0] = -config.w_jerk
    return Q, R, N


def lqr_terminal_matrix(config: MPCConfig, model: VehicleModel) -> np.ndarray:
    """Riccati matrix ``P`` (the LQR cost-to-go) of the error model with the stage weights.

    Solved with :func:`scipy.linalg.solve_discrete_are` (no python-control at run time).
    """
    from scipy.linalg import solve_discrete_are

    A, B = model.linear_error_model()
    Q, R, N = lqr_weights(config, model)
    # the u_last state of A is not observable in Q when w_jerk = 0: regularise slightly
    Q = Q + 1e-12 * np.eye(model.nx)
    P = solve_discrete_are(A, B, Q, R, s=N)
    return 0.5 * (P + P.T)


def smooth_max(a: Any, b: Any, e_kw: float) -> Any:
    """``(a + b + sqrt((a - b)^2 + e^2)) / 2``: within ``e / 2`` of ``max(a, b)``, smooth."""
    return 0.5 * (a + b + ((a - b) ** 2 + e_kw**2) ** 0.5)


def kinetic_energy_rate(power: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> float:
    """Reversible rate ``c`` (kJ per (m/s)^2) of the drive: ``P(v,u) - P(v,0) ~ c v u``.

    Least squares over ``v`` in [5, 25] m/s, ``u`` in [-1.5, 1.5] m/s^2 of the power model
    ``power(v, u)`` (kW) (``c`` is close to the equivalent mass in tonnes, 1.52 for the BMW i3).
    """
    v, u = np.meshgrid(np.linspace(5.0, 25.0, 41), np.linspace(-1.5, 1.5, 31))
    p = np.asarray(power(v, u), dtype=np.float64)
    p0 = np.asarray(power(v, np.zeros_like(u)), dtype=np.float64)
    x = v * u
    return float(((p - p0) * x).sum() / (x * x).sum())


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class ParamLayout:
    """Layout of the numeric parameter vector of one follower's problem.

    ``[x0 (nx), d*, v*, vp_0..vp_H, vhat_0..vhat_H, gaphat_0..gaphat_H, vref_0..vref_H]``:
    measured state (with the last command), targets, the predecessor's assumed speeds, the own
    assumed speeds and gaps, and the speed reference of the cost (the predecessor's assumed
    speeds clipped to the speed bounds: a reference the follower may not reach is no target).
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

    @property
    def vp(self) -> slice:
        s = self.nx + 2
        return slice(s, s + self.horizon + 1)

    @property
    def vhat(self) -> slice:
        s = self.nx + 2 + self.horizon + 1
        return slice(s, s + self.horizon + 1)

    @property
    def gaphat(self) -> slice:
        s = self.nx + 2 + 2 * (self.horizon + 1)
        return slice(s, s + self.horizon + 1)

    @property
    def vref(self) -> slice:
        s = self.nx + 2 + 3 * (self.horizon + 1)
        return slice(s, s + self.horizon + 1)

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


def feasible_lag_accel(
    speed_mps: np.ndarray,
    realised_accel_mps2: np.ndarray,
    model: VehicleModel,
    params: PlatoonParams,
) -> np.ndarray:
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


def make_parameters(
    layout: ParamLayout,
    model: VehicleModel,
    params: PlatoonParams,
    gap_m: np.ndarray,
    speed_mps: np.ndarray,
    realised_accel_mps2: np.ndarray,
    last_command_mps2: np.ndarray,
    vp_assumed: np.ndarray,
    vhat: np.ndarray,
    target_gap_m: float,
    target_speed_mps: float,
) -> np.ndarray:
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


def assumed_predecessor_speeds(
    received: np.ndarray, step: int, measured_pred_speed_mps: np.ndarray
) -> np.ndarray:
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


def idm_prediction_mps(
    speed_mps: np.ndarray,
    accel_mps2: np.ndarray,
    horizon: int,
    params: PlatoonParams,
    idm: IDMParams | None = None,
) -> np.ndarray:
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
    from envs.humans import idm_accel_mps2

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


def human_predecessor_speeds(
    vp_assumed: np.ndarray,
    human_pred: np.ndarray,
    measured_pred_speed_mps: np.ndarray,
    measured_pred_accel_mps2: np.ndarray,
    prediction: str,
    params: PlatoonParams,
) -> np.ndarray:
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
        out[:, human_pred] = idm_prediction_mps(
            vm, measured_pred_accel_mps2[:, human_pred], h1 - 1, params
        )
    else:
        out[:, human_pred] = vm[..., None]
    return out


# --------------------------------------------------------------------------- the problem


@dataclass
class OCP:
    """One follower's problem, symbolic (CasADi SX), variables ordered stage by stage.

    ``z = [x_0, w_0, x_1, w_1, ..., x_{H-1}, w_{H-1}, x_H]`` with ``w_k = [u_k, s_k]``;
    constraints ``lbg <= g(z, p) <= ubg`` ordered stage by stage (initial state, then per stage
    the dynamics, the soft minimum gap and the speed bounds), bounds ``lbz <= z <= ubz``.

    Attributes
    ----------
    z, p : casadi.SX
        Decision variables and parameters (:class:`ParamLayout`).
    f, g : casadi.SX
        Objective and constraints.
    lbg, ubg, lbz, ubz : ndarray
        Constant bounds.
    equality : list of bool
        Which constraints are equalities (fatrop's structure detection needs it).
    i_u, i_s : ndarray of int
        Indices of ``u_k``, ``s_k`` in ``z`` (k = 0..H-1).
    i_v : ndarray of int
        Indices of ``v_k`` in ``z`` (k = 0..H).
    stage_size : int
        ``nx + 2``.
    """

    z: Any
    p: Any
    f: Any
    g: Any
    lbg: np.ndarray
    ubg: np.ndarray
    lbz: np.ndarray
    ubz: np.ndarray
    equality: list[bool]
    i_u: np.ndarray
    i_s: np.ndarray
    i_v: np.ndarray
    stage_size: int
    nx: int
    horizon: int

    @property
    def nz(self) -> int:
        return int(self.z.shape[0])

    def initial_guess(self, p: np.ndarray) -> np.ndarray:
        """A cold start: the measured state held, zero inputs and slacks."""
        z0 = np.zeros(self.nz)
        x0 = p[: self.nx].copy()
        x0[-1] = 0.0
        for k in range(self.horizon + 1):
            z0[k * self.stage_size : k * self.stage_size + self.nx] = x0
        z0[0 : self.nx] = p[: self.nx]
        return z0

    def shift(self, z: np.ndarray) -> np.ndarray:
        """Warm start for the next step: the solution shifted by one stage, the last repeated."""
        perm = getattr(self, "_shift_perm", None)
        if perm is None:
            ns, h = self.stage_size, self.horizon
            idx = np.arange(self.nz)
            perm = np.empty_like(idx)
            perm[: (h - 1) * ns] = idx[ns : h * ns]
            perm[(h - 1) * ns : h * ns] = idx[(h - 1) * ns : h * ns]
            perm[(h - 1) * ns : (h - 1) * ns + self.nx] = idx[h * ns :]
            perm[h * ns :] = idx[h * ns :]
            self._shift_perm = perm
        return z[perm]


def build_ocp(
    config: MPCConfig,
    model: VehicleModel,
    params: PlatoonParams,
    energy_model: PowerPolynomial | None = None,
    energy_weight: float = 0.0,
    kinetic_credit: bool = True,
    smooth_max_kw: float = 3.0,
) -> OCP:
    """Build the symbolic problem of one follower (see the module docstring).

    Parameters
    ----------
    config : MPCConfig
        Horizon, weights, soft-constraint and terminal options.
    model : VehicleModel
        The env's model (lag or not).
    params : PlatoonParams
        Bounds.
    energy_model : PowerPolynomial, optional
        Fitted power model (kW) for the energy term; None for no energy term (the quadratic
        problem of ``mpc-qp``).
    energy_weight : float
        Weight of the power (per kW per step).
    kinetic_credit : bool
        Charge the horizon's energy net of the change of kinetic energy (module docstring).
    smooth_max_kw : float
        Smoothing of the power model's maximum (:func:`smooth_max`).
    """
    import casadi as ca

    h = config.horizon
    nx = model.nx
    layout = ParamLayout(nx, h)
    p = ca.SX.sym("p", layout.size)
    xs = [ca.SX.sym(f"x{k}", nx) for k in range(h + 1)]
    ws = [ca.SX.sym(f"w{k}", 2) for k in range(h)]
    d_star = p[layout.gap_target]
    v_star = p[layout.speed_target]
    vp = p[layout.vp]
    vhat = p[layout.vhat]
    gaphat = p[layout.gaphat]
    vref = p[layout.vref]
    f_gap = config.self_weight * config.w_gap
    f_v = config.self_weight * config.w_speed_pred
    w_vc = config.w_speed_pred + config.w_speed_target
    v_c = (config.w_speed_pred * vref[h] + config.w_speed_target * v_star) / max(w_vc, 1e-12)
    p_term = lqr_terminal_matrix(config, model) if config.terminal == "lqr" else None
    poly = None
    c_ke = 0.0
    if energy_model is not None and energy_weight > 0:
        poly = energy_model
        c_ke = kinetic_energy_rate(energy_model) if kinetic_credit else 0.0
    dt = model.dt_s
    z_parts: list[Any] = []
    g_parts: list[Any] = []
    lbg: list[float] = []
    ubg: list[float] = []
    f = 0
    inf = np.inf
    for k in range(h):
        x, w = xs[k], ws[k]
        u, s = w[0], w[1]
        z_parts += [x, w]
        if k == 0:
            g_parts.append(x - p[layout.x0])
            lbg += [0.0] * nx
            ubg += [0.0] * nx
        gap_n, v_n, a_n = model.step(x, u, vp[k], vp[k + 1])
        x_next = ca.vertcat(gap_n, v_n, a_n, u) if model.has_lag else ca.vertcat(gap_n, v_n, u)
        g_parts.append(xs[k + 1] - x_next)
        lbg += [0.0] * nx
        ubg += [0.0] * nx
        g_parts += [gap_n + s, v_n]
        lbg += [config.gap_safe_m, 0.0]
        ubg += [inf, params.speed_max_mps]
        if k < h - 1 or p_term is None:
            f += config.w_gap * (gap_n - d_star) ** 2
            f += config.w_speed_pred * (v_n - vref[k + 1]) ** 2
            f += config.w_speed_target * (v_n - v_star) ** 2
        else:
            zt = [gap_n - d_star, v_n - v_c] + ([a_n] if model.has_lag else []) + [u]
            zt_v = ca.vertcat(*zt)
            f += ca.mtimes([zt_v.T, ca.DM(p_term), zt_v])
        if config.self_weight > 0:
            f += f_gap * (gap_n - gaphat[k + 1]) ** 2 + f_v * (v_n - vhat[k + 1]) ** 2
        f += config.w_accel * u**2 + config.w_jerk * (u - x[nx - 1]) ** 2
        f += config.w_slack * s**2 + config.w_slack_l1 * s
        if poly is not None:
            e = poly.expression(v_n, a_n, lambda a, b: smooth_max(a, b, smooth_max_kw))
            if c_ke:
                e = e - c_ke * v_n * a_n + c_ke * dt * a_n**2 / 2
            f += energy_weight * e
    z_parts.append(xs[h])
    z = ca.vertcat(*z_parts)
    g = ca.vertcat(*g_parts)
    ns = nx + 2
    nz = h * ns + nx
    lbz = np.full(nz, -inf)
    ubz = np.full(nz, inf)
    i_u = np.arange(h) * ns + nx
    i_s = i_u + 1
    lbz[i_u] = params.accel_min_mps2
    ubz[i_u] = params.accel_max_mps2
    lbz[i_s] = 0.0
    lbg_a = np.asarray(lbg, dtype=np.float64)
    ubg_a = np.asarray(ubg, dtype=np.float64)
    return OCP(
        z=z,
        p=p,
        f=f,
        g=g,
        lbg=lbg_a,
        ubg=ubg_a,
        lbz=lbz,
        ubz=ubz,
        equality=[bool(a == b) for a, b in zip(lbg_a, ubg_a)],
        i_u=i_u,
        i_s=i_s,
        i_v=np.arange(h + 1) * ns + 1,
        stage_size=ns,
        nx=nx,
        horizon=h,
    )


# --------------------------------------------------------------------------- fallback


def acc_fallback_mps2(
    gap_m: np.ndarray | float,
    speed_mps: np.ndarray | float,
    pred_speed_mps: np.ndarray | float,
    target_gap_m: float,
    params: PlatoonParams,
) -> np.ndarray:
    """The ACC law of the fallback, with a full brake when about to collide.

    ``u = 0.2 (gap - d*) + 0.7 (v_pred - v)``, clipped; ``accel_min`` when the gap is below
    ``2 gap_min`` and closing.
    """
    gap = np.asarray(gap_m, dtype=np.float64)
    dv = np.asarray(pred_speed_mps, dtype=np.float64) - np.asarray(speed_mps, dtype=np.float64)
    u = FALLBACK_GAIN_GAP * (gap - target_gap_m) + FALLBACK_GAIN_SPEED * dv
    u = np.where((gap < 2 * params.gap_min_m) & (dv < 0), params.accel_min_mps2, u)
    return np.clip(u, params.accel_min_mps2, params.accel_max_mps2)


# --------------------------------------------------------------------------- controller base


@dataclass
class SolveResult:
    """Outcome of one follower's solve: success flag, first command, planned speeds ``(H+1,)``."""

    ok: bool
    command_mps2: float
    plan_speed_mps: np.ndarray
    plan_command_mps2: np.ndarray


class DistributedMPCBase(Controller):
    """Shared loop of the distributed MPC variants: V2V plans, parameters, warm start, fallback.

    Subclasses set ``config_cls`` and implement :meth:`_build` (once per physics and horizon; kept
    across resets) and :meth:`_solve` (one follower's problem from its parameter vector).
    ``solve_count`` counts the problems solved: one per automated seat, running episode and step
    (human seats are not solved; module docstring, "Human drivers").
    """

    family = "mpc"
    deterministic = True
    needs_observation = False
    config_cls: type = MPCConfig

    def __init__(self, **options: Any) -> None:
        super().__init__()
        self.config = build_config(self.config_cls, options, self.name)
        self.options = dict(options)
        self._built_for: tuple[Any, ...] | None = None
        self.solve_count = 0

    # -- to implement
    @abstractmethod
    def _build(self) -> None:
        """Build the solver(s) for ``self.model`` and ``self.layout``."""

    @abstractmethod
    def _solve(self, p: np.ndarray, warm: Any) -> tuple[SolveResult, Any]:
        """Solve one problem; returns the result and the new warm-start state (None = cold)."""

    # -- Controller API
    def prepare(self, params: PlatoonParams = PlatoonParams()) -> None:
        """Build the problem for these physics (done by :meth:`reset`; kept across resets)."""
        self.params = params
        self.model = VehicleModel.from_params(params)
        self.layout = ParamLayout(self.model.nx, self.config.horizon)
        key = (self.model, params)
        if self._built_for != key:
            self._build()
            self._built_for = key

    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """The assumed speed plan to the follower behind: its stamp and H+1 speeds (none held
        before the first one: NaN)."""
        return (Message("mpc_plan", self.config.horizon + 2, "predecessor", initial=math.nan),)

    def reset(self, ctx: EpisodeContext) -> None:
        self.prepare(ctx.params)
        h = self.config.horizon
        self.target_gap_m = ctx.target_gap_m
        self.target_speed_mps = ctx.target_speed_mps
        b, n = ctx.batch_size, ctx.n_vehicles
        self.channel: V2VChannel = ctx.channel("mpc_plan")
        self._received = np.full((b, n, h + 2), np.nan)
        self._plan_v: np.ndarray | None = None  # (B, N, H+1) own plans, made at _plan_step
        self._plan_u = np.zeros((b, n, h))
        self._plan_step = -1
        self._last_u = np.zeros((b, n))
        self._warm: list[list[Any]] = [[None] * n for _ in range(b)]
        # radar: each follower's last reading of its predecessor's speed (for its acceleration)
        self._vp_prev_mps: np.ndarray | None = None

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        t = state.step
        h = self.config.horizon
        b, n = state.gap_m.shape
        params = self.params
        vp_meas = state.pred_speed_mps
        vp = assumed_predecessor_speeds(self._received, t, vp_meas)
        automated = state.automated_mask
        human_pred = human_predecessor_mask(automated, state.ring)
        if human_pred.any():  # module docstring, "Human drivers"
            prev = self._vp_prev_mps
            ap_meas = np.zeros((b, n)) if prev is None else (vp_meas - prev) / params.dt_s
            vp = human_predecessor_speeds(
                vp, human_pred, vp_meas, ap_meas, self.config.human_prediction, params
            )
        self._vp_prev_mps = vp_meas.copy()
        if self._plan_v is None:
            vhat = np.repeat(
                np.clip(state.speed_mps, 0, params.speed_max_mps)[..., None], h + 1, -1
            )
            u_shift: np.ndarray | None = None
        else:
            age = t - self._plan_step
            vhat = shift_and_hold(self._plan_v, age)
            u_shift = shift_and_hold(
                np.concatenate([self._plan_u, self._plan_u[..., -1:]], axis=-1), age
            )[..., :h]
            if age >= h:
                u_shift = None
        p_all = make_parameters(
            self.layout,
            self.model,
            params,
            state.gap_m,
            state.speed_mps,
            state.realised_accel_mps2,
            self._last_u,
            vp,
            vhat,
            self.target_gap_m,
            self.target_speed_mps,
        )
        u = np.zeros((b, n))
        plan_v = vhat.copy()
        plan_u = np.zeros((b, n, h)) if u_shift is None else u_shift.copy()
        for bi in range(b):
            if state.done[bi]:
                continue
            for i in range(n):
                if not automated[i]:
                    continue  # a human seat: the env drives it, its command (0) is ignored
                try:
                    res, warm = self._solve(p_all[bi, i], self._warm[bi][i])
                    ok = (
                        res.ok
                        and bool(np.isfinite(res.command_mps2))
                        and bool(np.all(np.isfinite(res.plan_speed_mps)))
                    )
                except Exception:  # noqa: BLE001 - a solver error must never end a run
                    ok, warm = False, None
                if not ok:
                    raise_if_interrupted()  # a signal is not a solver failure
                self.solve_count += 1
                if ok:
                    u[bi, i] = res.command_mps2
                    plan_v[bi, i] = res.plan_speed_mps
                    plan_u[bi, i] = res.plan_command_mps2
                    self._warm[bi][i] = warm
                else:
                    self.solver_failures += 1
                    self._warm[bi][i] = None
                    u_acc = float(
                        acc_fallback_mps2(
                            state.gap_m[bi, i],
                            state.speed_mps[bi, i],
                            vp_meas[bi, i],
                            self.target_gap_m,
                            params,
                        )
                    )
                    if u_shift is not None:
                        u[bi, i] = min(float(u_shift[bi, i, 0]), u_acc)
                    else:
                        u[bi, i] = u_acc
                        plan_u[bi, i] = u_acc
                    # the plan it keeps (and sends): the shifted one (or its speed held)
        u = np.clip(u, params.accel_min_mps2, params.accel_max_mps2)
        self._last_u = u.copy()
        self._plan_v = plan_v
        self._plan_u = plan_u
        self._plan_step = t
        self._received = self.channel.transmit(
            encode_plans(t, state.leader_speed_now_mps, plan_v)
        ).copy()
        return u
