"""CommNet: agents broadcast their hidden states; each adds the mapped mean of its neighbours'.

Every agent sends its previous LSTM hidden state (64 floats). The receiver averages the hidden
states of the neighbours it has (front and rear; one at the ends of the chain), maps the mean
with a linear layer and adds it to its encoded observation before the LSTM. Gradients flow
through the communicated states (within a segment). Reward scale 1/5000, global reward (alpha 1).

Messages (each received by the front and rear neighbours; counted in bits per agent):

- execution, every step: the 5-float vehicle block and the 64-float hidden state (2,208 bits);
- training, every step: the same, the action index (2 bits) for the neighbours' critics, and
  back to each neighbour the gradient of its own loss with respect to that neighbour's state
  (64 floats each, 4,096 bits).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from marl.config import Algorithm
from marl.consensus import degree
from marl.dial import MessageConfig, MessageNet
from marl.layers import BatchedLinear


@dataclass(frozen=True)
class CommNetConfig(MessageConfig):
    """CommNet hyper-parameters: those of the learned-message family
    (:class:`marl.dial.MessageConfig`: reward scale 1/5000, global reward)."""


class CommNetNet(MessageNet):
    """IA2C trunk plus the communication layer ``C mean_j h_j``."""

    def __init__(self, n_agents, hidden=64, with_critic=True, generator=None):
        super().__init__(n_agents, hidden, with_critic, generator)
        self.comm = BatchedLinear(n_agents, hidden, hidden, 1.0, generator)
        deg = degree(n_agents, torch.zeros(n_agents, 1, 1)).clamp(min=1.0)
        self.register_buffer("inv_degree", 1.0 / deg, persistent=False)

    def message(self, state):
        return state["h"]

    def message_gates(self, state, front, rear):
        assert front is not None and rear is not None
        mean = (front + rear) * self.inv_degree
        return self.lstm.input_gates(self.comm(mean), bias=False)


ALGORITHM = Algorithm("commnet", CommNetConfig, CommNetNet)
