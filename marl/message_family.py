"""What the learned-message learners DIAL and CommNet share: their config and their network.

Each agent broadcasts a 64-float message derived from its previous LSTM hidden state; the
receiver adds a mapping of its front and rear neighbours' messages to its LSTM input gates
(:meth:`marl.networks.SharedTrunkNet.message_gates`). During training the messages are re-derived
from the recomputed states, so the receiver's loss reaches the sender's weights within a segment
(``differentiable_messages``). Rewards are scaled by 1/5000 and shared globally, as the published
DIAL/CommNet family. Each algorithm's file keeps only what differs: what it sends and how the
receiver maps it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from marl.config import A2CConfig
from marl.networks import SharedTrunkNet


@dataclass(frozen=True)
class MessageConfig(A2CConfig):
    """Hyper-parameters of DIAL and CommNet: reward scale 1/5000; global reward (alpha = 1) on
    catchup and slowdown, as their published configs."""

    reward_scale: float = 1.0 / 5000.0
    PUBLISHED_REWARD_ALPHA: ClassVar[dict[str, float]] = {"catchup": 1.0, "slowdown": 1.0}


class MessageNet(SharedTrunkNet):
    """The IA2C trunk with a ``hidden``-float message through which gradients flow; subclasses
    add the sender's :meth:`message` and the receiver's :meth:`message_gates`."""

    differentiable_messages = True

    def __init__(
        self,
        n_agents: int,
        hidden: int = 64,
        with_critic: bool = True,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__(n_agents, hidden, with_critic, generator=generator)
        self.msg_width = hidden
