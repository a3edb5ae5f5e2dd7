"""DCEA: differential consensus (unquantised) of the critics' LSTM weights.

As WAC (separate actor and critic per agent), but after every update each agent moves its critic
LSTM weights towards its neighbours': ``w_i <- w_i + eps sum_j (w_j - w_i)``, eps = 0.001, over
front and rear neighbours, synchronously (:func:`marl.consensus.dcea`). Payload: 32 bits per
shared weight per round.

Messages (each received by the front and rear neighbours; counted in bits per agent):

- execution, every step: the 5-float vehicle block (160 bits);
- training, every step: the same plus the action index (2 bits) for the neighbours' critics;
  after every update: the critic-LSTM weights (33,024 floats, 32 bits each).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import ClassVar

import torch

from envs.errors import ConfigError
from marl.a2c import (
    FLOAT_BITS,
    A2CConfig,
    AgentNet,
    Algorithm,
    Run,
    SeparateActorCriticNet,
)
from marl.consensus import consensus_round, dcea


@dataclass(frozen=True)
class DCEAConfig(A2CConfig):
    """DCEA hyper-parameters (IA2C family) plus the consensus step.

    Attributes
    ----------
    consensus_eps : float
        Step ``eps`` of the differential update (paper 0.001; at most 0.5 for stability).
    share_whole_critic : bool
        Share the whole critic instead of its LSTM only (published: LSTM).
    """

    reward_scale: float = 1.0 / 800.0
    #: the published consensus configs share no reward (``coop_gamma = 0``) on every scenario
    PUBLISHED_REWARD_ALPHA: ClassVar[dict[str, float]] = {"catchup": 0.0, "slowdown": 0.0}
    DEFAULT_REWARD_ALPHA: ClassVar[float] = 0.0
    consensus_eps: float = 0.001
    share_whole_critic: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0 < self.consensus_eps <= 0.5:
            raise ConfigError(f"consensus_eps must lie in (0, 0.5], got {self.consensus_eps}")


def build_net(config: DCEAConfig, n_agents: int, with_critic: bool = True,
              generator: torch.Generator | None = None) -> SeparateActorCriticNet:
    """Separate actor and critic per agent."""
    return SeparateActorCriticNet(n_agents, config.hidden, with_critic, generator)


def differential_consensus(run: Run, net: AgentNet) -> None:
    """After every update: one synchronous differential round on the shared critic weights."""
    cfg = run.config
    assert isinstance(cfg, DCEAConfig) and isinstance(net, SeparateActorCriticNet)
    shared = [p[run.rows] for p in net.shared_critic_parameters(cfg.share_whole_critic)]
    rule = functools.partial(dcea, eps=cfg.consensus_eps)
    run.bits["consensus"] += consensus_round(shared, rule) * FLOAT_BITS


ALGORITHM = Algorithm("dcea", DCEAConfig, build_net, after_step=differential_consensus)
