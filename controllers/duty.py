"""``duty``: a fixed schedule of the MARL action set, the reference a learned policy must beat.

Every follower takes OVM action 3 (alpha, beta) = (0.5, 0.5) at every k-th step (steps 0, k,
2k, ...) and action 2 (0, 0.5) otherwise: the spacing term acts one step in k, the speed
matching term always. ``k = 1`` is ``ovm``. Without ``k`` the controller uses the best k in
1..``k_max`` on the validation seeds (fewest collisions, then the best mean reward; a tie goes
to the smaller k), chosen for the run's scenario, N and physics and recorded in
:attr:`DutyController.chosen_k`. It shows what a trivial, open-loop-in-time use of the same four
actions achieves.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from controllers.base import ClosedLoop, Controller, EpisodeContext
from envs.dynamics import action_to_command_mps2
from envs.params import VALIDATION_SEEDS, PlatoonParams, check_decision_seeds
from envs.platoon import PlatoonState
from envs.scenarios import Scenario, as_scenario
from infra.errors import ConfigError


@dataclass(frozen=True)
class DutyConfig:
    """Options of ``duty``.

    Attributes
    ----------
    k : int or None
        Period of action 3 in steps (1 = ``ovm``). None (default): the best k on the
        validation seeds for the run's scenario, N and physics.
    k_max : int
        Largest period searched when ``k`` is None.
    """

    k: int | None = None
    k_max: int = 20

    def __post_init__(self) -> None:
        if self.k is not None and self.k < 1:
            raise ConfigError(f"duty: k must be >= 1, got {self.k}")
        if self.k_max < 1:
            raise ConfigError(f"duty: k_max must be >= 1, got {self.k_max}")


def duty_actions(step: int, k: int | np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Actions ``(B, N)`` of every follower at ``step``: 3 when ``step % k == 0``, else 2; ``k``
    one period, or one per episode ``(B,)``."""
    hit = np.reshape(step % np.asarray(k) == 0, (-1, 1))
    return np.broadcast_to(np.where(hit, 3, 2), shape).astype(np.int64)


_SCORES: dict[tuple, tuple[tuple[int, int, float], ...]] = {}


def duty_scores(
    scenario: Scenario | str,
    n_vehicles: int,
    k_max: int,
    params: PlatoonParams = PlatoonParams(),
    closed_loop: ClosedLoop | None = None,
    seeds: Sequence[int] = VALIDATION_SEEDS,
) -> tuple[tuple[int, int, float], ...]:
    """``(k, collisions, mean reward)`` of every k in 1..k_max on the validation seeds.

    The reward is the benchmark's: per episode the mean over its steps of the sum over agents
    (evaluation form, a collision ends the episode), then the mean over the episodes (the 32
    validation seeds by default). All k run as one batch of ``k_max x len(seeds)`` episodes
    through ``closed_loop``, the benchmark's (:func:`benchmark.rollout.rollout_batch`); results
    are cached per process.

    Raises
    ------
    ConfigError
        Without ``closed_loop`` on a first call, or when any of ``seeds`` is a test seed (choosing
        k is a decision: :func:`envs.params.check_decision_seeds`).
    """
    check_decision_seeds(seeds, "duty (choosing k)")
    seed_list = [int(s) for s in seeds]
    sc = as_scenario(scenario)
    # the length is part of the key: a shortened copy of a scenario (perf timing) has the same id
    key = (sc.id, repr(sorted(sc.options.items())), sc.n_steps, n_vehicles, k_max, params,
           tuple(seed_list))
    if key not in _SCORES:
        if closed_loop is None:
            raise ConfigError(
                "duty: choosing k runs episodes through the benchmark's closed loop; run duty "
                "through benchmark.rollout (cacc-bench run), pass "
                "closed_loop=benchmark.rollout.rollout_batch, or give k")
        schedules = DutyController(k=1)  # no search of its own: a k per episode, ks
        schedules.ks = ks = np.repeat(np.arange(1, k_max + 1), len(seed_list))
        trajs = closed_loop(schedules, sc, n_vehicles, seed_list * k_max, params)
        out = []
        for k in range(1, k_max + 1):
            mine = [t for t, kk in zip(trajs, ks, strict=True) if kk == k]
            out.append((k, sum(bool(t.collided) for t in mine),
                        float(np.mean([t.reward.mean() for t in mine]))))
        _SCORES[key] = tuple(out)
    return _SCORES[key]


def best_k(
    scenario: Scenario | str,
    n_vehicles: int,
    k_max: int = 20,
    params: PlatoonParams = PlatoonParams(),
    closed_loop: ClosedLoop | None = None,
    seeds: Sequence[int] = VALIDATION_SEEDS,
) -> int:
    """The k of :func:`duty_scores` with the fewest collisions, then the best reward (on the
    validation seeds by default; test seeds are refused)."""
    scores = duty_scores(scenario, n_vehicles, k_max, params, closed_loop, seeds)
    return min(scores, key=lambda r: (r[1], -r[2], r[0]))[0]


class DutyController(Controller):
    """OVM action 3 every k-th step, action 2 otherwise, for every follower."""

    name = "duty"
    family = "human"
    drives_mixed = False  # a schedule of the paper's actions, for its homogeneous platoon
    needs_leader = True
    batch_invariant = True
    config_cls = DutyConfig
    config: DutyConfig

    def __init__(self, **options: object) -> None:
        super().__init__(**options)
        self.chosen_k: int | None = self.config.k
        #: the search's batch (:func:`duty_scores`): a k per episode, instead of ``chosen_k``
        self.ks: np.ndarray | None = None

    def reset(self, ctx: EpisodeContext) -> None:
        self.params = ctx.params
        if self.config.k is None:
            self.chosen_k = best_k(ctx.scenario, ctx.n_vehicles, self.config.k_max, ctx.params,
                                   ctx.closed_loop)
        self.t = 0

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        k = self.chosen_k if self.ks is None else self.ks
        assert k is not None
        actions = duty_actions(self.t, k, state.gap_m.shape)
        self.t += 1
        return action_to_command_mps2(
            actions, state.gap_m, state.speed_mps, state.pred_speed_mps, self.params
        )
