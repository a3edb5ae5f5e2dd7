"""Centralised MPC of the whole platoon with full information (``cmpc``), cvxpy.

The reference of what full communication could buy: one quadratic problem per episode and
step over all ``N`` followers jointly, with the same model, weights, soft constraints and LQR
terminal cost as the distributed variants but every follower's predecessor a decision variable
(:class:`controllers.mpc_optimiser.CentralisedProblem`, built once with cvxpy Parameters; a step
only assigns their values and re-solves). No energy term: comparable with ``mpc-qp``.

Full information is this controller's premise: it reads the true state of every follower.
Each step every follower's ``[gap, speed, acceleration]`` is still sent to the coordinator (the
leader) through a V2V channel so that its communication load is counted like everyone else's;
the channel's delay and loss do not act on it (an idealised reference).

Human drivers
-------------
On a string with human drivers behind the leader (``humans=2+5``, ``cav_fraction=0.5``; the
ring has no leader and is refused, ``needs_leader``) the plan chooses the automated seats'
inputs only. A human seat is a row of the problem whose input is fixed at 0 over the horizon
(the stated prediction model: constant speed; its realised acceleration is taken as 0 too, so
with an actuator lag it is still exactly constant speed), and it carries no cost and no minimum-
gap constraint of its own (the plan cannot steer it). Its state is not sent over V2V (a human
sends nothing, ``envs.channel``); what the leader knows of it is what an automated vehicle
senses:

- the automated follower directly behind a human measures the human's speed with its radar and
  sends it to the leader on a second channel, ``cmpc_human`` (one float per step, from those
  followers only, counted as every other bit); its own gap to the human is its own state, sent
  on ``cmpc_state`` as before;
- nobody senses a human's own gap (to its predecessor), nor the speed of a human followed by
  another human or driving last: those values are unknown and set to 0 in the problem, which
  is harmless because no row that carries a cost or a constraint depends on them (the human
  rows carry none, and the row of an automated vehicle depends only on its predecessor's speed,
  which it senses).

So every human splits the platoon's problem into independent blocks, each an automated run of
vehicles behind a predecessor predicted at constant speed (the leader's speed held, or a human's
measured speed held). Only ``human_prediction="constant-speed"`` is accepted. Homogeneous
strings build and solve exactly the problem above, with the same messages.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.base import EpisodeContext, Message
from controllers.mpc_controller import MPCController, acc_fallback_mps2
from controllers.mpc_model import VehicleModel, feasible_lag_accel, human_predecessor_mask
from controllers.mpc_optimiser import CentralisedProblem, MPCConfig
from envs.platoon import PlatoonState
from infra.errors import ConfigError
from infra.interrupt import raise_if_interrupted

CVXPY_SOLVERS = ("OSQP", "CLARABEL")


@dataclass(frozen=True)
class CMPCConfig(MPCConfig):
    """Options of ``cmpc``: those of :class:`MPCConfig` (``self_weight`` unused: there are no
    assumed trajectories) plus the cvxpy solver.

    Attributes
    ----------
    solver : {"OSQP", "CLARABEL"}
        QP solver cvxpy calls.
    eps : float
        Absolute and relative tolerance passed to OSQP.
    """

    solver: str = "OSQP"
    eps: float = 1e-5

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.solver.upper() not in CVXPY_SOLVERS:
            raise ConfigError(
                f"solver must be one of {', '.join(CVXPY_SOLVERS)}, got {self.solver!r}"
            )
        if not self.eps > 0:
            raise ConfigError(f"eps must be > 0, got {self.eps}")
        if self.human_prediction != "constant-speed":
            raise ConfigError(
                "cmpc predicts human drivers at constant speed only (human_prediction="
                f"constant-speed), got {self.human_prediction!r}"
            )


class CentralisedMPCController(MPCController):
    """Centralised MPC with full information (registered as ``cmpc``), cvxpy with Parameters."""

    name = "cmpc"
    needs_leader = True  # the plan is made at the leader, which collects every state
    config_cls = CMPCConfig

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        self._problems: dict[tuple[Any, ...], CentralisedProblem] = {}

    def preflight(self, scenario: Any, n_vehicles: int, params: Any = None) -> None:
        """Refuse a string of vehicle classes: the centralised problem has one vehicle model for
        every follower."""
        if scenario.vehicle_classes(n_vehicles) is not None:
            raise ConfigError(
                f"cmpc cannot run on {scenario.label or scenario.id}: its centralised problem "
                "models every follower as one vehicle; on a string of vehicle classes run the "
                "distributed MPC (mpc, mpc-qp), whose followers each use their class's model")

    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """Every automated follower's gap, speed and acceleration to the leader, where the plan is
        made (human seats send nothing); on a mixed string also, from each automated follower
        directly behind a human, the human's speed as its radar measures it (``cmpc_human``)."""
        out = [Message("cmpc_state", 3, "to_leader")]
        behind = human_watchers(ctx.automated)
        if behind:
            out.append(Message("cmpc_human", 1, tuple((i, 0) for i in behind)))
        return tuple(out)

    def reset(self, ctx: EpisodeContext) -> None:
        self.params = ctx.params
        self.model = VehicleModel.from_params(ctx.params)
        automated = np.asarray(ctx.automated, dtype=bool)
        key = (ctx.params, ctx.n_vehicles, tuple(automated.tolist()))
        if key not in self._problems:
            self._problems[key] = CentralisedProblem(
                self.config, ctx.params, ctx.n_vehicles, automated
            )
        self.problem = self._problems[key]
        self.automated = automated
        self._watchers = human_watchers(automated)
        self.human_channel = ctx.channel("cmpc_human") if self._watchers else None
        self.target_gap_m = ctx.target_gap_m
        self.target_speed_mps = ctx.target_speed_mps
        n = ctx.n_vehicles
        self.channel = ctx.channel("cmpc_state")
        b, h = ctx.batch_size, self.config.horizon
        self._plan_u = np.full((b, n, h), np.nan)
        self._u_last = np.zeros((b, n))

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        params = self.params
        pr = self.problem
        b, n = state.gap_m.shape
        h = self.config.horizon
        payload = np.zeros((b, n + 1, 3))
        payload[:, 1:, 0] = state.gap_m
        payload[:, 1:, 1] = state.speed_mps
        payload[:, 1:, 2] = state.applied_accel_mps2
        self.channel.transmit(payload)  # counted; full information is the premise (see module)
        gap0, speed0 = state.gap_m, state.speed_mps
        accel0 = state.realised_accel_mps2
        if not self.automated.all():  # module docstring, "Human drivers"
            human = ~self.automated
            gap0, speed0, accel0 = gap0.copy(), speed0.copy(), accel0.copy()
            gap0[:, human] = 0.0  # unknown, and no row with a cost depends on it
            speed0[:, human] = 0.0  # unknown unless an automated follower senses it (below)
            accel0[:, human] = 0.0  # the stated model: constant speed
            if self.human_channel is not None:
                seen = np.zeros((b, n + 1, 1))
                w = np.asarray(self._watchers)
                seen[:, w, 0] = state.pred_speed_mps[:, w - 1]  # follower w's radar reading
                self.human_channel.transmit(seen)  # counted, idealised as cmpc_state
                speed0[:, w - 2] = seen[:, w, 0]  # the human is seat w - 2 (follower w - 1)
        u = np.zeros((b, n))
        lead = state.leader_speed_now_mps
        vmax = params.speed_max_mps
        pr.d_star.value = float(self.target_gap_m)
        pr.v_star.value = float(self.target_speed_mps)
        for bi in range(b):
            if state.done[bi]:
                continue
            pr.gap0.value = gap0[bi]
            pr.v0.value = np.clip(speed0[bi], 0.0, vmax)
            pr.a0.value = feasible_lag_accel(pr.v0.value, accel0[bi], self.model, params)
            pr.ulast0.value = self._u_last[bi]
            pr.v_lead.value = np.full(h + 1, lead[bi])
            pr.v_lead_ref.value = np.full(h + 1, min(max(lead[bi], 0.0), vmax))
            try:
                ok, plan = pr.solve(self.config.solver.upper(), self.config.eps)
            except Exception:  # noqa: BLE001 - a solver error must never end a run
                ok, plan = False, np.full((n, h), np.nan)
            if not ok:
                raise_if_interrupted()  # a signal is not a solver failure
            if ok and np.all(np.isfinite(plan[:, 0])):
                u[bi] = plan[:, 0]
                self._plan_u[bi] = plan
            else:
                self.solver_failures += 1
                vp = state.pred_speed_mps[bi]
                u_acc = acc_fallback_mps2(
                    state.gap_m[bi], state.speed_mps[bi], vp, self.target_gap_m, params
                )
                shifted = self._plan_u[bi, :, 1] if h > 1 else np.full(n, np.nan)
                u[bi] = np.where(np.isfinite(shifted), np.minimum(shifted, u_acc), u_acc)
                self._plan_u[bi] = np.concatenate(
                    [self._plan_u[bi, :, 1:], self._plan_u[bi, :, -1:]], axis=1
                )
        u = np.clip(u, params.accel_min_mps2, params.accel_max_mps2)
        u[:, ~self.automated] = 0.0  # human seats: the env drives them, the command is ignored
        self._u_last = u.copy()
        return u


def human_watchers(automated: np.ndarray) -> list[int]:
    """Vehicle indices (1..N) of the automated followers directly behind a human driver: the
    ones whose radar senses a human's speed (none on a homogeneous string)."""
    auto = np.asarray(automated, dtype=bool)
    return [int(i) + 1 for i in np.flatnonzero(auto & human_predecessor_mask(auto, ring=False))]
