"""The episode's own random streams: every random number of an episode comes from its seed and a
stream's name, never from a global state, so an episode gives the same numbers alone or in a
batch, on every executor.

- :func:`episode_stream`: a numpy Generator of one named stream of one episode (scenario draws,
  the OpenACC-like leader, the ring's perturbation, a random placement);
- :func:`episode_uniforms`: counter-based uniforms of (seed, name, step, index), for what is drawn
  every step (packet losses, sampled actions).
"""

from __future__ import annotations

import numpy as np

_MASK64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = x + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def _name_key(name: str) -> int:
    h = 1469598103934665603
    for ch in name.encode():
        h = ((h ^ ch) * 1099511628211) & 0xFFFFFFFFFFFFFFFF
    return h


def episode_uniforms(seeds: np.ndarray, name: str, step: int, n: int, steps: int = 0
                     ) -> np.ndarray:
    """Uniform numbers in [0, 1) of shape ``(B, n)`` for one step of one named stream, or
    ``(steps, B, n)`` for the ``steps`` steps from ``step`` on (``steps`` > 0; the same numbers
    as one call per step, in one vectorised pass).

    A pure function of (seed, name, step, index): the same episode gets the same numbers whether
    it runs alone or in a batch.
    """
    seeds = np.asarray(seeds, dtype=np.int64).astype(np.uint64)
    base = _splitmix64(seeds ^ np.uint64(_name_key(name)))
    ts = np.arange(step, step + max(steps, 1), dtype=np.uint64)
    with np.errstate(over="ignore"):
        key = base[None, :, None] + (ts * np.uint64(1_000_003))[:, None, None]
        key = key + np.arange(n, dtype=np.uint64)[None, None, :] * np.uint64(0x632BE59BD9B4E019)
    bits = _splitmix64(_splitmix64(key)) >> np.uint64(11)
    out = bits.astype(np.float64) * (1.0 / 9007199254740992.0)
    return out if steps > 0 else out[0]


def episode_stream(seed: int, stream: str) -> np.random.Generator:
    """An independent random stream of one episode, named (e.g. ``"loss"``, ``"noise"``).

    Depends only on the episode seed and the stream's name, never on a global state.
    """
    key = [int(b) for b in stream.encode()]
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), *key])))
