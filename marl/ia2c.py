"""IA2C: independent advantage actor-critic, one agent per follower (published baseline).

Each agent sees its own and its neighbours' vehicle blocks (15 numbers), encodes them with an FC
64 (ReLU) layer and an LSTM 64, and reads 4 action logits and (with the neighbours' current
actions, one-hot) a state value from the LSTM output. No learned communication: at execution an
agent only sends its 5-float vehicle block to its neighbours. The learner is
:mod:`marl.a2c` (n-step A2C with reward sharing); this file is the whole algorithm.

Messages (each received by the front and rear neighbours; counted in bits per agent):

- execution, every step: the 5-float vehicle block (160 bits);
- training, every step: the same block, plus the action index (2 bits) that the neighbours'
  critics take as input; no consensus, no gradients.
"""

from __future__ import annotations

from dataclasses import dataclass

from marl.config import A2CConfig, Algorithm
from marl.networks import SharedTrunkNet


@dataclass(frozen=True)
class IA2CConfig(A2CConfig):
    """IA2C hyper-parameters: those of :class:`marl.config.A2CConfig` (paper values).

    ``reward_scale`` 1/800 (published IA2C family); ``reward_alpha`` None: the published
    configs' value per scenario (global reward on catchup, own reward on slowdown).
    """

    reward_scale: float = 1.0 / 800.0


class IA2CNet(SharedTrunkNet):
    """FC 64 -> LSTM 64 -> actor head and critic head, N agents batched."""


ALGORITHM = Algorithm("ia2c", IA2CConfig, IA2CNet)
