"""Physical parameters of the common platoon environment (published CACC benchmark values)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from infra.errors import ConfigError

#: MARL action index -> (alpha, beta) of the OVM law (published benchmark).
OVM_ACTIONS: tuple[tuple[float, float], ...] = ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5))

#: Published evaluation seeds: 2000, 2010, ..., 2490 (50 episodes).
EVAL_SEEDS: tuple[int, ...] = tuple(range(2000, 2500, 10))

#: Validation seeds 1..32: checkpoint selection, tuning and any other choice made on data. They
#: are never evaluation seeds and never training seeds (training episodes use seeds >= 1e7).
VALIDATION_SEEDS: tuple[int, ...] = tuple(range(1, 33))

#: Test seeds 900000..900099 (100 episodes): kept for the final word (the generalisation matrix
#: and the README's main table). No training, tuning, selection or budget decision reads them
#: (:func:`check_decision_seeds` refuses); they are disjoint from the training seeds
#: (``1e7 (seed + 1) + k``), the validation seeds, the published evaluation seeds and their
#: extension ``2000 + 10 k`` up to ``--episodes 10000``. Rule: ``docs/seed-sets.md``.
TEST_SEEDS: tuple[int, ...] = tuple(range(900_000, 900_100))

#: The named seed sets of ``cacc-bench run --seed-set``, the default first.
SEED_SETS: dict[str, tuple[int, ...]] = {
    "eval": EVAL_SEEDS,
    "test": TEST_SEEDS,
    "validation": VALIDATION_SEEDS,
}

_TEST_SEED_SET = frozenset(TEST_SEEDS)


def check_decision_seeds(seeds: Iterable[int] | np.ndarray, who: str) -> None:
    """Refuse the test seeds in a decision (training, validation, selection, tuning, budget).

    Decisions are made on the validation seeds (:data:`VALIDATION_SEEDS`); the test seeds
    (:data:`TEST_SEEDS`) are read only by the final evaluation, so that no choice is fitted to
    them. Every helper that makes such a choice calls this on the seeds it is given.

    Parameters
    ----------
    seeds : iterable of int or numpy.ndarray
        The episode seeds the decision would read.
    who : str
        The helper making the decision, named in the message
        (``"benchmark.policy_eval.validation_evaluator"``).

    Raises
    ------
    ConfigError
        When any of ``seeds`` is a test seed.
    """
    flat = seeds.ravel().tolist() if isinstance(seeds, np.ndarray) else seeds
    found = sorted({int(s) for s in flat} & _TEST_SEED_SET)
    if found:
        shown = ", ".join(str(s) for s in found[:5]) + (", ..." if len(found) > 5 else "")
        raise ConfigError(
            f"{who}: seeds {shown} are test seeds ({len(found)} of them); the test seeds "
            f"{TEST_SEEDS[0]}..{TEST_SEEDS[-1]} are kept for the final evaluation and no "
            "training, tuning, selection or budget decision may read them: decide on the "
            "validation seeds (envs.params.VALIDATION_SEEDS). The rule: docs/seed-sets.md"
        )

#: Evaluation modes of a learned policy, the default first: ``sampled`` (actions drawn from the
#: policy, as trained) and ``greedy`` (argmax; a different policy when the trained one stays
#: stochastic).
EVAL_MODES: tuple[str, ...] = ("sampled", "greedy")


@dataclass(frozen=True)
class PlatoonParams:
    """Longitudinal model of the platoon (all values published unless stated).

    Attributes
    ----------
    dt_s : float
        Control and simulation step, 0.1 s.
    accel_min_mps2, accel_max_mps2 : float
        Command bounds, -2.5 and 2.5 m/s^2.
    speed_max_mps : float
        Speed bound, 30 m/s (speeds are clipped to [0, speed_max_mps]).
    gap_min_m : float
        A gap below this is a collision, 1 m.
    gap_stop_m, gap_go_m : float
        OVM stopping and free-flow gaps, 5 m and 35 m.
    lag_s : float
        First-order actuator lag time constant (0 = none, as published).
    """

    dt_s: float = 0.1
    accel_min_mps2: float = -2.5
    accel_max_mps2: float = 2.5
    speed_max_mps: float = 30.0
    gap_min_m: float = 1.0
    gap_stop_m: float = 5.0
    gap_go_m: float = 35.0
    lag_s: float = 0.0

    def __post_init__(self) -> None:
        if not (self.dt_s > 0 and math.isfinite(self.dt_s)):
            raise ConfigError(f"dt_s must be positive, got {self.dt_s}")
        if not self.accel_min_mps2 < 0 < self.accel_max_mps2:
            raise ConfigError("acceleration bounds must satisfy accel_min < 0 < accel_max")
        if self.speed_max_mps <= 0:
            raise ConfigError(f"speed_max_mps must be positive, got {self.speed_max_mps}")
        if not 0 <= self.gap_min_m < self.gap_stop_m < self.gap_go_m:
            raise ConfigError("gaps must satisfy 0 <= gap_min < gap_stop < gap_go")
        if not (self.lag_s >= 0 and math.isfinite(self.lag_s)):
            raise ConfigError(f"actuator lag must be >= 0 s, got {self.lag_s}")

    @property
    def ovm_speed_max_mps(self) -> float:
        """Free-flow speed of the OVM (30 m/s, equal to ``speed_max_mps`` as published)."""
        return 30.0

    @property
    def lag_gain(self) -> float:
        """Fraction of the command error closed per step: ``1 - exp(-dt/tau)`` (1 without lag)."""
        return 1.0 if self.lag_s == 0 else 1.0 - math.exp(-self.dt_s / self.lag_s)


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the paper's multi-objective reward (w1..w5 = -1, -1, -0.1, -5, -10).

    ``r_i = w_gap (gap - d*)^2 + w_speed (v - v*)^2 + w_accel u^2
    + w_safety max(2 gap_stop - gap, 0)^2 + w_power P_i`` with ``P_i`` in kW;
    the safety term is used in training only (published), collision gives ``collision``.
    """

    gap: float = -1.0
    speed: float = -1.0
    accel: float = -0.1
    safety: float = -5.0
    power: float = -10.0
    collision: float = -1000.0
