"""Batched per-agent layers: N agents' separate weights stacked, applied as one tensor op.

Layout on the hot path is agent-major: activations ``(N, B, features)``. A
:class:`BatchedLinear` holds ``weight (N, in, out)`` and ``bias (N, out)`` and computes
``x @ W + b`` with one ``torch.baddbmm``; :class:`BatchedLSTMCell` does the same for an LSTM
cell (gate order i, f, g, o as ``torch.nn.LSTMCell``; one combined bias). Both equal a loop over
separate ``torch.nn.Linear`` / ``torch.nn.LSTMCell`` agents (tested).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from marl import arithmetic


def module_tensors(module: nn.Module) -> dict[str, torch.Tensor]:
    """Every parameter and buffer of ``module`` by name (a state dict leaves out the
    non-persistent buffers, which training needs)."""
    return dict([*module.named_parameters(), *module.named_buffers()])


def _orthogonal_stack(
    n: int, rows: int, cols: int, gain: float, generator: torch.Generator | None = None
) -> torch.Tensor:
    w = torch.empty(n, rows, cols)
    for i in range(n):  # initialisation only, not on the hot path
        nn.init.orthogonal_(w[i], gain=gain, generator=generator)
    return w


def _row_major(x: torch.Tensor) -> torch.Tensor:
    """A copy of ``x`` with row-major strides, also along size-1 axes (``.contiguous()`` keeps
    a transposed ``(N, in, 1)`` weight's odd strides, and the batched product then takes
    another kernel, rounding differently, than for a copy of some of its agents)."""
    return torch.empty(x.shape, dtype=x.dtype).copy_(x)


class BatchedLinear(nn.Module):
    """``N`` independent linear layers ``(N, B, in) -> (N, B, out)``.

    Parameters
    ----------
    n_agents, in_features, out_features : int
        Sizes.
    gain : float
        Orthogonal initialisation gain (biases start at 0).
    """

    def __init__(
        self,
        n_agents: int,
        in_features: int,
        out_features: int,
        gain: float = 1.0,
        generator: torch.Generator | None = None,
    ):
        super().__init__()
        w = _orthogonal_stack(n_agents, out_features, in_features, gain, generator)
        self.weight = nn.Parameter(_row_major(w.transpose(1, 2)))
        self.bias = nn.Parameter(torch.zeros(n_agents, out_features))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (N, B, in) -> (N, B, out)``."""
        return torch.baddbmm(self.bias.unsqueeze(1), x, self.weight)

    @classmethod
    def from_linears(cls, layers: Sequence[nn.Linear]) -> BatchedLinear:
        """Stack separate ``nn.Linear`` layers (for tests and conversions)."""
        w0 = layers[0].weight
        out = cls(len(layers), w0.shape[1], w0.shape[0])
        with torch.no_grad():
            out.weight.copy_(torch.stack([lin.weight.T for lin in layers]))
            out.bias.copy_(torch.stack([lin.bias for lin in layers]))
        return out


