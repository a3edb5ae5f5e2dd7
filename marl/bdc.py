"""BDC-MARL (the paper's method): binary differential consensus plus QSGD with error feedback.

Each agent has a separate actor and critic (as WAC and DCEA, whose shared parts, the consensus
family, open this file). After every update:

1. **Consensus** on ternary-quantised critic LSTM weights with the front and rear neighbours,
   synchronous: ``w_i <- w_i + eps sum_j (q(w_j) - q(w_i))`` with ``q(w) = sign(w)`` in
   {-1, 0, +1} (:func:`marl.consensus.bdc`). **No scale is sent**: a message is the sign pattern
   only, ``log2(3)`` bits per weight (:func:`marl.quantize.ternary_bits`; 2 bits if bit-packed).
2. **QSGD** (s = 1 by default) on every critic gradient tensor with error feedback, before the
   optimiser step: each agent's tensor is replaced by ``C = Q(g + e) / (1 + omega)`` and keeps
   ``e <- g + e - C`` (the scaling makes error feedback contractive; without it the residual
   diverged and the critic became NaN, see :class:`marl.quantize.ErrorFeedbackQSGD`).
   Payload per bucket and update: one 32-bit norm plus ``log2(2s+1)`` bits per entry.

Both payloads are tallied per agent in the run's ``bits`` and logged; only the first is sent.

Messages (each received by the front and rear neighbours; counted in bits per agent):

- execution, every step: the 5-float vehicle block (160 bits);
- training, every step: the same plus the action index (2 bits) for the neighbours' critics;
  after every update: the sign pattern of the critic-LSTM weights (33,024 ternary symbols,
  log2 3 bits each);
- **not a message**: the QSGD-compressed critic gradients. In the paper's Algorithm 1 each
  agent quantises its own gradient and applies it to its own weights; no agent receives it.
  Their payload is reported as ``local_qsgd_payload_bits_per_agent`` (what a sender would need
  if a parameter server or the neighbours received them) and counted as no communication.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import torch

from infra.errors import ConfigError
from marl.config import A2CConfig, Algorithm
from marl.consensus import bdc, consensus_round
from marl.networks import AgentNet, SeparateActorCriticNet
from marl.quantize import ErrorFeedbackQSGD, compress_gradients_, ternary_bits

if TYPE_CHECKING:
    from marl.config import RunState


# ---------------------------------------------------------------------------- the consensus family
# What WAC, DCEA and BDC share: their config, their network (a separate actor and critic per
# agent) and the consensus round after every update, in which the agents' critic LSTM weights
# (or whole critics) move towards their front and rear neighbours' by a rule of
# :mod:`marl.consensus`, the bits sent tallied per agent. ``wac.py`` and ``dcea.py`` keep only
# their rule and what a round costs.
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


def share_critics(run: RunState, net: AgentNet, rule: Callable[[torch.Tensor], torch.Tensor],
                  bits: Callable[[int], float]) -> None:
    """One synchronous round of ``rule`` on the run's shared critic weights (its rows of
    ``net``); ``bits(n)``, for ``n`` shared weights per agent, is added to the run's consensus
    tally."""
    cfg = run.config
    assert isinstance(cfg, ConsensusConfig) and isinstance(net, SeparateActorCriticNet)
    shared = [p[run.rows] for p in net.shared_critic_parameters(cfg.share_whole_critic)]
    run.bits["consensus"] += bits(consensus_round(shared, rule))


# ---------------------------------------------------------------------------- BDC
@dataclass(frozen=True)
class BDCConfig(ConsensusConfig):
    """BDC-MARL hyper-parameters: the consensus family's plus the communication scheme.

    Attributes
    ----------
    consensus_eps : float
        Step ``eps`` of the binary differential update (paper: "a small positive scalar"; we use
        DCEA's 0.001).
    qsgd_levels : int
        QSGD levels s on the critic gradients (1: ternary entries, as the paper); 0 turns QSGD
        off.
    qsgd_bucket : int or None
        Entries per QSGD bucket, each sent with its own 32-bit norm (QSGD's bucketing; the paper
        is silent). Default 128 (0.25 extra bits per entry). None: one norm per agent tensor
        (measured to fail: ``docs/learner-options.md``).
    packed_bits : bool
        Count 2 bits per ternary weight (bit-packed) instead of ``log2 3``.
    """

    consensus_eps: float = 0.001
    qsgd_levels: int = 1
    qsgd_bucket: int | None = 128
    packed_bits: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.qsgd_levels < 0:
            raise ConfigError(f"qsgd_levels must be >= 0, got {self.qsgd_levels}")
        if self.qsgd_bucket is not None and self.qsgd_bucket < 1:
            raise ConfigError(f"qsgd_bucket must be >= 1 or None, got {self.qsgd_bucket}")


def setup_qsgd(run: RunState) -> None:
    """The run's QSGD compressor with error feedback, on the run's own random stream."""
    cfg = run.config
    assert isinstance(cfg, BDCConfig)
    run.hook_state["qsgd"] = ErrorFeedbackQSGD(max(cfg.qsgd_levels, 1), run.generator,
                                               cfg.qsgd_bucket)


def compress_critic_gradients(run: RunState, net: AgentNet) -> None:
    """Before the optimiser step: every critic gradient tensor replaced by its QSGD
    compression with error feedback (applied locally, its payload tallied)."""
    cfg = run.config
    assert isinstance(cfg, BDCConfig)
    if cfg.qsgd_levels == 0:
        return
    compress_gradients_([p.grad[run.rows] for p in net.critic_parameters() if p.grad is not None],
                        run.hook_state["qsgd"], run.bits)


def binary_consensus(run: RunState, net: AgentNet) -> None:
    """After the optimiser step: one synchronous round of binary differential consensus on
    the shared critic weights (sign patterns sent)."""
    cfg = run.config
    assert isinstance(cfg, BDCConfig)
    share_critics(run, net, functools.partial(bdc, eps=cfg.consensus_eps),
                  lambda n: ternary_bits(n, cfg.packed_bits))


ALGORITHM = Algorithm("bdc", BDCConfig, SeparateActorCriticNet, setup=setup_qsgd,
                      before_step=compress_critic_gradients, after_step=binary_consensus)
