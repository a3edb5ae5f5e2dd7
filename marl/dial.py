"""DIAL: differentiable inter-agent learning with learned 64-float messages.

Every agent encodes its previous LSTM hidden state into a message ``m_i = tanh(W_m h_i + b)``
(64 floats) and broadcasts it. The receiver maps its front and rear neighbours' messages
(zeros where missing) with a linear layer and adds the result to its encoded observation before
the LSTM. During training the messages are re-derived from the recomputed hidden states, so the
gradients of the receiver's loss flow into the sender's network (within an n-step segment).
Rewards are scaled by 1/5000 and shared globally (alpha = 1), as the published DIAL/CommNet family.

Messages (each received by the front and rear neighbours; counted in bits per agent):

- execution, every step: the 5-float vehicle block and the 64-float message (2,208 bits);
- training, every step: the same, the action index (2 bits) for the neighbours' critics, and
  back to each neighbour the gradient of its own loss with respect to that neighbour's message
  (64 floats each, 4,096 bits).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from marl.config import A2CConfig, Algorithm
from marl.layers import BatchedLinear
from marl.networks import SharedTrunkNet


# ---------------------------------------------------------------------------- the message family
# What DIAL and CommNet (``commnet.py``) share: their config and a network whose messages,
# derived from the sender's previous LSTM hidden state, enter the receiver's LSTM input gates
# (:meth:`marl.networks.SharedTrunkNet.message_gates`) and carry gradients within a segment.
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

    def __init__(self, n_agents: int, hidden: int = 64, with_critic: bool = True,
                 generator: torch.Generator | None = None) -> None:
        super().__init__(n_agents, hidden, with_critic, generator=generator)
        self.msg_width = hidden


# ---------------------------------------------------------------------------- DIAL
@dataclass(frozen=True)
class DIALConfig(MessageConfig):
    """DIAL hyper-parameters: those of the message family (:class:`MessageConfig`)."""


class DIALNet(MessageNet):
    """IA2C trunk plus a sender-side message encoder and a receiver-side message layer."""

    def __init__(self, n_agents, hidden=64, with_critic=True, generator=None):
        super().__init__(n_agents, hidden, with_critic, generator)
        self.msg_out = BatchedLinear(n_agents, hidden, hidden, 1.0, generator)
        self.msg_in = BatchedLinear(n_agents, 2 * hidden, hidden, 1.0, generator)

    def message(self, state):
        return torch.tanh(self.msg_out(state["h"]))

    def message_gates(self, state, front, rear):
        assert front is not None and rear is not None
        m = self.msg_in(torch.cat([front, rear], dim=-1))
        return self.lstm.input_gates(m, bias=False)


ALGORITHM = Algorithm("dial", DIALConfig, DIALNet)
