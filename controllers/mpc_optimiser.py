"""The optimisation problems of the MPC family, and the solvers that solve them.

One follower's problem (:func:`build_ocp`, symbolic in CasADi) is shared by the distributed
variants; they differ only in how it is solved: :class:`NLPSolver` (CasADi, ``mpc``, with the
energy term) and :class:`OSQPSolver` (OSQP, ``mpc-qp``, without it). The centralised ``cmpc``
solves the whole platoon's problem (:class:`CentralisedProblem`, cvxpy) with the same weights,
model and terminal cost. The model and the parameter vector are those of
:mod:`controllers.mpc_model`.

Problem of follower ``i`` at step ``t`` (horizon ``H``, step ``dt``)
-------------------------------------------------------------------
State ``x = [gap, v, (a), u_last]``, input ``w = [u, s]`` (command in m/s^2, slack ``s >= 0``
of the soft constraints), the model's step ``x' = f(x_k, w_k)``. Stage cost of stage
``k = 0..H-1`` on the next state (so every term depends on one stage only, as fatrop needs)::

      w_gap (gap' - d*)^2 + w_speed_pred (v' - vr_{k+1})^2 + w_speed_target (v' - v*)^2   [G]
    + F_gap (gap' - gap^_{k+1})^2 + F_v (v' - v^_{k+1})^2                                [F]
    + w_accel u^2 + w_jerk (u - u_last)^2 + w_slack s^2 + w_slack_l1 s
    + energy_weight [P(v', a') - c v' a' + c dt a'^2 / 2]                     (mpc only)

``G`` is what the follower puts on its predecessor (gap and relative speed to the predecessor's
assumed trajectory, its speed reference ``vr``); ``F`` is Zheng et al.'s self-deviation term
(TCST 2017): the deviation from the vehicle's own assumed trajectory ``v^`` and from the gap
``gap^`` it would give. ``F = self_weight * G`` with ``self_weight >= 1`` (Zheng's sufficient
condition for asymptotic stability of predecessor-following DMPC, F_i >= G_{i+1}, with
homogeneous weights), or 0 to switch it off.

Terminal cost (``terminal="lqr"``): on the last stage the ``G`` terms are replaced by
``z' P z`` with ``z = [gap_H - d*, v_H - v_c, (a_H), u_{H-1}]``, ``P`` the solution of the
discrete algebraic Riccati equation of the same model and weights (:func:`lqr_terminal_matrix`;
the cost-to-go after the horizon, including the rate term of the step after it; ``v_c`` the
weighted mean of ``vr_H`` and ``v*``). With no active constraint, no self-deviation and a
predecessor at constant speed the problem is then the infinite-horizon LQR for any ``H``
(tested against ``control.dlqr``).

Constraints (per stage, on ``x'``): ``u`` in ``[accel_min, accel_max]`` and ``v'`` in
``[0, speed_max]`` (hard), ``gap' + s >= gap_safe_m`` with ``s >= 0`` (soft minimum gap). The
problem is always feasible (the measured state is made so, :mod:`controllers.mpc_model`).
(Softened speed bounds sharing the slack made the interior-point solvers stall when the bound
was active.)

Energy term (``mpc``): ``P(v, u)`` is the fitted battery-power model (kW) of
:func:`envs.energy.load_power_polynomial`, the one the reward and the metrics use, evaluated at
the next speed and the applied acceleration as the env does; its maximum of polynomial and
regeneration floor is smoothed (``max(a, b) ~ (a + b + sqrt((a - b)^2 + e^2)) / 2``,
``e`` = the option ``smooth_max_kw``, 3 kW) so that the problem stays twice differentiable.
A finite-horizon MPC that minimises battery energy alone would "earn" energy by braking inside
the horizon (regeneration) and leave the kinetic energy it lost to the next horizon. So the
horizon's energy is charged net of the change of kinetic energy valued at the drive's
reversible rate ``c`` (kJ per (m/s)^2, fitted from the model, :func:`kinetic_energy_rate`);
summed over the horizon, ``sum_k [P - c v' a' + c dt a'^2/2] dt = E_battery - c (v_H^2 -
v_0^2)/2`` exactly. What remains is the drive's loss (motor, regeneration limits, drag,
rolling, auxiliaries), which is what the controller can actually save.
"""

from __future__ import annotations

