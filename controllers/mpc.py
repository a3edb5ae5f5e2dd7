"""Energy-aware distributed MPC (``mpc``): one nonlinear problem per follower and step, CasADi.

The formulation (model, cost, soft constraints, terminal cost, assumed trajectories, V2V,
fallback) is the shared one of :mod:`controllers.mpc_common`; this variant adds the fitted battery
power ``P(v, u)`` of :func:`envs.energy.load_power_polynomial` to the cost (net of the kinetic
energy change, see there) and solves the resulting NLP with CasADi:

- ``solver=sqp`` (default): ``sqpmethod`` with the active-set QP solver ``qrqp`` (exact
  Hessian, eigenvalues clipped where it is not positive definite; the "regularize" strategy
  stalled), warm-started with the shifted primal and dual solution: near the previous solution
  it needs one or two QP iterations (about 0.7 ms per follower and step on the 2-core machine).
- ``solver=fatrop``: structure-exploiting interior point (variables and constraints are ordered
  stage by stage, ``structure_detection='auto'``), warm-started from the shifted previous primal
  solution; an interior point needs about 4 iterations even from the optimum (about 0.95 ms).
- ``solver=ipopt``: the reference (warm-started primal; about 7 ms).

The problem is built once (one parametric solver reused by every follower, episode and reset);
per step only the parameter vector changes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.mpc_common import (
    OCP,
    DistributedMPCBase,
    MPCConfig,
    SolveResult,
    build_ocp,
)
from infra.errors import ConfigError

SOLVERS = ("sqp", "fatrop", "ipopt")

#: Statuses of sqpmethod that mean "already at the solution" after a good warm start.
_SQP_ACCEPTED = ("Search_Direction_Becomes_Too_Small",)


@dataclass(frozen=True)
class DMPCConfig(MPCConfig):
    """Options of ``mpc`` (those of :class:`MPCConfig` plus the energy term and the solver).

    Attributes
    ----------
    energy_weight : float
        Weight of the battery power ``P(v, u)`` in kW per step (0 makes ``mpc`` the quadratic
        problem of ``mpc-qp``, solved by CasADi). 0.25 saves energy on catchup-v1 and
        slowdown-v1 at almost unchanged tracking errors; with 1.0 the 2-s horizon turns myopic
        (followers postpone the braking that the regeneration limit makes expensive, then brake
        harder down the platoon) and slowdown-v1 costs more energy than ``mpc-qp``.
    kinetic_credit : bool
        Charge the horizon's energy net of the kinetic energy change (see ``mpc_common``).
    smooth_max_kw : float
        Smoothing (kW) of the power model's maximum of polynomial and regeneration floor
        (:func:`controllers.mpc_common.smooth_max`); 3 kW by default: braking at the
        regeneration limit is often optimal, so the optimum sits at the kink, and with 2 kW the
        sqp solver hit 100 iterations in 41 of 800 solves (catchup-v1, N = 4, 200 steps, one
        seed), with 3 kW in 1 (in none with 200 iterations, the default).
    solver : {"sqp", "fatrop", "ipopt"}
        NLP solver (sqpmethod + qrqp by default; IPOPT is the reference).
    max_iter : int
        Iteration limit of the solver (a solve that hits it counts as a failure).
    tol : float
        Convergence tolerance of the solver.
    """

    energy_weight: float = 0.25
    kinetic_credit: bool = True
    smooth_max_kw: float = 3.0
    solver: str = "sqp"
    max_iter: int = 200
    tol: float = 1e-6

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.energy_weight < 0:
            raise ConfigError(f"energy_weight must be >= 0, got {self.energy_weight}")
        if self.solver not in SOLVERS:
            raise ConfigError(f"solver must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.max_iter < 1:
            raise ConfigError(f"max_iter must be >= 1, got {self.max_iter}")
        if not self.smooth_max_kw > 0:
            raise ConfigError(f"smooth_max_kw must be > 0, got {self.smooth_max_kw}")
        if not self.tol > 0:
            raise ConfigError(f"tol must be > 0, got {self.tol}")


def make_nlp_solver(ocp: OCP, solver: str, max_iter: int, tol: float) -> Any:
    """A CasADi ``nlpsol`` for the problem, quiet, with the iteration limit and tolerance."""
    import casadi as ca

    nlp = {"x": ocp.z, "p": ocp.p, "f": ocp.f, "g": ocp.g}
    common: dict[str, Any] = {"expand": True, "print_time": False, "error_on_fail": False}
    if solver == "fatrop":
        opts = {
            **common,
            "structure_detection": "auto",
            "equality": ocp.equality,
            "fatrop": {"print_level": 0, "max_iter": max_iter, "tol": tol, "mu_init": 1e-3},
        }
        return ca.nlpsol("mpc_fatrop", "fatrop", nlp, opts)
    if solver == "ipopt":
        opts = {
            **common,
            "ipopt": {
                "print_level": 0,
                "sb": "yes",
                "max_iter": max_iter,
                "tol": tol,
                "acceptable_iter": 0,
            },
        }
        return ca.nlpsol("mpc_ipopt", "ipopt", nlp, opts)
    if solver == "sqp":
        opts = {
            **common,
            "qpsol": "qrqp",
            "qpsol_options": {"print_iter": False, "print_header": False, "error_on_fail": False},
            "convexify_strategy": "eigen-clip",
            "max_iter": max_iter,
            "tol_pr": tol,
            "tol_du": tol,
            "print_header": False,
            "print_iteration": False,
            "print_status": False,
        }
        return ca.nlpsol("mpc_sqp", "sqpmethod", nlp, opts)
    raise ConfigError(f"unknown solver {solver!r}")


class DMPCController(DistributedMPCBase):
    """Energy-aware distributed MPC (registered as ``mpc``), CasADi (sqp / fatrop / IPOPT)."""

    name = "mpc"
    config_cls = DMPCConfig

    def _build(self) -> None:
        from envs.energy import load_power_polynomial

        cfg: DMPCConfig = self.config
        self.ocp = build_ocp(
            cfg, self.model, self.params, load_power_polynomial(), cfg.energy_weight,
            cfg.kinetic_credit, cfg.smooth_max_kw,
        )
        self.solver = make_nlp_solver(self.ocp, cfg.solver, cfg.max_iter, cfg.tol)
        import casadi as ca

        self._dm = ca.DM
        self._bounds = [
            ca.DM(self.ocp.lbz),
            ca.DM(self.ocp.ubz),
            ca.DM(self.ocp.lbg),
            ca.DM(self.ocp.ubg),
        ]
        self._zero_lam = [ca.DM.zeros(self.ocp.nz), ca.DM.zeros(len(self.ocp.lbg))]
        self._lbg = self.ocp.lbg
        self._ubg = self.ocp.ubg
        self.iterations = 0

    def _solve(self, p: np.ndarray, warm: Any) -> tuple[SolveResult, Any]:
        ocp = self.ocp
        dm = self._dm
        if warm is None:
            z0 = ocp.initial_guess(p)
            lam = self._zero_lam
        else:
            z0 = ocp.shift(warm[0])
            z0[: ocp.nx] = p[: ocp.nx]
            lam = [warm[1], warm[2]] if self.config.solver == "sqp" else self._zero_lam
        # positional call with DM inputs: nlpsol's (x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0)
        out = self.solver.call([dm(z0), dm(p), *self._bounds, *lam])
        stats = self.solver.stats()
        self.iterations += int(stats.get("iter_count", 0))
        z = out[0].full().ravel()
        ok = bool(stats["success"])
        if not ok and self.config.solver == "sqp" and stats["return_status"] in _SQP_ACCEPTED:
            g = out[2].full().ravel()
            viol = max(
                float(np.max(self._lbg - g, initial=0)), float(np.max(g - self._ubg, initial=0))
            )
            ok = viol < 1e-6
        res = SolveResult(
            ok=ok,
            command_mps2=float(z[ocp.i_u[0]]),
            plan_speed_mps=z[ocp.i_v],
            plan_command_mps2=z[ocp.i_u],
        )
        if ok:
            lam_x, lam_g = out[3], out[4]
            if self.config.solver == "sqp":
                lam_x = dm(self._shift_lam_x(lam_x.full().ravel()))
                lam_g = dm(self._shift_lam_g(lam_g.full().ravel()))
            return res, (z, lam_x, lam_g)
        return res, None

    def _shift_lam_x(self, lam: np.ndarray) -> np.ndarray:
        return self.ocp.shift(lam)

    def _shift_lam_g(self, lam: np.ndarray) -> np.ndarray:
        perm = getattr(self, "_perm_g", None)
        if perm is None:
            nx, h = self.ocp.nx, self.ocp.horizon
            per = nx + 2
            idx = np.arange(len(lam))
            blk = idx[nx : nx + h * per].reshape(h, per)
            perm = idx.copy()
            perm[nx : nx + h * per] = np.concatenate([blk[1:], blk[-1:]]).ravel()
            self._perm_g = perm
        return lam[perm]

    def solve_parameters(self, p: np.ndarray) -> tuple[SolveResult, dict[str, Any]]:
        """Solve one follower's problem cold from a parameter vector (tests and diagnostics)."""
        res, _ = self._solve(np.asarray(p, dtype=np.float64), None)
        return res, dict(self.solver.stats())
