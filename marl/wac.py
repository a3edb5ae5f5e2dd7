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
from typing import TYPE_CHECKING

from marl.bdc import ConsensusConfig, share_critics
from marl.config import Algorithm
from marl.consensus import wac
from marl.networks import FLOAT_BITS, AgentNet, SeparateActorCriticNet

if TYPE_CHECKING:
    from marl.config import RunState


@dataclass(frozen=True)
class WACConfig(ConsensusConfig):
    """WAC hyper-parameters: those of the consensus family
    (:class:`marl.bdc.ConsensusConfig`), nothing else."""


def average_critics(run: RunState, net: AgentNet) -> None:
    """After every update: one synchronous averaging round of the shared critic weights with
    the front and rear neighbours (32-bit floats sent)."""
    share_critics(run, net, wac, lambda n: n * FLOAT_BITS)


ALGORITHM = Algorithm("wac", WACConfig, SeparateActorCriticNet, after_step=average_critics)