import math
import signal
from collections.abc import Callable
from dataclasses import dataclass, fields
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers.mpc_model import HUMAN_PREDICTIONS, ParamLayout, VehicleModel
from envs.params import PlatoonParams
from infra.errors import ConfigError
from infra.interrupt import caught_by_library

if TYPE_CHECKING:
    from envs.energy import PowerPolynomial

TERMINAL_CHOICES = ("lqr", "stage")
#: CasADi solvers of :class:`NLPSolver` (``mpc``'s option ``solver``).
NLP_SOLVERS = ("sqp", "fatrop", "ipopt")
#: Statuses of sqpmethod that mean "already at the solution" after a good warm start.
_SQP_ACCEPTED = ("Search_Direction_Becomes_Too_Small",)


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
        speed held, or the nominal IDM under the stated assumption of
        :mod:`controllers.mpc_model` ("Human drivers"). Automated predecessors are never
        predicted: they send plans.
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
        weights = ("w_gap", "w_speed_pred", "w_speed_target", "w_accel", "w_jerk", "w_slack",
                   "w_slack_l1")
        for name in weights:
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
                f"self-deviation weight to dominate the predecessor weight, got {self.self_weight}")
        if self.terminal not in TERMINAL_CHOICES:
            raise ConfigError(
                f"terminal must be one of {', '.join(TERMINAL_CHOICES)}, got {self.terminal!r}")
        if self.human_prediction not in HUMAN_PREDICTIONS:
            raise ConfigError(f"human_prediction must be one of {', '.join(HUMAN_PREDICTIONS)}, "
                              f"got {self.human_prediction!r}")


# --------------------------------------------------------------------------- cost terms


