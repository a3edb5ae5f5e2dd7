"""Statistics for the leaderboard: seeded bootstrap intervals over episodes."""

from __future__ import annotations

import math
from collections.abc import Callable

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
    return _percentile_interval(mean, x[idx].mean(axis=1), confidence)


def _percentile_interval(mean: float, means: np.ndarray, confidence: float
                         ) -> tuple[float, float, float]:
    """``mean`` and the central ``confidence`` interval of the resampled ``means``."""
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(means, [alpha, 1.0 - alpha])
    return mean, float(lo), float(hi)


def hierarchical_bootstrap_ci(
    groups: list[np.ndarray] | list[list[float]],
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """Mean and two-stage percentile-bootstrap interval over groups of episodes (training seeds).

    Each resample draws as many groups as there are, with replacement, then within every drawn
    group as many of its episodes, with replacement, and takes the mean of all drawn episodes.
    The interval so covers the variation between training seeds as well as between episodes
    (a plain bootstrap over the pooled episodes treats the seeds as fixed).

    Parameters
    ----------
    groups : list of 1-D arrays
        One array of per-episode values per group; NaNs are dropped, empty groups left out.

    Returns
    -------
    mean, low, high : float
        ``mean`` is the mean over all episodes; NaN if there is none.
    """
    arrays = [np.asarray(g, dtype=np.float64) for g in groups]
    arrays = [a[np.isfinite(a)] for a in arrays]
    arrays = [a for a in arrays if a.size]
    if not arrays:
        return math.nan, math.nan, math.nan
    allv = np.concatenate(arrays)
    mean = float(allv.mean())
    if len(arrays) == 1:
        return bootstrap_ci(arrays[0], confidence, n_resamples, seed)
    rng = np.random.Generator(np.random.PCG64(seed))
    g = len(arrays)
    sums = np.zeros(n_resamples)
    counts = np.zeros(n_resamples)
    picks = rng.integers(0, g, size=(n_resamples, g))
    for j in range(g):
        for k in range(g):
            sel = picks[:, j] == k
            m = int(sel.sum())
            if not m:
                continue
            a = arrays[k]
            idx = rng.integers(0, a.size, size=(m, a.size))
            sums[sel] += a[idx].sum(axis=1)
            counts[sel] += a.size
    return _percentile_interval(mean, sums / counts, confidence)


#: Statistics of :func:`paired_ci`, per episode, from ``ours`` and ``other`` (seeds averaged).
PAIRED_STATISTICS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "difference": lambda ours, other: ours - other,
    "saving": lambda ours, other: 100.0 * (other - ours) / other,
}
#: Statistics of :func:`paired_ci` of the two sides' means over the episodes (a ratio of means,
#: not a mean of per-episode ratios: an episode whose value is near 0 cannot dominate it).
PAIRED_MEAN_STATISTICS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "saving-of-means": lambda ours, other: 100.0 * (other - ours) / other,
}


def paired_ci(
    ours: np.ndarray,
    other: np.ndarray,
    statistic: str = "difference",
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """Mean over episodes of a paired statistic and its two-stage percentile-bootstrap
    interval: each resample draws each side's training seeds with replacement, averages them
    per episode, then draws the episodes with replacement (the same episodes for both sides,
    which keeps the pairing).

    Parameters
    ----------
    ours, other : (seeds, episodes) arrays
        One row per training seed (any number on each side), one column per episode seed, in
        the same episode order on both sides; no NaN.
    statistic : {"difference", "saving", "saving-of-means"}
        Per episode ``ours - other``, or the saving ``100 (other - ours) / other`` in %; or
        ``saving-of-means``: the saving of the means over the episodes, ``100 (mean(other) -
        mean(ours)) / mean(other)`` (the resampled episodes the same for both sides; NaN when
        other's mean is not positive: a saving in % of it means nothing).

    Returns
    -------
    mean, low, high : float
        ``mean`` uses all seeds and episodes (seeds averaged per episode). With one seed on
        each side the interval is the paired bootstrap over episodes alone.
    """
    of_means = statistic in PAIRED_MEAN_STATISTICS
    stat = (PAIRED_MEAN_STATISTICS if of_means else PAIRED_STATISTICS).get(statistic)
    if stat is None:
        raise ValueError(f"unknown paired statistic {statistic!r}; valid: "
                         f"{', '.join([*PAIRED_STATISTICS, *PAIRED_MEAN_STATISTICS])}")
    a, b = np.atleast_2d(np.asarray(ours, float)), np.atleast_2d(np.asarray(other, float))
    if a.shape[1] != b.shape[1] or a.shape[1] == 0:
        raise ValueError(f"the two sides need the same episodes, got {a.shape} and {b.shape}")
    if of_means:
        base = float(b.mean(0).mean())
        if not base > 0.0:
            return math.nan, math.nan, math.nan
        mean = float(stat(np.asarray(a.mean(0).mean()), np.asarray(base)))
    else:
        mean = float(np.mean(stat(a.mean(0), b.mean(0))))
    rng = np.random.Generator(np.random.PCG64(seed))
    ra = a[rng.integers(0, a.shape[0], (n_resamples, a.shape[0]))].mean(1)  # (R, episodes)
    rb = b[rng.integers(0, b.shape[0], (n_resamples, b.shape[0]))].mean(1)
    episodes = rng.integers(0, a.shape[1], (n_resamples, a.shape[1]))
    if of_means:
        with np.errstate(divide="ignore", invalid="ignore"):
            means = stat(np.take_along_axis(ra, episodes, axis=1).mean(1),
                         np.take_along_axis(rb, episodes, axis=1).mean(1))
    else:
        means = np.take_along_axis(stat(ra, rb), episodes, axis=1).mean(1)
    return _percentile_interval(mean, means, confidence)
