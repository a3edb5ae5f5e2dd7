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
from typing import TYPE_CHECKING

from marl.bdc import ConsensusConfig, share_critics
from marl.config import Algorithm
from marl.consensus import dcea
from marl.networks import FLOAT_BITS, AgentNet, SeparateActorCriticNet

if TYPE_CHECKING:
    from marl.config import RunState


@dataclass(frozen=True)
class DCEAConfig(ConsensusConfig):
    """DCEA hyper-parameters: the consensus family's plus the consensus step.

    Attributes
    ----------
    consensus_eps : float
        Step ``eps`` of the differential update (paper 0.001; at most 0.5 for stability).
    """

    consensus_eps: float = 0.001


def differential_consensus(run: RunState, net: AgentNet) -> None:
    """After every update: one synchronous differential round on the shared critic weights
    (32-bit floats sent)."""
    cfg = run.config
    assert isinstance(cfg, DCEAConfig)
    share_critics(run, net, functools.partial(dcea, eps=cfg.consensus_eps),
                  lambda n: n * FLOAT_BITS)


ALGORITHM = Algorithm("dcea", DCEAConfig, SeparateActorCriticNet, after_step=differential_consensus)
