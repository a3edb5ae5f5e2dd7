"""Synchronous consensus rounds on stacked per-agent tensors ``(N, ...)``, chain neighbours.

Agent ``i``'s neighbours are ``i-1`` and ``i+1`` (front and rear vehicle; the ends have one).
Every rule reads only the pre-round snapshot and returns a new tensor, so all agents update at
once (the published code averaged in place, agent by agent, so agent i+1 saw agent i's updated
weights: not here).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch

from marl.quantize import ternary


def neighbour_sum(w: torch.Tensor) -> torch.Tensor:
    """``sum_{j in {i-1, i+1}} w_j`` for every agent ``i`` (missing neighbours count 0)."""
    out = torch.zeros_like(w)
    out[1:] += w[:-1]
    out[:-1] += w[1:]
    return out


def degree(n_agents: int, like: torch.Tensor) -> torch.Tensor:
    """Number of chain neighbours of each agent, shaped to broadcast against ``like`` (N, ...)."""
    deg = torch.full((n_agents,), 2.0, dtype=like.dtype, device=like.device)
    if n_agents >= 1:
        deg[0] -= 1
        deg[-1] -= 1
    return deg.reshape((n_agents,) + (1,) * (like.dim() - 1))


def wac(w: torch.Tensor) -> torch.Tensor:
    """Weight-averaging consensus: mean of own and neighbours' weights."""
    return (w + neighbour_sum(w)) / (1.0 + degree(w.shape[0], w))


def dcea(w: torch.Tensor, eps: float) -> torch.Tensor:
    """Differential consensus ``w_i + eps sum_j (w_j - w_i)`` (unquantised)."""
    return w + eps * (neighbour_sum(w) - degree(w.shape[0], w) * w)


def bdc(
    w: torch.Tensor, eps: float, q: Callable[[torch.Tensor], torch.Tensor] = ternary
) -> torch.Tensor:
    """Binary differential consensus ``w_i + eps sum_j (q(w_j) - q(w_i))``, ``q = sign``."""
    qw = q(w)
    return w + eps * (neighbour_sum(qw) - degree(w.shape[0], w) * qw)


@torch.no_grad()
def consensus_round(
    params: Iterable[torch.Tensor], rule: Callable[[torch.Tensor], torch.Tensor]
) -> int:
    """Apply ``rule`` to every stacked parameter from its snapshot; returns weights per agent."""
    n_per_agent = 0
    for p in params:
        p.copy_(rule(p.detach().clone()))
        n_per_agent += p[0].numel()
    return n_per_agent
