"""FPrint: IA2C plus the neighbours' previous-step policies ("fingerprints") as extra input.

Every agent broadcasts its policy vector of the previous step (4 floats) next to its vehicle
block. The receiver encodes the front and rear fingerprints (zeros where there is no neighbour)
with a separate FC 64 (ReLU) and concatenates that with its encoded observation before the LSTM
(input 128). Fingerprints are inputs, not a channel for gradients.

Messages (each received by the front and rear neighbours; counted in bits per agent):

- execution, every step: the 5-float vehicle block and the 4-float fingerprint (288 bits);
- training, every step: the same, plus the action index (2 bits) for the neighbours' critics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from marl.config import A2CConfig, Algorithm
from marl.layers import BatchedLinear
from marl.networks import N_ACTIONS, SharedTrunkNet, State


@dataclass(frozen=True)
class FPrintConfig(A2CConfig):
    """FPrint hyper-parameters (IA2C family: reward scale 1/800, published reward sharing)."""

    reward_scale: float = 1.0 / 800.0


class FPrintNet(SharedTrunkNet):
    """IA2C network with a fingerprint encoder: LSTM input = [FC(obs), FC(fingerprints)]."""

    msg_width = N_ACTIONS

    def __init__(self, n_agents, hidden=64, with_critic=True, generator=None):
        super().__init__(n_agents, hidden, with_critic, lstm_in=2 * hidden, generator=generator)
        self.fp_fc = BatchedLinear(n_agents, 2 * N_ACTIONS, hidden, math.sqrt(2.0), generator)

    def initial_state(self, batch: int) -> State:
        state = super().initial_state(batch)
        state["pi"] = torch.zeros(self.n_agents, batch, N_ACTIONS, device=self.device)
        return state

    def message(self, state):
        return state["pi"]

    def message_gates(self, state, front, rear):
        assert front is not None and rear is not None
        fp = torch.relu(self.fp_fc(torch.cat([front, rear], dim=-1)))
        return self.lstm.input_gates(fp, slice(self.hidden, 2 * self.hidden), bias=False)

    def after_policy(self, state, logits):
        return {**state, "pi": torch.softmax(logits, -1).detach()}


ALGORITHM = Algorithm("fprint", FPrintConfig, FPrintNet)