def lqr_weights(config: MPCConfig,
                model: VehicleModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


# --------------------------------------------------------------------------- one follower's problem


def _shift_stages(perm: np.ndarray, start: int, n_stages: int, width: int) -> None:
    """In ``perm``, give each of ``n_stages`` blocks of ``width`` from ``start`` the next block's
    entries, the last block its own."""
    stop = start + n_stages * width
    blocks = perm[start:stop].reshape(n_stages, width)
    perm[start:stop] = np.concatenate([blocks[1:], blocks[-1:]]).ravel()


@dataclass
class OCP:
    """One follower's problem, symbolic (CasADi SX), variables ordered stage by stage.

    ``z = [x_0, w_0, x_1, w_1, ..., x_{H-1}, w_{H-1}, x_H]`` with ``w_k = [u_k, s_k]``;
    constraints ``lbg <= g(z, p) <= ubg`` ordered stage by stage (initial state, then per stage
    the dynamics, the soft minimum gap and the speed bounds), bounds ``lbz <= z <= ubz``.

    Attributes
    ----------
    z, p : casadi.SX
        Decision variables and parameters (:class:`controllers.mpc_model.ParamLayout`).
    f, g : casadi.SX
        Objective and constraints.
    lbg, ubg, lbz, ubz : ndarray
        Constant bounds.
    nx, horizon : int
        State size and ``H``.
    """

    z: Any
    p: Any
    f: Any
    g: Any
    lbg: np.ndarray
    ubg: np.ndarray
    lbz: np.ndarray
    ubz: np.ndarray
    nx: int
    horizon: int

    @property
    def nz(self) -> int:
        return int(self.z.shape[0])

    @property
    def stage_size(self) -> int:
        """``nx + 2``: a stage's state and its input ``[u, s]``."""
        return self.nx + 2

    @cached_property
    def i_u(self) -> np.ndarray:
        """Indices of ``u_k`` in ``z`` (k = 0..H-1)."""
        return np.arange(self.horizon) * self.stage_size + self.nx

    @cached_property
    def i_v(self) -> np.ndarray:
        """Indices of ``v_k`` in ``z`` (k = 0..H)."""
        return np.arange(self.horizon + 1) * self.stage_size + 1

    @property
    def equality(self) -> list[bool]:
        """Which constraints are equalities (fatrop's structure detection needs it)."""
        return [bool(a == b) for a, b in zip(self.lbg, self.ubg)]

    @cached_property
    def _z_shift(self) -> np.ndarray:
        ns, h = self.stage_size, self.horizon
        perm = np.arange(self.nz)
        _shift_stages(perm, 0, h, ns)
        perm[(h - 1) * ns : (h - 1) * ns + self.nx] = np.arange(h * ns, self.nz)  # x_H last
        return perm

    def shift(self, z: np.ndarray) -> np.ndarray:
        """A solution (or its bound multipliers) shifted by one stage, the last repeated."""
        return z[self._z_shift]

    def multiplier_shift(self, size: int) -> np.ndarray:
        """The permutation that shifts ``size`` constraint multipliers by one stage, the last
        repeated: those of ``g`` (the initial state's, then ``nx + 2`` per stage) and, beyond
        them (:class:`OSQPSolver`), those of the bounded ``[u_k, s_k]``."""
        perm = np.arange(size)
        end_g = self.nx + self.horizon * self.stage_size
        _shift_stages(perm, self.nx, self.horizon, self.stage_size)
        if size > end_g:
            _shift_stages(perm, end_g, self.horizon, 2)
        return perm

    def initial_guess(self, p: np.ndarray, previous: np.ndarray | None = None) -> np.ndarray:
        """Start of a solve from the parameters ``p``: the previous solution shifted by one
        stage from the measured state, or cold (the measured state held, zero inputs and
        slacks)."""
        if previous is not None:
            z0 = self.shift(previous)
            z0[: self.nx] = p[: self.nx]
            return z0
        z0 = np.zeros(self.nz)
        x0 = p[: self.nx].copy()
        x0[-1] = 0.0
        for k in range(self.horizon + 1):
            z0[k * self.stage_size : k * self.stage_size + self.nx] = x0
        z0[0 : self.nx] = p[: self.nx]
        return z0


def build_ocp(config: MPCConfig, model: VehicleModel, params: PlatoonParams,
              energy_model: PowerPolynomial | None = None, energy_weight: float = 0.0,
              kinetic_credit: bool = True, smooth_max_kw: float = 3.0) -> OCP:
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
    ocp = OCP(z=ca.vertcat(*z_parts), p=p, f=f, g=ca.vertcat(*g_parts),
              lbg=np.asarray(lbg, dtype=np.float64), ubg=np.asarray(ubg, dtype=np.float64),
              lbz=np.full(h * (nx + 2) + nx, -inf), ubz=np.full(h * (nx + 2) + nx, inf),
              nx=nx, horizon=h)
    ocp.lbz[ocp.i_u] = params.accel_min_mps2
    ocp.ubz[ocp.i_u] = params.accel_max_mps2
    ocp.lbz[ocp.i_u + 1] = 0.0  # the slacks
    return ocp


# --------------------------------------------------------------------------- solvers


@dataclass
class SolveResult:
    """Outcome of one follower's solve: success flag, first command, planned speeds ``(H+1,)``."""

    ok: bool
    command_mps2: float
    plan_speed_mps: np.ndarray
    plan_command_mps2: np.ndarray


class NLPSolver:
    """One follower's problem by a CasADi ``nlpsol``, built once, quiet, warm-started.

    - ``"sqp"``: ``sqpmethod`` with the active-set QP solver ``qrqp`` (exact Hessian, eigenvalues
      clipped where it is not positive definite; the "regularize" strategy stalled),
      warm-started with the shifted primal and dual solution: near the previous solution it
      needs one or two QP iterations (about 0.7 ms per follower and step on the 2-core
      machine). A stop at a too small search direction with the constraints met is a success.
    - ``"fatrop"``: structure-exploiting interior point (variables and constraints are ordered
      stage by stage, ``structure_detection='auto'``), warm-started from the shifted previous
      primal solution; an interior point needs about 4 iterations even from the optimum (about
      0.95 ms).
    - ``"ipopt"``: the reference (warm-started primal; about 7 ms).

    Parameters
    ----------
    ocp : OCP
        The problem (any energy term).
    solver : {"sqp", "fatrop", "ipopt"}
    max_iter : int
        Iteration limit (a solve that hits it fails).
    tol : float
        Convergence tolerance.
    """

    def __init__(self, ocp: OCP, solver: str, max_iter: int, tol: float) -> None:
        import casadi as ca

        plugins: dict[str, dict[str, Any]] = {
            "sqp": {"qpsol": "qrqp", "qpsol_options": {"print_iter": False, "print_header": False,
                                                        "error_on_fail": False},
                    "convexify_strategy": "eigen-clip", "max_iter": max_iter, "tol_pr": tol,
                    "tol_du": tol, "print_header": False, "print_iteration": False,
                    "print_status": False},
            "fatrop": {"structure_detection": "auto", "equality": ocp.equality,
                       "fatrop": {"print_level": 0, "max_iter": max_iter, "tol": tol,
                                  "mu_init": 1e-3}},
            "ipopt": {"ipopt": {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": tol,
                                "acceptable_iter": 0}},
        }
        opts = {"expand": True, "print_time": False, "error_on_fail": False, **plugins[solver]}
        nlp = {"x": ocp.z, "p": ocp.p, "f": ocp.f, "g": ocp.g}
        plugin = "sqpmethod" if solver == "sqp" else solver
        self.nlp = ca.nlpsol(f"mpc_{solver}", plugin, nlp, opts)
        self.ocp, self.method, self._dm = ocp, solver, ca.DM
        self._bounds = [ca.DM(ocp.lbz), ca.DM(ocp.ubz), ca.DM(ocp.lbg), ca.DM(ocp.ubg)]
        self._zero_lam = [ca.DM.zeros(ocp.nz), ca.DM.zeros(len(ocp.lbg))]
        self._g_shift = ocp.multiplier_shift(len(ocp.lbg))

    def solve(self, p: np.ndarray, warm: Any) -> tuple[SolveResult, Any]:
        """Solve from the parameters ``p`` and the warm start the previous solve returned (None:
        cold); returns the result and the next warm start (None after a failure)."""
        ocp, dm = self.ocp, self._dm
        z0 = ocp.initial_guess(p, None if warm is None else warm[0])
        lam = [warm[1], warm[2]] if warm is not None and self.method == "sqp" else self._zero_lam
        # positional call with DM inputs: nlpsol's (x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0)
        out = self.nlp.call([dm(z0), dm(p), *self._bounds, *lam])
        stats = self.nlp.stats()
        z = out[0].full().ravel()
        ok = bool(stats["success"])
        if not ok and self.method == "sqp" and stats["return_status"] in _SQP_ACCEPTED:
            g = out[2].full().ravel()
            ok = max(float(np.max(ocp.lbg - g, initial=0)),
                     float(np.max(g - ocp.ubg, initial=0))) < 1e-6
        res = SolveResult(ok, float(z[ocp.i_u[0]]), z[ocp.i_v], z[ocp.i_u])
        if not ok:
            return res, None
        lam_x, lam_g = out[3], out[4]
        if self.method == "sqp":
            lam_x = dm(ocp.shift(lam_x.full().ravel()))
            lam_g = dm(lam_g.full().ravel()[self._g_shift])
        return res, (z, lam_x, lam_g)

    def stats(self) -> dict[str, Any]:
        """CasADi's statistics of the last solve."""
        return dict(self.nlp.stats())


@dataclass
class QPData:
    """The QP ``min 1/2 z' H z + q' z  s.t.  l <= A z <= u`` of one follower, affine in ``p``.

    Attributes
    ----------
    H, A : scipy.sparse.csc_matrix
        Constant Hessian (full symmetric) and constraint matrix (constraints ``g``, then the
        bounded variables).
    Gq, q0 : ndarray
        ``q = Gq @ p + q0``.
    Gb : ndarray
        ``l = l0 - Gb @ p``, ``u = u0 - Gb @ p``.
    l0, u0 : ndarray
    """

    H: Any
    A: Any
    Gq: np.ndarray
    q0: np.ndarray
    Gb: np.ndarray
    l0: np.ndarray
    u0: np.ndarray

    def vectors(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``q, l, u`` for the parameter vector ``p``."""
        stacked = getattr(self, "_stacked", None)
        if stacked is None:
            stacked = self._stacked = np.vstack([self.Gq, self.Gb])
        r = stacked @ p
        nz = len(self.q0)
        b = r[nz:]
        q = r[:nz]
        q += self.q0
        return q, self.l0 - b, self.u0 - b


def extract_qp(ocp: OCP) -> QPData:
    """The QP matrices of a quadratic :class:`OCP` (no energy term), exactly, via CasADi.

    Raises
    ------
    ConfigError
        If the objective is not quadratic or the constraints not affine in ``z``.
    """
    import casadi as ca
    import scipy.sparse as sp

    z, p = ocp.z, ocp.p
    hess, grad = ca.hessian(ocp.f, z)
    jac_g = ca.jacobian(ocp.g, z)
    if ca.depends_on(hess, ca.vertcat(z, p)) or ca.depends_on(jac_g, ca.vertcat(z, p)):
        raise ConfigError("the MPC problem is not a QP (energy term on?)")
    zero_z = ca.DM.zeros(z.shape[0])
    q_expr = ca.substitute(grad, z, zero_z)
    b_expr = ca.substitute(ocp.g, z, zero_z)
    fun = ca.Function("qp_maps", [p], [hess, jac_g, ca.jacobian(q_expr, p), q_expr,
                                       ca.jacobian(b_expr, p), b_expr])
    zero_p = np.zeros(p.shape[0])
    h_dm, a_dm, gq, q0, gb, b0 = fun(zero_p)
    H = np.asarray(ca.DM(h_dm).full())
    Ag = np.asarray(ca.DM(a_dm).full())
    bounded = np.flatnonzero(np.isfinite(ocp.lbz) | np.isfinite(ocp.ubz))
    Ab = np.zeros((len(bounded), z.shape[0]))
    Ab[np.arange(len(bounded)), bounded] = 1.0
    A = np.vstack([Ag, Ab])
    b0_v = np.asarray(ca.DM(b0).full()).ravel()
    gb_m = np.asarray(ca.DM(gb).full())
    l0 = np.concatenate([ocp.lbg - b0_v, ocp.lbz[bounded]])
    u0 = np.concatenate([ocp.ubg - b0_v, ocp.ubz[bounded]])
    Gb = np.vstack([gb_m, np.zeros((len(bounded), p.shape[0]))])
    return QPData(H=sp.csc_matrix(0.5 * (H + H.T)), A=sp.csc_matrix(A),
                  Gq=np.asarray(ca.DM(gq).full()), q0=np.asarray(ca.DM(q0).full()).ravel(),
                  Gb=Gb, l0=l0, u0=u0)


class OSQPSolver:
    """One follower's quadratic problem (no energy term) by OSQP, its matrices built once.

    The problem is a convex QP whose matrices do not depend on the step: they are extracted once
    from the symbolic problem (:func:`extract_qp`) together with the affine maps from the
    parameter vector to the QP's vectors, ``q = G_q p + q_0``, ``l = l_0 - G_b p``,
    ``u = u_0 - G_b p``, so each solve is one small matrix-vector product, an update of
    ``q, l, u`` and a warm-started solve. One OSQP workspace serves every follower of every
    episode; each follower's warm start (its shifted previous primal and dual solution) and its
    own adapted step size ``rho`` are set before its solve, so a follower's solves never depend
    on the others' (batched and one-by-one runs agree exactly). The compiled workspace is called
    directly (osqp 1.x's ``OSQP._solver``), which saves the Python wrapper's per-call overhead
    (about 60 us of a 100 us solve).

    Parameters
    ----------
    ocp : OCP
        A quadratic problem.
    **settings
        OSQP's settings (tolerances, iteration limit, ...); a fixed ``adaptive_rho_interval``
        keeps the iterates reproducible (OSQP's default, 0, adapts ``rho`` after a share of the
        measured setup time, which makes them depend on the machine's load).
    """

    def __init__(self, ocp: OCP, **settings: Any) -> None:
        import osqp

        self.ocp = ocp
        self.qp = extract_qp(ocp)
        q, lo, up = self.qp.vectors(np.zeros(ocp.p.shape[0]))
        self.osqp = osqp.OSQP()
        self.osqp.setup(self.qp.H, q, self.qp.A, lo, up, verbose=False, warm_starting=True,
                        **settings)
        self._solved = int(osqp.SolverStatus.OSQP_SOLVED)
        #: OSQP catches SIGINT during a solve and returns this status instead
        self._sigint = int(osqp.SolverStatus.OSQP_SIGINT)
        self._ext = getattr(self.osqp, "_solver", None)
        self._rho0 = self._rho_now = float(self.osqp.settings.rho)
        # infinite bounds must be exactly OSQP's infinity (1e30) or beyond, else its duality
        # gap check takes them for finite ones and never terminates
        infty = float(osqp.constant("OSQP_INFTY"))
        self.qp.l0 = np.maximum(self.qp.l0, -infty)
        self.qp.u0 = np.minimum(self.qp.u0, infty)
        self._dual_shift = ocp.multiplier_shift(len(self.qp.l0))

    def solve(self, p: np.ndarray, warm: Any) -> tuple[SolveResult, Any]:
        """As :meth:`NLPSolver.solve`."""
        ocp = self.ocp
        q, lo, up = self.qp.vectors(p)
        x0 = ocp.initial_guess(p, None if warm is None else warm[0])
        y0 = np.zeros(len(lo)) if warm is None else warm[1][self._dual_shift]
        ext = self._ext
        if ext is not None:
            # each follower keeps its own step size rho (OSQP adapts it): the solve does not
            # depend on which other problems the shared workspace solved before
            rho = self._rho0 if warm is None else warm[2]
            if rho != self._rho_now:
                ext.update_rho(rho)
                self._rho_now = rho
            ext.update_data_vec(q=q, l=lo, u=up)
            ext.warm_start(x0, y0)
            ext.solve()
            info = ext.info
            z = np.array(ext.solution.x, dtype=np.float64)
            y = np.array(ext.solution.y, dtype=np.float64)
            if info.rho_updates:
                self._rho_now = float(ext.get_settings().rho)
        else:  # pragma: no cover - other osqp builds
            self.osqp.update(q=q, l=lo, u=up)
            self.osqp.warm_start(x=x0, y=y0)
            r = self.osqp.solve(raise_error=False)
            info = r.info
            z = np.array(r.x, dtype=np.float64)
            y = np.array(r.y, dtype=np.float64)
        self.last_info = info
        if int(info.status_val) == self._sigint:  # the command's Ctrl-C, not a failed solve
            caught_by_library(signal.SIGINT)
        ok = int(info.status_val) == self._solved and bool(np.all(np.isfinite(z)))
        self._last_ok = ok
        if z.size:
            res = SolveResult(ok, float(z[ocp.i_u[0]]), z[ocp.i_v], z[ocp.i_u])
        else:
            res = SolveResult(ok, math.nan, np.full(ocp.horizon + 1, np.nan),
                              np.full(ocp.horizon, np.nan))
        return res, ((z, y, self._rho_now) if ok else None)

    def stats(self) -> dict[str, Any]:
        """OSQP's status and iterations of the last solve, and its success."""
        info = self.last_info
        return {"status": info.status, "iter": info.iter, "success": self._last_ok}


# --------------------------------------------------------------------------- the platoon's problem


class CentralisedProblem:
    """The platoon's QP (``cmpc``), built once with cvxpy Parameters for ``N`` followers.

    The same model, weights, soft constraints and LQR terminal cost as one follower's problem,
    over all ``N`` followers jointly: every follower's predecessor is a decision variable of the
    same problem instead of an assumed trajectory (so there is no self-deviation term); the
    leader's assumed trajectory is its current speed held. No energy term (a convex QP). The
    problem is written once with cvxpy ``Parameter`` objects (DPP): a step only assigns the
    parameter values and re-solves (OSQP, warm-started), never rebuilds.

    Parameters (set per solve): ``gap0, v0, a0, ulast0`` (N,), ``v_lead`` (H+1,) and its clipped
    copy ``v_lead_ref``, targets ``d_star``, ``v_star``.

    Parameters
    ----------
    config : MPCConfig
    params : PlatoonParams
    n_vehicles : int
        Followers N.
    automated : (N,) bools, optional
        The seats the plan commands (default: all). A human seat's input is fixed at 0 (the
        stated model: constant speed) and its row carries no cost and no minimum-gap
        constraint (the plan cannot steer it).
    """

    def __init__(self, config: MPCConfig, params: PlatoonParams, n_vehicles: int,
                 automated: np.ndarray | None = None) -> None:
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
        cons += [gap[:, 1:]
                 == gap[:, :-1] + dt / 2 * (vpred[:, :-1] + vpred[:, 1:] - v[:, :-1] - v[:, 1:])]
        cons += [gap[rows, 1:] + s[rows] >= config.gap_safe_m, v[:, 1:] >= 0,
                 v[:, 1:] <= params.speed_max_mps]
        if humans.size:  # the stated model of a human: input 0 (constant speed)
            cons += [u[humans, :] == 0]
        vref = cp.vstack([cp.reshape(self.v_lead_ref, (1, h + 1), order="C"), v[:-1, :]])
        u_prev = cp.hstack([cp.reshape(self.ulast0, (n, 1), order="C"), u[:, :-1]])
        last = h - 1 if config.terminal == "lqr" else h
        cost = config.w_gap * cp.sum_squares(gap[rows, 1 : last + 1] - self.d_star)
        cost += config.w_speed_pred * cp.sum_squares(v[rows, 1 : last + 1]
                                                      - vref[rows, 1 : last + 1])
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
            ok = self.problem.status == cp.OPTIMAL and self.u.value is not None
        except cp.error.SolverError:
            ok = False
        return ok, (np.asarray(self.u.value) if ok else np.full((self.n, self.h), np.nan))
