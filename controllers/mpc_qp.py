"""Quadratic distributed MPC (``mpc-qp``): the shared formulation without the energy term, OSQP.

The problem is the one of :mod:`controllers.mpc_common` with ``energy_weight = 0`` (no energy
term, not even a quadratic approximation of it: this variant is the tracking-only reference the
energy-aware ``mpc`` is compared with). It is a convex QP whose matrices do not depend on the
step: they are extracted once from the symbolic problem (Hessian, constraint Jacobian) together
with the affine maps from the parameter vector to the QP's vectors,

    q = G_q p + q_0,   l = l_0 - G_b p,   u = u_0 - G_b p,

so each solve is one small matrix-vector product, ``OSQP.update(q=, l=, u=)`` and a
warm-started ``solve()``. One OSQP workspace serves every follower of every episode; each
follower's warm start (its shifted previous primal and dual solution) and its own adapted step
size ``rho`` are set before its solve, so a follower's solves never depend on the others'
(batched and one-by-one runs agree exactly). The compiled workspace is called directly (osqp
1.x's ``OSQP._solver``), which saves the Python wrapper's per-call overhead.
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


@dataclass(frozen=True)
class QPDMPCConfig(MPCConfig):
    """Options of ``mpc-qp`` (those of :class:`MPCConfig` plus OSQP's).

    Attributes
    ----------
    eps_abs, eps_rel : float
        OSQP's absolute and relative tolerances.
    max_iter : int
        OSQP's iteration limit (a solve that hits it counts as a failure).
    polishing : bool
        OSQP's solution polishing (exact active-set solution, slower).
    check_termination : int
        Check convergence every this many ADMM iterations. OSQP's default 25 saves the checks
        but rounds iteration counts up to multiples of 25; warm-started DMPC problems converge
        in about 10 iterations, so 5 is faster here.
    adaptive_rho_interval : int
        Iterations between OSQP's step-size adaptations (fixed, for reproducible iterates).
    """

    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    max_iter: int = 4000
    polishing: bool = False
    check_termination: int = 5
    adaptive_rho_interval: int = 25

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (self.eps_abs > 0 and self.eps_rel >= 0):
            raise ConfigError("OSQP tolerances must satisfy eps_abs > 0, eps_rel >= 0")
        if self.max_iter < 1 or self.check_termination < 1 or self.adaptive_rho_interval < 1:
            raise ConfigError("max_iter, check_termination, adaptive_rho_interval must be >= 1")


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
    fun = ca.Function(
        "qp_maps",
        [p],
        [hess, jac_g, ca.jacobian(q_expr, p), q_expr, ca.jacobian(b_expr, p), b_expr],
    )
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
    return QPData(
        H=sp.csc_matrix(0.5 * (H + H.T)),
        A=sp.csc_matrix(A),
        Gq=np.asarray(ca.DM(gq).full()),
        q0=np.asarray(ca.DM(q0).full()).ravel(),
        Gb=Gb,
        l0=l0,
        u0=u0,
    )


class QPDMPCController(DistributedMPCBase):
    """Quadratic distributed MPC (registered as ``mpc-qp``), OSQP with matrices built once."""

    name = "mpc-qp"
    config_cls = QPDMPCConfig

    def _build(self) -> None:
        import osqp

        cfg: QPDMPCConfig = self.config
        self.ocp = build_ocp(cfg, self.model, self.params)
        self.qp = extract_qp(self.ocp)
        q, lo, up = self.qp.vectors(np.zeros(self.layout.size))
        self.solver = osqp.OSQP()
        self.solver.setup(
            self.qp.H,
            q,
            self.qp.A,
            lo,
            up,
            verbose=False,
            eps_abs=cfg.eps_abs,
            eps_rel=cfg.eps_rel,
            max_iter=cfg.max_iter,
            polishing=cfg.polishing,
            warm_starting=True,
            check_termination=cfg.check_termination,
            # a fixed interval: OSQP's default (0) adapts rho after a share of the measured
            # setup time, which makes iterates depend on the machine's load
            adaptive_rho_interval=cfg.adaptive_rho_interval,
        )
        self._solved = (int(osqp.SolverStatus.OSQP_SOLVED),)
        # The compiled workspace behind osqp.OSQP (osqp 1.x): calling it directly saves the
        # Python wrapper's per-call overhead (about 60 us of a 100 us solve).
        self._ext = getattr(self.solver, "_solver", None)
        self._rho0 = self._rho_now = float(self.solver.settings.rho)
        # infinite bounds must be exactly OSQP's infinity (1e30) or beyond, else its duality
        # gap check takes them for finite ones and never terminates
        infty = float(osqp.constant("OSQP_INFTY"))
        self.qp.l0 = np.maximum(self.qp.l0, -infty)
        self.qp.u0 = np.minimum(self.qp.u0, infty)
        self.iterations = 0
        self._dual_perm = self._dual_shift_permutation()

    def _solve(self, p: np.ndarray, warm: Any) -> tuple[SolveResult, Any]:
        ocp = self.ocp
        q, lo, up = self.qp.vectors(p)
        if warm is None:
            x0, y0 = ocp.initial_guess(p), np.zeros(len(lo))
        else:
            x0 = ocp.shift(warm[0])
            x0[: ocp.nx] = p[: ocp.nx]
            y0 = warm[1][self._dual_perm]
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
            self.solver.update(q=q, l=lo, u=up)
            self.solver.warm_start(x=x0, y=y0)
            r = self.solver.solve(raise_error=False)
            info = r.info
            z = np.array(r.x, dtype=np.float64)
            y = np.array(r.y, dtype=np.float64)
        self.last_info = info
        self.iterations += int(info.iter)
        ok = int(info.status_val) in self._solved
        res = SolveResult(
            ok=ok and bool(np.all(np.isfinite(z))),
            command_mps2=float(z[ocp.i_u[0]]) if z.size else float("nan"),
            plan_speed_mps=z[ocp.i_v] if z.size else np.full(ocp.horizon + 1, np.nan),
            plan_command_mps2=z[ocp.i_u] if z.size else np.full(ocp.horizon, np.nan),
        )
        warm_new = (z, y, self._rho_now) if res.ok else None
        return res, warm_new

    def _dual_shift_permutation(self) -> np.ndarray:
        """Dual warm start: stage ``k`` gets stage ``k+1``'s multipliers, the last repeated."""
        ocp = self.ocp
        nx, h = ocp.nx, ocp.horizon
        per = nx + 2
        m = len(self.qp.l0)
        idx = np.arange(m)
        out = idx.copy()
        g0 = nx
        blk = idx[g0 : g0 + h * per].reshape(h, per)
        out[g0 : g0 + h * per] = np.concatenate([blk[1:], blk[-1:]]).ravel()
        b0 = g0 + h * per
        bnd = idx[b0 : b0 + 2 * h].reshape(h, 2)
        out[b0 : b0 + 2 * h] = np.concatenate([bnd[1:], bnd[-1:]]).ravel()
        return out

    def solve_parameters(self, p: np.ndarray) -> tuple[SolveResult, dict[str, Any]]:
        """Solve one follower's problem cold from a parameter vector (tests and diagnostics)."""
        res, _ = self._solve(np.asarray(p, dtype=np.float64), None)
        info = self.last_info
        return res, {"status": info.status, "iter": info.iter, "success": res.ok}
