"""The controller side of the MPC family: options, the distributed loop, V2V plans, fallback.

Each step a distributed follower measures, predicts its predecessor
(:mod:`controllers.mpc_model`), solves its problem (:mod:`controllers.mpc_optimiser`), applies
the first command and sends its planned speeds to the follower behind.

Human drivers
-------------
On a mixed string (``humans=2+5``, ``cav_fraction=0.5``, ``ring-v1``) the controller commands
the automated seats only (``EpisodeContext.automated``, ``PlatoonState.automated_mask``): no
problem is solved for a human seat (none is counted in ``solve_count``); its command is 0,
which the env ignores (the human model drives it), and its "plan" row is never delivered: a
human sends nothing over V2V. A follower behind a human predicts it as
:mod:`controllers.mpc_model` states ("Human drivers").

Fallback
--------
A solver failure (status not successful, non-finite solution, exception) never ends a run: the
follower applies ``min(shifted previous plan, ACC law)`` (the ACC law alone when no previous plan
is left), clipped to the bounds, keeps the shifted plan as its plan, and the failure is counted
in ``solver_failures``.

Vehicle classes
---------------
On a string of vehicle classes (``classes=bus+van+car*6``, :mod:`envs.vehicle_classes`) each
follower predicts itself with its own model: the run's physics with its class's actuator lag and
acceleration bounds. One problem is built per distinct class (kept across resets) and every
follower solves the one of its class; the homogeneous platoon builds the one problem as before.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from typing import Any

import numpy as np

from controllers.base import Controller, EpisodeContext, Message
from controllers.mpc_model import (
    ParamLayout,
    VehicleModel,
    assumed_predecessor_speeds,
    encode_plans,
    human_predecessor_mask,
    human_predecessor_speeds,
    make_parameters,
    shift_and_hold,
)
from controllers.mpc_optimiser import MPCConfig, SolveResult
from envs.channel import V2VChannel
from envs.params import PlatoonParams
from envs.platoon import PlatoonState
from infra.interrupt import raise_if_interrupted

#: Gains of the ACC law used by the fallback: ``u = k_gap (gap - d*) + k_speed (v_pred - v)``.
FALLBACK_GAIN_GAP = 0.2
FALLBACK_GAIN_SPEED = 0.7


def acc_fallback_mps2(gap_m: np.ndarray | float, speed_mps: np.ndarray | float,
                      pred_speed_mps: np.ndarray | float, target_gap_m: float,
                      params: PlatoonParams) -> np.ndarray:
    """The ACC law of the fallback, with a full brake when about to collide.

    ``u = 0.2 (gap - d*) + 0.7 (v_pred - v)``, clipped; ``accel_min`` when the gap is below
    ``2 gap_min`` and closing.
    """
    gap = np.asarray(gap_m, dtype=np.float64)
    dv = np.asarray(pred_speed_mps, dtype=np.float64) - np.asarray(speed_mps, dtype=np.float64)
    u = FALLBACK_GAIN_GAP * (gap - target_gap_m) + FALLBACK_GAIN_SPEED * dv
    u = np.where((gap < 2 * params.gap_min_m) & (dv < 0), params.accel_min_mps2, u)
    return np.clip(u, params.accel_min_mps2, params.accel_max_mps2)


class MPCController(Controller):
    """What every MPC controller shares: its family and the options of :class:`MPCConfig`
    (a variant's ``config_cls`` extends them)."""

    family = "mpc"
    config_cls: type = MPCConfig


class DistributedMPCBase(MPCController):
    """Shared loop of the distributed MPC variants: V2V plans, parameters, warm start, fallback.

    Subclasses set ``config_cls`` and implement :meth:`_build`, which sets ``self.solver`` (an
    :class:`controllers.mpc_optimiser.NLPSolver` or ``OSQPSolver``; once per physics and
    horizon, kept across resets). ``solve_count`` counts the problems solved: one per automated
    seat, running episode and step (human seats are not solved; module docstring).
    """

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        self.solver: Any = None  # set by _build
        self.solve_count = 0
        #: built problems by physics: (model, layout, solver) (vehicle classes: one per class)
        self._problems: dict[PlatoonParams, tuple[VehicleModel, ParamLayout, Any]] = {}
        #: per class group: its physics and its seats (None: the homogeneous platoon)
        self._groups: list[tuple[PlatoonParams, np.ndarray]] | None = None

    @abstractmethod
    def _build(self) -> None:
        """Build ``self.solver`` for ``self.model``, ``self.params`` and ``self.config``."""

    def _solve(self, p: np.ndarray, warm: Any) -> tuple[SolveResult, Any]:
        """Solve one problem; returns the result and the new warm-start state (None = cold)."""
        return self.solver.solve(p, warm)

    def solve_parameters(self, p: np.ndarray) -> tuple[SolveResult, dict[str, Any]]:
        """Solve one follower's problem cold from a parameter vector (tests and diagnostics);
        returns the result and the solver's statistics."""
        res, _ = self._solve(np.asarray(p, dtype=np.float64), None)
        return res, self.solver.stats()

    # -- Controller API
    def prepare(self, params: PlatoonParams = PlatoonParams()) -> None:
        """Make the problem of these physics the current one: built once, then kept across
        resets (:meth:`reset` prepares the run's, and each vehicle class's)."""
        if params not in self._problems:
            self.params = params
            self.model = VehicleModel.from_params(params)
            self.layout = ParamLayout(self.model.nx, self.config.horizon)
            self._build()
            self._problems[params] = (self.model, self.layout, self.solver)
        self.params = params
        self.model, self.layout, self.solver = self._problems[params]

    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """The assumed speed plan to the follower behind: its stamp and H+1 speeds (none held
        before the first one: NaN)."""
        return (Message("mpc_plan", self.config.horizon + 2, "predecessor", initial=math.nan),)

    def reset(self, ctx: EpisodeContext) -> None:
        self.prepare(ctx.params)
        self._run_params = ctx.params
        self._groups = ctx.class_groups()
        if self._groups is not None:  # one problem per class: its lag and bounds
            for p_i, _ in self._groups:
                self.prepare(p_i)
            self.prepare(self._groups[0][0])
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
        params = self.params if self._groups is None else self._run_params
        vp_meas = state.pred_speed_mps
        vp = assumed_predecessor_speeds(self._received, t, vp_meas)
        automated = state.automated_mask
        human_pred = human_predecessor_mask(automated, state.ring)
        if human_pred.any():  # controllers.mpc_model, "Human drivers"
            prev = self._vp_prev_mps
            ap_meas = np.zeros((b, n)) if prev is None else (vp_meas - prev) / params.dt_s
            vp = human_predecessor_speeds(vp, human_pred, vp_meas, ap_meas,
                                          self.config.human_prediction, params)
        self._vp_prev_mps = vp_meas.copy()
        if self._plan_v is None:
            vhat = np.repeat(np.clip(state.speed_mps, 0, params.speed_max_mps)[..., None], h + 1,
                             -1)
            u_shift: np.ndarray | None = None
        else:
            age = t - self._plan_step
            vhat = shift_and_hold(self._plan_v, age)
            u_shift = shift_and_hold(
                np.concatenate([self._plan_u, self._plan_u[..., -1:]], axis=-1), age
            )[..., :h]
            if age >= h:
                u_shift = None
        u = np.zeros((b, n))
        plan_v = vhat.copy()
        plan_u = np.zeros((b, n, h)) if u_shift is None else u_shift.copy()
        if self._groups is None:
            self._solve_seats(state, np.arange(n), vp, vhat, vp_meas, u_shift, u, plan_v, plan_u)
            u = np.clip(u, params.accel_min_mps2, params.accel_max_mps2)
        else:  # each class's seats with its own problem and bounds
            for p_i, seats in self._groups:
                self.prepare(p_i)
                self._solve_seats(state, seats, vp, vhat, vp_meas, u_shift, u, plan_v, plan_u)
                u[:, seats] = np.clip(u[:, seats], p_i.accel_min_mps2, p_i.accel_max_mps2)
        self._last_u = u.copy()
        self._plan_v = plan_v
        self._plan_u = plan_u
        self._plan_step = t
        self._received = self.channel.transmit(encode_plans(t, state.leader_speed_now_mps,
                                                            plan_v)).copy()
        return u

    def _solve_seats(self, state: PlatoonState, seats: np.ndarray, vp: np.ndarray,
                     vhat: np.ndarray, vp_meas: np.ndarray, u_shift: np.ndarray | None,
                     u: np.ndarray, plan_v: np.ndarray, plan_u: np.ndarray) -> None:
        """Solve the problems of the automated ``seats`` with the current problem
        (:meth:`prepare`), writing their commands and plans into ``u``, ``plan_v``, ``plan_u``."""
        params = self.params
        automated = state.automated_mask
        b = state.gap_m.shape[0]
        p_all = make_parameters(self.layout, self.model, params, state.gap_m, state.speed_mps,
                                state.realised_accel_mps2, self._last_u, vp, vhat,
                                self.target_gap_m, self.target_speed_mps)
        for bi in range(b):
            if state.done[bi]:
                continue
            for i in seats.tolist():
                if not automated[i]:
                    continue  # a human seat: the env drives it, its command (0) is ignored
                try:
                    res, warm = self._solve(p_all[bi, i], self._warm[bi][i])
                    ok = (res.ok and bool(np.isfinite(res.command_mps2))
                          and bool(np.all(np.isfinite(res.plan_speed_mps))))
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
                    u_acc = float(acc_fallback_mps2(state.gap_m[bi, i], state.speed_mps[bi, i],
                                                    vp_meas[bi, i], self.target_gap_m, params))
                    if u_shift is not None:
                        u[bi, i] = min(float(u_shift[bi, i, 0]), u_acc)
                    else:
                        u[bi, i] = u_acc
                        plan_u[bi, i] = u_acc
                    # the plan it keeps (and sends): the shifted one (or its speed held)
