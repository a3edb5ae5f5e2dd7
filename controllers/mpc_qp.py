"""Quadratic distributed MPC (``mpc-qp``): the shared formulation without the energy term, OSQP.

The problem is the one of :mod:`controllers.mpc_optimiser` with ``energy_weight = 0`` (no energy
term, not even a quadratic approximation of it: this variant is the tracking-only reference the
energy-aware ``mpc`` is compared with): a convex QP whose matrices are built once, solved by
OSQP (:class:`controllers.mpc_optimiser.OSQPSolver`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from controllers.mpc_controller import DistributedMPCBase
from controllers.mpc_optimiser import MPCConfig, OSQPSolver, build_ocp
from infra.errors import ConfigError


@dataclass(frozen=True)
class QPDMPCConfig(MPCConfig):
    """Options of ``mpc-qp``: those of :class:`MPCConfig` plus OSQP's settings (by OSQP's names).

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


class QPDMPCController(DistributedMPCBase):
    """Quadratic distributed MPC (registered as ``mpc-qp``), OSQP with matrices built once."""

    name = "mpc-qp"
    config_cls = QPDMPCConfig

    def _build(self) -> None:
        cfg: QPDMPCConfig = self.config
        self.ocp = build_ocp(cfg, self.model, self.params)
        osqp_settings = {f.name: getattr(cfg, f.name) for f in fields(cfg)[len(fields(MPCConfig)):]}
        self.solver = OSQPSolver(self.ocp, **osqp_settings)
        self.qp = self.solver.qp