class BatchedLSTMCell(nn.Module):
    """``N`` independent LSTM cells on ``(N, B, in)`` with states ``(N, B, H)``."""

    def __init__(
        self,
        n_agents: int,
        input_size: int,
        hidden_size: int,
        generator: torch.Generator | None = None,
    ):
        super().__init__()
        self.hidden_size = hidden_size
        w_ih = _orthogonal_stack(n_agents, 4 * hidden_size, input_size, 1.0, generator)
        w_hh = _orthogonal_stack(n_agents, 4 * hidden_size, hidden_size, 1.0, generator)
        self.weight_ih = nn.Parameter(_row_major(w_ih.transpose(1, 2)))
        self.weight_hh = nn.Parameter(_row_major(w_hh.transpose(1, 2)))
        self.bias = nn.Parameter(torch.zeros(n_agents, 4 * hidden_size))

    def forward(
        self, x: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One step: ``x (N, B, in)``, ``(h, c) (N, B, H)`` -> new ``(h, c)``."""
        return self.step_from_gates(self.input_gates(x), state)

    def input_gates(
        self, x: torch.Tensor, rows: slice | None = None, bias: bool = True
    ) -> torch.Tensor:
        """Input part of the gates ``x W_ih (+ b)``, ``(N, M, 4H)`` for any number of rows M.

        ``rows`` selects a block of input features (when the input is a concatenation whose
        parts are computed separately); the bias is added once (``bias=True``).
        """
        w = self.weight_ih if rows is None else self.weight_ih[:, rows]
        if bias:
            return torch.baddbmm(self.bias.unsqueeze(1), x, w)
        return torch.bmm(x, w)

    def step_from_gates(
        self, input_gates: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Recurrent half of a step: add ``h W_hh`` to precomputed input gates, update (h, c)."""
        h, c = state
        gates = torch.baddbmm(input_gates, h, self.weight_hh)
        i, f, g, o = gates.chunk(4, dim=-1)
        c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h_new = torch.sigmoid(o) * torch.tanh(c_new)
        return h_new, c_new

    def segment(
        self, input_gates: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """T steps at once: input gates ``(N, T, B, 4H)`` (precomputed, bias included) and the
        state at the start -> hidden states ``(N, T, B, H)`` and the state after the last step.

        The forward is :meth:`step_from_gates` step by step (the same numbers); the backward is
        written out (:class:`_LSTMSegment`): back through time one step at a time for the
        state, and the gradient of ``W_hh`` as one product over all ``T B`` rows instead of T
        small ones."""
        hs, c_last = _LSTMSegment.apply(input_gates, state[0], state[1], self.weight_hh)
        return hs, (hs[:, -1], c_last)

    @classmethod
    def from_cells(cls, cells: Sequence[nn.LSTMCell]) -> BatchedLSTMCell:
        """Stack separate ``nn.LSTMCell`` agents (biases ``b_ih + b_hh`` combined)."""
        c0 = cells[0]
        out = cls(len(cells), c0.input_size, c0.hidden_size)
        with torch.no_grad():
            out.weight_ih.copy_(torch.stack([c.weight_ih.T for c in cells]))
            out.weight_hh.copy_(torch.stack([c.weight_hh.T for c in cells]))
            out.bias.copy_(torch.stack([c.bias_ih + c.bias_hh for c in cells]))
        return out


class _LSTMSegment(torch.autograd.Function):
    """Autograd of :meth:`BatchedLSTMCell.segment` (gate order i, f, g, o)."""

    @staticmethod
    def forward(
        ctx: Any, input_gates: torch.Tensor, h0: torch.Tensor, c0: torch.Tensor,
        weight_hh: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        n, t_len, b, h4 = input_gates.shape
        hs = input_gates.new_empty(n, t_len, b, h4 // 4)
        cs = torch.empty_like(hs)
        acts = torch.empty_like(input_gates)  # sigmoid(i), sigmoid(f), tanh(g), sigmoid(o)
        h, c = h0, c0
        for t in range(t_len):
            i, f, g, o = torch.baddbmm(input_gates[:, t], h, weight_hh).chunk(4, dim=-1)
            si, sf, tg, so = torch.sigmoid(i), torch.sigmoid(f), torch.tanh(g), torch.sigmoid(o)
            c = sf * c + si * tg  # as step_from_gates, operation by operation
            h = so * torch.tanh(c)
            torch.cat([si, sf, tg, so], dim=-1, out=acts[:, t])
            hs[:, t], cs[:, t] = h, c
        ctx.save_for_backward(h0, c0, weight_hh, hs, cs, acts)
        return hs, cs[:, -1]

    @staticmethod
    def backward(
        ctx: Any, d_hs: torch.Tensor | None, d_c_last: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        h0, c0, weight_hh, hs, cs, acts = ctx.saved_tensors
        n, t_len, b, hidden = hs.shape
        d_gates = torch.empty_like(acts)
        dh = torch.zeros_like(h0)  # from the step after
        dc = torch.zeros_like(c0) if d_c_last is None else d_c_last.clone()
        w_t = weight_hh.transpose(1, 2)
        for t in range(t_len - 1, -1, -1):
            si, sf, tg, so = acts[:, t].chunk(4, dim=-1)
            if d_hs is not None:
                dh = dh + d_hs[:, t]
            tc = torch.tanh(cs[:, t])
            dc = dc + dh * so * (1 - tc * tc)
            c_prev = cs[:, t - 1] if t > 0 else c0
            torch.cat([dc * tg * si * (1 - si), dc * c_prev * sf * (1 - sf),
                       dc * si * (1 - tg * tg), dh * tc * so * (1 - so)], dim=-1,
                      out=d_gates[:, t])
            dh = torch.bmm(d_gates[:, t], w_t)
            dc = dc * sf
        h_prev = torch.cat([h0.unsqueeze(1), hs[:, :-1]], 1).reshape(n, t_len * b, hidden)
        d_w = torch.bmm(h_prev.transpose(1, 2), d_gates.reshape(n, t_len * b, 4 * hidden))
        return d_gates, dh, dc, d_w


@functools.cache
def _portable() -> bool:
    """Whether this process trains portably (its environment is read once, as the libraries
    read theirs at start)."""
    return arithmetic.current() == "portable"


def sqrt(t: torch.Tensor) -> torch.Tensor:
    """Square root of a tensor without gradient, as the learners' updates take it: PyTorch's
    kernel natively; in a portable process the correctly rounded one (numpy's, which is the
    processor's square-root instruction). PyTorch's float32 CPU kernel rounds about a fifth of
    its results to a neighbour, and not alike on an Intel Xeon and an AMD EPYC
    (:mod:`marl.arithmetic_fingerprint`)."""
    if not _portable():
        return t.sqrt()
    return torch.from_numpy(np.sqrt(t.detach().numpy()))


def per_agent_clip_(
    params: Sequence[torch.Tensor], max_norm: float | torch.Tensor
) -> torch.Tensor:
    """Clip every agent's gradient to global norm ``max_norm`` (over all its stacked tensors;
    a tensor ``(N,)`` gives each agent its own).

    Equal to one ``clip_grad_norm_`` per agent network, as with separate optimisers.
    Returns the per-agent norms before clipping, ``(N,)``.
    """
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return torch.zeros(0)
    # per agent: one sum per tensor, added tensor by tensor (elementwise, so each agent's norm
    # does not depend on how many agents are stacked; a sum over dim 0 of the stacked sums
    # rounded otherwise for 3 and 6 agents on an AVX-512 CPU)
    sq = grads[0].reshape(grads[0].shape[0], -1).square().sum(1)
    for g in grads[1:]:
        sq = sq + g.reshape(g.shape[0], -1).square().sum(1)
    norm = sqrt(sq)
    scale = (max_norm / (norm + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(scale.reshape((-1,) + (1,) * (g.dim() - 1)))
    return norm


def rmsprop_(
    param: torch.Tensor, grad: torch.Tensor, square_avg: torch.Tensor, lr: float, alpha: float,
    eps: float,
) -> None:
    """One RMSprop step in place (no momentum, not centred), in the operation order of
    ``torch.optim.RMSprop``."""
    square_avg.mul_(alpha).addcmul_(grad, grad, value=1 - alpha)
    avg = sqrt(square_avg).add_(eps)
    param.addcdiv_(grad, avg, value=-lr)
