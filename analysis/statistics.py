"""Statistics for the leaderboard: seeded bootstrap intervals over episodes."""

from __future__ import annotations

import math

import numpy as np


def bootstrap_ci(
    values: np.ndarray | list[float],
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """Mean and percentile-bootstrap interval of the mean over episodes.

    Parameters
    ----------
    values : 1-D array
        One value per episode; NaNs are dropped.
    confidence : float
        Coverage of the interval (0.95 gives the 2.5 and 97.5 percentiles).
    n_resamples : int
        Bootstrap resamples.
    seed : int
        Seed of the resampling stream (the same inputs always give the same interval).

    Returns
    -------
    mean, low, high : float
        NaN if there is no finite value; ``low == high == mean`` for one value.
    """
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return math.nan, math.nan, math.nan
    mean = float(x.mean())
    if x.size == 1:
        return mean, mean, mean
    rng = np.random.Generator(np.random.PCG64(seed))
    idx = rng.integers(0, x.size, size=(n_resamples, x.size))
    means = x[idx].mean(axis=1)
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(means, [alpha, 1.0 - alpha])
    return mean, float(lo), float(hi)
