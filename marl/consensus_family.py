"""What the consensus learners WAC, DCEA and BDC share: their config, their network and the
consensus round after every update.

Each agent has a separate actor and critic (:class:`marl.networks.SeparateActorCriticNet`);
after every optimiser step the agents' critic LSTM weights (or whole critics) move towards their
front and rear neighbours' in one synchronous round of a rule of :mod:`marl.consensus`, and the
bits sent are tallied per agent. Each algorithm's file keeps only what differs: its rule, what a
round costs in bits, its own options, and (BDC) its gradient compression.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import torch

from infra.errors import ConfigError
from marl.config import A2CConfig
from marl.consensus import consensus_round
from marl.networks import AgentNet, SeparateActorCriticNet

if TYPE_CHECKING:
    from marl.config import RunState


@dataclass(frozen=True)
class ConsensusConfig(A2CConfig):
    """Hyper-parameters of the consensus family (IA2C family reward scale, no reward sharing).

    Attributes
    ----------
    share_whole_critic : bool
        Share the whole critic instead of its LSTM only (published: LSTM).

    A ``consensus_eps`` field of a subclass (DCEA, BDC: the step ``eps`` of the differential
    update, paper 0.001) must lie in (0, 0.5] (larger steps are unstable).
    """

    reward_scale: float = 1.0 / 800.0
    #: the published consensus configs share no reward (``coop_gamma = 0``) on every scenario
    PUBLISHED_REWARD_ALPHA: ClassVar[dict[str, float]] = {"catchup": 0.0, "slowdown": 0.0}
    DEFAULT_REWARD_ALPHA: ClassVar[float] = 0.0
    share_whole_critic: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        eps = getattr(self, "consensus_eps", None)
        if eps is not None and not 0 < eps <= 0.5:
            raise ConfigError(f"consensus_eps must lie in (0, 0.5], got {eps}")


def build_net(config: ConsensusConfig, n_agents: int, with_critic: bool = True,
              generator: torch.Generator | None = None) -> SeparateActorCriticNet:
    """Separate actor and critic per agent."""
    return SeparateActorCriticNet(n_agents, config.hidden, with_critic, generator)


Rule = Callable[[torch.Tensor], torch.Tensor]


def share_critics(run: RunState, net: AgentNet, rule: Rule, bits: Callable[[int], float]) -> None:
    """One synchronous round of ``rule`` on the run's shared critic weights (its rows of
    ``net``); ``bits(n)``, for ``n`` shared weights per agent, is added to the run's consensus
    tally."""
    cfg = run.config
    assert isinstance(cfg, ConsensusConfig) and isinstance(net, SeparateActorCriticNet)
    shared = [p[run.rows] for p in net.shared_critic_parameters(cfg.share_whole_critic)]
    run.bits["consensus"] += bits(consensus_round(shared, rule))
