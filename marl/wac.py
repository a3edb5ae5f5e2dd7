"""WAC: weight-averaging consensus of the critics' LSTM weights between chain neighbours.

Each agent has a separate actor (FC 64 -> LSTM 64 -> logits) and critic (FC 64 -> LSTM 64 ->
value with the neighbours' one-hot actions). After every update, each agent's critic LSTM weights
become the mean of its own and its front and rear neighbours' weights. The round is synchronous:
every agent averages the pre-round snapshot (:func:`marl.consensus.wac`), unlike the published
code which averaged in place agent by agent. Payload: 32 bits per shared weight per round.

Messages (each received by the front and rear neighbours; counted in bits per agent):

- execution, every step: the 5-float vehicle block (160 bits);
- training, every step: the same plus the action index (2 bits) for the neighbours' critics;
  after every update: the critic-LSTM weights (33,024 floats, 32 bits each).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from marl.a2c import (
    FLOAT_BITS,
    A2CConfig,
    AgentNet,
    Algorithm,
    Run,
    SeparateActorCriticNet,
)
from marl.consensus import consensus_round, wac


@dataclass(frozen=True)
class WACConfig(A2CConfig):
    """WAC hyper-parameters (IA2C family) plus what is shared.

    Attributes
    ----------
    share_whole_critic : bool
        Share the whole critic instead of its LSTM only (published: LSTM).
    """

    reward_scale: float = 1.0 / 800.0
    #: the published consensus configs share no reward (``coop_gamma = 0``) on every scenario
    PUBLISHED_REWARD_ALPHA: ClassVar[dict[str, float]] = {"catchup": 0.0, "slowdown": 0.0}
    DEFAULT_REWARD_ALPHA: ClassVar[float] = 0.0
    share_whole_critic: bool = False


def build_net(config: WACConfig, n_agents: int, with_critic: bool = True,
              generator: torch.Generator | None = None) -> SeparateActorCriticNet:
    """Separate actor and critic per agent."""
    return SeparateActorCriticNet(n_agents, config.hidden, with_critic, generator)


def average_critics(run: Run, net: AgentNet) -> None:
    """After every update: one synchronous averaging round of the shared critic weights with
    the front and rear neighbours (32-bit floats sent)."""
    cfg = run.config
    assert isinstance(cfg, WACConfig) and isinstance(net, SeparateActorCriticNet)
    shared = [p[run.rows] for p in net.shared_critic_parameters(cfg.share_whole_critic)]
    run.bits["consensus"] += consensus_round(shared, wac) * FLOAT_BITS


ALGORITHM = Algorithm("wac", WACConfig, build_net, after_step=average_critics)
