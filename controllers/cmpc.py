"""Centralised MPC of the whole platoon with full information (``cmpc``), cvxpy.

The reference of what full communication could buy: one quadratic problem per episode and
step over all ``N`` followers jointly, with the same model, weights, soft constraints and LQR
terminal cost as the distributed variants (:mod:`controllers.mpc_common`), but where every
follower's predecessor is a decision variable of the same problem instead of an assumed
trajectory (so there is no self-deviation term). The leader is not controlled: its assumed
trajectory is its current speed held, as in the distributed variants. No energy term (the
problem is a convex QP, comparable with ``mpc-qp``).

Full information is this controller's premise: it reads the true state of every follower.
Each step every follower's ``[gap, speed, acceleration]`` is still sent to the coordinator (the
leader) through a V2V channel so that its communication load is counted like everyone else's;
the channel's delay and loss do not act on it (an idealised reference).

The problem is written once with cvxpy ``Parameter`` objects (DPP): a step only assigns the
parameter values and re-solves (OSQP, warm-started), never rebuilds.

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

from controllers.base import Controller, EpisodeContext, Message
from controllers.mpc_common import (
    MPCConfig,
    VehicleModel,
    acc_fallback_mps2,
    feasible_lag_accel,
    lqr_terminal_matrix,
)
from controllers.registry import build_config
from envs.params import PlatoonParams
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


class CentralisedProblem:
    """The platoon's QP, built once with cvxpy Parameters for ``N`` followers.

    Parameters (set per solve): ``gap0, v0, a0, ulast0`` (N,), ``v_lead`` (H+1,) and its clipped
    copy ``v_lead_ref``, targets ``d_star``, ``v_star``.

    Parameters
    ----------
    config : MPCConfig
    params : PlatoonParams
    n_vehicles : int
        Followers N.
    automated : (N,) bools, optional
        The seats the plan commands (default: all). A human seat's input is fixed at 0 and its
        row carries no cost and no minimum-gap constraint (module docstring, "Human drivers").
    """

    def __init__(
        self,
        config: MPCConfig,
        params: PlatoonParams,
        n_vehicles: int,
        automated: np.ndarray | None = None,
    ) -> None:
        import cvxpy as cp

        model = VehicleModel.from_params(params)
        h, n, dt = config.horizon, n_vehicles, params.dt_s
        self.n, self.h = n, h
        auto = np.ones(n, dtype=bool) if automated is None else np.asarray(automated, dtype=bool)
        humans = np.flatnonzero(~auto)
        # the rows that carry a cost: all (the same expressions as ever) or the automated ones
        rows: Any = slice(None) if humans.size == 0 else np.flatnonzero(auto)
        self.gap0 = cp.Parameter(n, name="gap0")
        self.v0 = cp.Parameter(n, name="v0")
        self.a0 = cp.Parameter(n, name="a0")
        self.ulast0 = cp.Parameter(n, name="ulast0")
        self.v_lead = cp.Parameter(h + 1, name="v_lead")
        self.v_lead_ref = cp.Parameter(h + 1, name="v_lead_ref")
        self.d_star = cp.Parameter(name="d_star")
        self.v_star = cp.Parameter(name="v_star")
        self.u = cp.Variable((n, h), name="u")
        self.s = cp.Variable((n, h), nonneg=True, name="slack")
        self.v = cp.Variable((n, h + 1), name="v")
        self.gap = cp.Variable((n, h + 1), name="gap")
        u, s, v, gap = self.u, self.s, self.v, self.gap
        cons = [v[:, 0] == self.v0, gap[:, 0] == self.gap0]
        cons += [u >= params.accel_min_mps2, u <= params.accel_max_mps2]
        if model.has_lag:
            self.a = cp.Variable((n, h + 1), name="a")
            a = self.a
            g = model.lag_gain
            cons += [a[:, 0] == self.a0, a[:, 1:] == (1 - g) * a[:, :-1] + g * u]
            a_next = a[:, 1:]
        else:
            a_next = u
        cons += [v[:, 1:] == v[:, :-1] + dt * a_next]
        vpred = cp.vstack([cp.reshape(self.v_lead, (1, h + 1), order="C"), v[:-1, :]])
        cons += [
            gap[:, 1:]
            == gap[:, :-1] + dt / 2 * (vpred[:, :-1] + vpred[:, 1:] - v[:, :-1] - v[:, 1:])
        ]
        cons += [
            gap[rows, 1:] + s[rows] >= config.gap_safe_m,
            v[:, 1:] >= 0,
            v[:, 1:] <= params.speed_max_mps,
        ]
        if humans.size:  # the stated model of a human: input 0 (constant speed)
            cons += [u[humans, :] == 0]
        vref = cp.vstack([cp.reshape(self.v_lead_ref, (1, h + 1), order="C"), v[:-1, :]])
        u_prev = cp.hstack([cp.reshape(self.ulast0, (n, 1), order="C"), u[:, :-1]])
        last = h - 1 if config.terminal == "lqr" else h
        cost = config.w_gap * cp.sum_squares(gap[rows, 1 : last + 1] - self.d_star)
        cost += config.w_speed_pred * cp.sum_squares(
            v[rows, 1 : last + 1] - vref[rows, 1 : last + 1]
        )
        cost += config.w_speed_target * cp.sum_squares(v[rows, 1 : last + 1] - self.v_star)
        cost += config.w_accel * cp.sum_squares(u) + config.w_jerk * cp.sum_squares(u - u_prev)
        cost += config.w_slack * cp.sum_squares(s) + config.w_slack_l1 * cp.sum(s)
        if config.terminal == "lqr":
            p_term = lqr_terminal_matrix(config, model)
            w_vc = config.w_speed_pred + config.w_speed_target
            v_c = (config.w_speed_pred * vref[:, h] + config.w_speed_target * self.v_star) / w_vc
            cols = [gap[:, h] - self.d_star, v[:, h] - v_c]
            if model.has_lag:
                cols.append(self.a[:, h])
            cols.append(u[:, h - 1])
            zt: Any = cp.vstack(cols)  # (nx, N)
            if humans.size:
                zt = zt[:, rows]
            # sum_i zt_i' P zt_i = ||L' zt||_F^2 with P = L L'
            w, vecs = np.linalg.eigh(p_term)
            lt = (vecs * np.sqrt(np.clip(w, 0, None))).T
            cost += cp.sum_squares(lt @ zt)
        self.problem = cp.Problem(cp.Minimize(cost), cons)
        if not self.problem.is_dpp():  # pragma: no cover - a formulation bug
            raise RuntimeError("the centralised MPC problem is not DPP")

    def solve(self, solver: str, eps: float) -> tuple[bool, np.ndarray]:
        """Solve with the current parameter values; returns (success, u (N, H))."""
        import cvxpy as cp

        kwargs: dict[str, Any] = {"warm_start": True}
        if solver == "OSQP":
            kwargs.update(eps_abs=eps, eps_rel=eps, max_iter=20000, polishing=False)
        try:
            self.problem.solve(solver=solver, **kwargs)
        except cp.error.SolverError:
            return False, np.full((self.n, self.h), np.nan)
        ok = self.problem.status == cp.OPTIMAL and self.u.value is not None
        if not ok:
            return False, np.full((self.n, self.h), np.nan)
        return True, np.asarray(self.u.value)


class CentralisedMPCController(Controller):
    """Centralised MPC with full information (registered as ``cmpc``), cvxpy with Parameters."""

    name = "cmpc"
    family = "mpc"
    needs_leader = True  # the plan is made at the leader, which collects every state
    deterministic = True
    needs_observation = False

    config_cls = CMPCConfig

    def __init__(self, **options: Any) -> None:
        super().__init__()
        self.config: CMPCConfig = build_config(self.config_cls, options, "cmpc")
        self.options = dict(options)
        self._problems: dict[tuple[Any, ...], CentralisedProblem] = {}

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
    return [i + 1 for i in range(1, len(auto)) if auto[i] and not auto[i - 1]]
