"""Quantisers of the communication-efficient learners: ternary sign and QSGD with error feedback.

``ternary`` is the BDC weight quantiser ``q(w) = sign(w)`` in {-1, 0, +1} (no scale).
``qsgd`` is the stochastic quantiser of Alistarh et al. (NeurIPS 2017) with ``s`` levels: for a
vector ``g`` (here: one agent's tensor), ``Q(g)_k = ||g|| sign(g_k) xi_k`` with
``l = floor(s |g_k| / ||g||)`` and ``xi_k = (l + 1)/s`` with probability ``s |g_k|/||g|| - l``,
else ``l/s``. It is unbiased: ``E[Q(g)] = g``. (The published consensus code compares the
uniform draw the wrong way round, which biases it; the test checks unbiasedness.)
"""

from __future__ import annotations

import math

import torch


def ternary(w: torch.Tensor) -> torch.Tensor:
    """BDC weight quantiser ``sign(w)`` in {-1, 0, +1} (same dtype)."""
    return torch.sign(w)


def qsgd(
    g: torch.Tensor,
    s: int = 1,
    generator: torch.Generator | None = None,
    bucket: int | None = None,
) -> torch.Tensor:
    """QSGD-quantise every agent's tensor (leading axis = agents) with ``s`` levels.

    Parameters
    ----------
    g : (N, ...)
        Stacked per-agent tensors; each agent's tensor is one vector for the norm.
    s : int
        Quantisation levels (s = 1: every entry becomes 0 or +-norm).
    generator : torch.Generator, optional
        Random stream (training streams only).
    bucket : int, optional
        Quantise consecutive buckets of this many entries, each with its own norm (QSGD's
        bucketing, Alistarh et al. section 3.1: the variance bound falls from
        ``sqrt(D)/s ||g||^2`` for a whole D-entry tensor to ``sqrt(bucket)/s`` per bucket). None:
        one norm per agent tensor.
    """
    if s < 1:
        raise ValueError(f"QSGD needs s >= 1 levels, got {s}")
    if bucket is not None and bucket < 1:
        raise ValueError(f"QSGD bucket must be >= 1 entries, got {bucket}")
    flat = g.reshape(g.shape[0], -1)
    d = flat.shape[1]
    width = d if bucket is None or bucket >= d else bucket
    pad = (-d) % width
    if pad:
        flat = torch.cat([flat, flat.new_zeros(flat.shape[0], pad)], dim=1)
    blocks = flat.reshape(flat.shape[0], -1, width)
    norm = torch.linalg.vector_norm(blocks, dim=2, keepdim=True)
    safe = torch.where(norm > 0, norm, torch.ones_like(norm))
    level = s * blocks.abs() / safe
    low = torch.floor(level)
    # drawn where the generator is (a run's CPU stream, the same draws on every device)
    u = torch.rand(blocks.shape, generator=generator, dtype=blocks.dtype,
                   device=None if generator is None else generator.device).to(blocks.device)
    xi = (low + (u < (level - low)).to(blocks.dtype)) / s
    out = (norm * torch.sign(blocks) * xi).reshape(flat.shape[0], -1)[:, :d]
    return out.reshape(g.shape)


def qsgd_variance_bound(n_values: int, s: int = 1, bucket: int | None = None) -> float:
    """QSGD's variance factor ``omega``: ``E||Q(g) - g||^2 <= omega ||g||^2`` (Alistarh et al.
    2017, Lemma 3.1: ``omega = min(d / s^2, sqrt(d) / s)`` for a d-entry bucket)."""
    d = n_values if bucket is None else min(bucket, n_values)
    return min(d / s**2, math.sqrt(d) / s)


class ErrorFeedbackQSGD:
    """QSGD with error feedback on a list of stacked per-agent tensors.

    ``compress(grads)`` sends ``C(g + e)`` and keeps the residual ``e <- (g + e) - C(g + e)``,
    so the sum of what was sent plus the final residual equals the sum of the true gradients.

    ``C = Q / (1 + omega)`` (``contractive=True``, default): error feedback needs a contractive
    compressor, ``E||x - C(x)||^2 <= (1 - delta) ||x||^2``, and unbiased QSGD is not one: with
    s = 1 its error can reach ``omega = sqrt(d)`` times ``||x||^2``, so the residual grows
    geometrically. Scaling an unbiased compressor of variance ``omega`` by ``1 / (1 + omega)``
    makes it contractive with ``delta = 1 / (1 + omega)`` (Stich and Karimireddy 2020;
    Beznosikov et al. 2020). The receiver knows the factor, so it costs no bits. Without it
    (``contractive=False``) BDC diverges (measured: ``docs/learner-options.md``).

    Parameters
    ----------
    s : int
        QSGD levels.
    generator : torch.Generator
        Random stream.
    bucket : int, optional
        Entries per QSGD bucket (None: one norm per tensor).
    contractive : bool
        Scale by ``1 / (1 + omega)`` (see above); False sends plain QSGD (diverges).
    """

    def __init__(
        self,
        s: int = 1,
        generator: torch.Generator | None = None,
        bucket: int | None = None,
        contractive: bool = True,
    ) -> None:
        self.s = int(s)
        self.generator = generator
        self.bucket = bucket
        self.contractive = contractive
        self.residual: list[torch.Tensor] | None = None

    def compress(self, grads: list[torch.Tensor]) -> list[torch.Tensor]:
        """Quantised gradients (new tensors); updates the residuals."""
        if self.residual is None:
            self.residual = [torch.zeros_like(g) for g in grads]
        out = []
        for i, g in enumerate(grads):
            corrected = g + self.residual[i]
            q = qsgd(corrected, self.s, self.generator, self.bucket)
            if self.contractive:
                n_values = corrected[0].numel()
                q = q / (1.0 + qsgd_variance_bound(n_values, self.s, self.bucket))
            self.residual[i] = corrected - q
            out.append(q)
        return out


def compress_gradients_(grads: list[torch.Tensor], compressor: ErrorFeedbackQSGD,
                        bits: dict[str, float]) -> None:
    """Replace every stacked gradient ``(N, ...)`` of ``grads`` in place by its compression
    (applied locally: sent nowhere), adding each one's payload per agent to
    ``bits["qsgd_local"]``."""
    for g, q in zip(grads, compressor.compress(grads), strict=True):
        g.copy_(q)
        bits["qsgd_local"] += qsgd_bits(g[0].numel(), compressor.s, bucket=compressor.bucket)


def ternary_bits(n_values: int, packed: bool = False) -> float:
    """Bits to send ``n_values`` ternary symbols: ``log2 3`` each, or 2 each if bit-packed."""
    return n_values * (2.0 if packed else math.log2(3.0))


def qsgd_bits(
    n_values: int, s: int = 1, float_bits: int = 32, bucket: int | None = None
) -> float:
    """Bits of one QSGD message: one float norm per bucket (one per tensor without buckets)
    plus ``log2(2s+1)`` bits per entry."""
    n_norms = 1 if bucket is None or bucket >= n_values else math.ceil(n_values / bucket)
    return n_norms * float_bits + n_values * math.log2(2 * s + 1)
