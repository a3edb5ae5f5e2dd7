"""n-step returns of the on-policy learners, with reward sharing.

Shapes: ``T`` steps of a segment, ``B`` parallel episodes, ``N`` agents. Everything here is a
pure, vectorised function of torch tensors; ``tests/test_marl_kernels.py`` checks it against a
slow loop.
"""

from __future__ import annotations

import torch


def sharing_matrix(n_agents: int, alpha: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``(N, N)`` weights ``alpha^|i-j|`` (alpha = 0: own reward only, alpha = 1: global sum)."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"reward-sharing alpha must lie in [0, 1], got {alpha}")
    idx = torch.arange(n_agents)
    dist = (idx[:, None] - idx[None, :]).abs().to(dtype)
    if alpha == 0.0:
        return torch.eye(n_agents, dtype=dtype)
    return torch.pow(torch.tensor(alpha, dtype=dtype), dist)


def share_rewards(reward: torch.Tensor, alpha: float) -> torch.Tensor:
    """Shared rewards ``r'_i = sum_j alpha^|i-j| r_j`` over the last (agent) axis.

    Parameters
    ----------
    reward : (..., N)
        Per-agent rewards.
    alpha : float
        Spatial discount in [0, 1].
    """
    w = sharing_matrix(reward.shape[-1], alpha, reward.dtype)
    return reward @ w.T


def nstep_returns(
    reward: torch.Tensor,
    bootstrap: torch.Tensor,
    terminal: torch.Tensor,
    gamma: float,
) -> torch.Tensor:
    """Discounted n-step returns of a segment, bootstrapped from the value after its last step.

    ``R_t = r_t + gamma (1 - terminal_t) R_{t+1}`` with ``R_T = bootstrap``: a terminal step
    (the episode ended after it) cuts both the later rewards and the bootstrap.

    Parameters
    ----------
    reward : (T, B, N)
        Rewards (already shared and scaled).
    bootstrap : (B, N)
        Value estimate of the observation after the last step (anything where terminal).
    terminal : (T, B) or (T, B, N) bool/float
        1 where the episode ended after step t.
    gamma : float
        Discount.

    Returns
    -------
    (T, B, N)
    """
    t_len = reward.shape[0]
    term = terminal.to(reward.dtype)
    if term.dim() == reward.dim() - 1:
        term = term.unsqueeze(-1)
    term = term.expand_as(reward)
    # D_k = number of terminals strictly before step k, k = 0..T
    d = torch.cat([torch.zeros_like(term[:1]), torch.cumsum(term, 0)], 0)  # (T+1, B, N)
    steps = torch.arange(t_len + 1, dtype=reward.dtype)
    lag = steps[None, :] - steps[:t_len, None]  # (T, T+1): k - t
    disc = torch.where(
        lag >= 0, torch.pow(torch.tensor(gamma, dtype=reward.dtype), lag.clamp(min=0)), 0.0
    )
    # k contributes to R_t iff k >= t and no terminal in t..k-1, i.e. D_k == D_t
    same = (d[None, :, ...] == d[:t_len, None, ...]).to(reward.dtype)  # (T, T+1, B, N)
    weights = disc[:, :, None, None] * same
    values = torch.cat([reward, bootstrap.unsqueeze(0)], 0)  # (T+1, B, N)
    return (weights * values.unsqueeze(0)).sum(1)
