"""``ippo-bdc``: BDC-MARL's communication scheme on the acceleration-action learner.

The PPO loop of :mod:`marl.ppo`, with what the paper's BDC adds (Section III of the paper;
:mod:`marl.bdc` on the paper's learner): an actor and a local critic per follower (so the policy
is trained for one N), each critic gradient compressed by QSGD with error feedback before the
Adam step (applied locally, as :func:`marl.bdc.compress_critic_gradients`, its payload tallied
per agent), and after every step one synchronous round of binary differential consensus on the
critics' weights with the front and rear neighbours (ternary signs, ``log2 3`` bits a weight).
"""

from __future__ import annotations

import functools

import torch

from marl.consensus import bdc, consensus_round
from marl.ppo import PPOTrainer, Rollout
from marl.quantize import ErrorFeedbackQSGD, compress_gradients_, ternary_bits


class IPPOBDCTrainer(PPOTrainer):
    """:class:`marl.ppo.PPOTrainer` with a network per follower, compressed critic gradients
    and consensus on the critics."""

    def setup(self) -> None:
        """The compressor of the critic gradients and the bit tallies (per agent)."""
        cfg = self.cfg
        self.qsgd = ErrorFeedbackQSGD(max(cfg.qsgd_levels, 1), self.gen, cfg.qsgd_bucket)
        self.bits = {"consensus": 0.0, "qsgd_local": 0.0}

    def rows(self, ro: Rollout, adv: torch.Tensor, ret: torch.Tensor
             ) -> tuple[list[torch.Tensor], int]:
        """One row per live episode-step, holding its N agents (each agent's own network
        reads its column); the minibatch holds as many agent-steps as the shared learner's."""
        keep = ro.live.all(-1).reshape(-1)
        t_b = ro.reward.shape[0] * ro.reward.shape[1]
        return ([x.reshape(t_b, *x.shape[2:])[keep]
                 for x in (ro.obs, ro.critic_obs, ro.action, ro.logp, adv, ret)],
                max(1, self.cfg.minibatch_rows // self.n))

    def before_step(self) -> None:
        """Every critic gradient replaced by its QSGD compression with error feedback."""
        if self.cfg.qsgd_levels:
            compress_gradients_([p.grad for p in self.critic.parameters() if p.grad is not None],
                                self.qsgd, self.bits)

    def after_step(self) -> None:
        """One synchronous BDC round on the critics' weights."""
        n_weights = consensus_round(self.critic.parameters(),
                                    functools.partial(bdc, eps=self.cfg.consensus_eps))
        self.bits["consensus"] += ternary_bits(n_weights)

    def bits_per_agent(self) -> dict[str, float]:
        """Bits each agent sent in training: consensus signs and compressed gradients."""
        return self.bits


#: The trainer of ``ippo-bdc`` (the learner registry names this module).
TRAINER = IPPOBDCTrainer
