"""Acting with a trained (or untrained) policy: build an algorithm's acting network, load a
checkpoint's weights into it, and pick actions, greedy or sampled.

What :mod:`controllers.policy` and the validation loop need, and nothing of the learner: this
module imports the algorithms' configs and networks (:mod:`marl.config`, :mod:`marl.networks`),
never :mod:`marl.a2c` or the population trainer.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from marl.config import Algorithm, algorithm, config_from_dict
from marl.learners import PAPER_ALGORITHMS
from marl.networks import AgentNet, State, exchange

__all__ = [
    "PAPER_ALGORITHMS",
    "Algorithm",
    "acting_net",
    "algorithm",
    "config_from_dict",
    "exchange",
    "policy_actions",
    "sample_from_logits",
    "untrained_net",
]


def untrained_net(algo: str, n_vehicles: int, seed: int) -> AgentNet:
    """``algo``'s acting network (no critic) of ``n_vehicles`` agents with freshly initialised
    weights from ``seed`` and the default config (the "untrained policy" reference)."""
    spec = algorithm(algo)
    gen = torch.Generator().manual_seed(seed)
    return spec.build_net(spec.config_cls(), n_vehicles, with_critic=False, generator=gen)


def acting_net(algo: str, n_vehicles: int, data: dict[str, Any]) -> AgentNet:
    """``algo``'s acting network of ``n_vehicles`` agents with a checkpoint's config and weights
    (``data``: what :func:`marl.checkpoint.load_checkpoint` returns), in evaluation mode."""
    spec = algorithm(algo)
    config = config_from_dict(spec, data["config"])
    net = spec.build_net(config, n_vehicles, with_critic=False)
    net.load_state_dict(data["weights"], strict=True)
    net.eval()
    return net


def sample_from_logits(logits: torch.Tensor, uniforms: np.ndarray) -> np.ndarray:
    """Inverse-CDF draws from ``softmax(logits)``: logits ``(N, B, A)``, uniforms ``(B, N)`` in
    [0, 1) -> actions ``(B, N)`` (the first action whose cumulative probability exceeds u)."""
    probs = torch.softmax(logits.to(torch.float64), -1).permute(1, 0, 2).numpy()  # (B, N, A)
    cdf = np.cumsum(probs, axis=-1)
    actions = (uniforms[..., None] >= cdf[..., :-1]).sum(-1)
    return actions.astype(np.int64)


@torch.no_grad()
def policy_actions(
    net: AgentNet,
    obs_np: np.ndarray,
    state: State,
    messages: tuple | None = None,
    uniforms: np.ndarray | None = None,
) -> tuple[np.ndarray, State]:
    """Actions ``(B, N)`` for observations ``(B, N, 15)``: greedy (argmax) when ``uniforms`` is
    None, else drawn from the policy with one uniform ``(B, N)`` per agent
    (:func:`sample_from_logits`). Messages default to instant, lossless exchange."""
    obs = torch.from_numpy(np.ascontiguousarray(obs_np, dtype=np.float32)).transpose(0, 1)
    front, rear = exchange(net, state) if messages is None else messages
    logits, _, state = net.act_step(obs.contiguous(), state, front, rear)
    if uniforms is None:
        return logits.argmax(-1).T.numpy(), state
    return sample_from_logits(logits, uniforms), state
