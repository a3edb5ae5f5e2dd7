"""Validation of learned policies through the benchmark's own closed loop.

Training selects its snapshots with :func:`validation_evaluator`: the weights being trained act
through :class:`controllers.policy.PolicyController` (:meth:`~controllers.policy.PolicyController.from_net`:
a paper learner's network or a shared learner's actor) in :func:`benchmark.rollout.rollout_batch`,
so a validation score is exactly what ``cacc-bench run`` would report for those weights on those
seeds (the episodes run batched; the same code, not a second loop).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from benchmark.rollout import rollout_batch
from envs.channel import ChannelConfig
from envs.params import VALIDATION_SEEDS, check_decision_seeds
from envs.scenarios import Scenario, as_scenario


def evaluate_policy(
    algo: str,
    net: Any,
    scenario: str | Scenario,
    n_vehicles: int,
    seeds: Sequence[int],
    mode: str = "sampled",
    channel: ChannelConfig = ChannelConfig(),
) -> dict[str, float]:
    """Episodes of an in-memory policy network in the benchmark's closed loop (on ``scenario``,
    built or a label: :func:`envs.scenarios.as_scenario`; V2V through ``channel``).

    Returns
    -------
    dict
        ``reward`` and ``tracking_reward``: means over episodes of each episode's mean over steps
        of the sum over agents (the ``runs.csv`` columns); ``collisions``: episodes that collided;
        ``episodes``.
    """
    from controllers.policy import PolicyController

    sc = as_scenario(scenario)
    ctrl = PolicyController.from_net(algo, net, sc.id, n_vehicles, mode)
    trajs = rollout_batch(ctrl, sc, n_vehicles, seeds, channel=channel)
    return {
        "reward": float(np.mean([t.reward.mean() for t in trajs])),
        "tracking_reward": float(np.mean([t.tracking_reward.mean() for t in trajs])),
        "collisions": float(sum(t.collided for t in trajs)),
        "episodes": float(len(trajs)),
    }


def validation_evaluator(
    algo: str, scenario: str | Scenario | Sequence[Scenario], n_vehicles: int,
    seeds: Sequence[int] = VALIDATION_SEEDS, channel: ChannelConfig = ChannelConfig(),
) -> Callable[[Any, str], dict[str, float]]:
    """The evaluator the trainers take (:func:`marl.selection.run_training`,
    :func:`marl.ppo.train`, :func:`marl.distill.distill`): ``(net, mode) -> summary``, V2V
    through ``channel`` (a shared learner's: :attr:`marl.ppo_nets.PPOConfig.validation_channel`).
    Given several scenarios (a policy trained on several roads:
    :meth:`marl.ppo_nets.PPOConfig.validation_roads`), the summary is over all of them: the
    mean of their rewards, their collisions and episodes summed (a ring at its own N).

    Its scores choose the kept snapshot (and, through ``cacc-bench tune``, the tuned configs):
    a decision, so test seeds are refused (:func:`envs.params.check_decision_seeds`).

    Raises
    ------
    ConfigError
        When any of ``seeds`` is a test seed (:data:`envs.params.TEST_SEEDS`).
    """
    check_decision_seeds(seeds, "benchmark.policy_eval.validation_evaluator")
    seeds = tuple(int(s) for s in seeds)
    roads = ([as_scenario(scenario)] if isinstance(scenario, str | Scenario)
             else list(scenario))  # built once, for every snapshot it scores
    sizes = [sc.default_vehicles if sc.ring else n_vehicles for sc in roads]

    def evaluate(net: Any, mode: str) -> dict[str, float]:
        scores = [evaluate_policy(algo, net, sc, n, seeds, mode, channel)
                  for sc, n in zip(roads, sizes, strict=True)]
        if len(scores) == 1:
            return scores[0]
        return {"reward": float(np.mean([s["reward"] for s in scores])),
                "tracking_reward": float(np.mean([s["tracking_reward"] for s in scores])),
                "collisions": float(sum(s["collisions"] for s in scores)),
                "episodes": float(sum(s["episodes"] for s in scores))}

    return evaluate
