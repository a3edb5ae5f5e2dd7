"""The leaderboard's intervals against what a percentile bootstrap must give."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.statistics import (
    bootstrap_ci,
    hierarchical_bootstrap_ci,
    paired_ci,
)


def test_bootstrap_interval_matches_the_normal_approximation() -> None:
    """For 400 standard-normal draws the 95 % percentile-bootstrap interval of the mean is close
    to mean +- 1.96 s / sqrt(n) (within 5 %: a 96.7 % interval would be 9 % wider)."""
    x = np.random.default_rng(7).standard_normal(400)
    mean, lo, hi = bootstrap_ci(x, n_resamples=20_000)
    half = 1.96 * x.std(ddof=1) / np.sqrt(x.size)
    assert mean == pytest.approx(x.mean())
    assert (hi - lo) / 2 == pytest.approx(half, rel=0.05)
    assert (mean - lo) == pytest.approx(hi - mean, rel=0.15)
    m90, lo90, hi90 = bootstrap_ci(x, confidence=0.90, n_resamples=20_000)
    assert (hi90 - lo90) / 2 == pytest.approx(1.645 * x.std(ddof=1) / np.sqrt(x.size), rel=0.05)


def test_default_seed_is_zero_and_reproducible() -> None:
    x = np.arange(30.0) ** 1.5
    assert bootstrap_ci(x) == bootstrap_ci(x, seed=0) == bootstrap_ci(list(x), seed=0)
    assert bootstrap_ci(x, seed=1) != bootstrap_ci(x, seed=0)
    groups = [x[:10], x[10:20], x[20:]]
    assert hierarchical_bootstrap_ci(groups) == hierarchical_bootstrap_ci(groups, seed=0)


def test_hierarchical_interval_covers_the_spread_between_groups() -> None:
    """Two training seeds whose episodes sit at 0 and 10 (small noise): the pooled mean is 5 and
    the two-stage interval reaches towards both (a resample may draw the same seed twice); a
    plain bootstrap over the pooled episodes is far narrower."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(0.0, 0.1, 50), rng.normal(10.0, 0.1, 50)
    mean, lo, hi = hierarchical_bootstrap_ci([a, b])
    assert mean == pytest.approx(np.concatenate([a, b]).mean())
    assert lo < 0.5 and hi > 9.5 and lo <= mean <= hi
    _, plo, phi = bootstrap_ci(np.concatenate([a, b]))
    assert phi - plo < 0.3 * (hi - lo)


def test_hierarchical_draws_every_episode_of_a_group() -> None:
    """One extreme episode (index 0) in one group: some resamples must include it."""
    a = np.array([1000.0, 0.0, 0.0, 0.0])
    b = np.zeros(4)
    _, lo, hi = hierarchical_bootstrap_ci([a, b], n_resamples=4000)
    assert hi > 100.0 and lo == 0.0


def test_one_group_is_the_plain_bootstrap_and_nan_and_empty_groups_drop() -> None:
    x = np.arange(20.0)
    assert hierarchical_bootstrap_ci([x]) == bootstrap_ci(x)
    assert hierarchical_bootstrap_ci([x, np.array([np.nan]), []]) == bootstrap_ci(x)
    assert all(np.isnan(v) for v in hierarchical_bootstrap_ci([[np.nan], []]))
    assert bootstrap_ci([3.0]) == (3.0, 3.0, 3.0)


def test_two_stage_resamples_count_every_drawn_group_with_few_resamples() -> None:
    """With four resamples, each resample's mean is that of the g groups it drew (their
    first-stage picks are the generator's first draw; groups of constant values make the
    second stage irrelevant): the interval at confidence 1 spans exactly the smallest and
    largest of those means, even where a group is drawn by no resample at some position."""
    from benchmark.statistics import hierarchical_bootstrap_ci

    values, sizes = (0.0, 10.0, 20.0), (1, 2, 3)
    groups = [np.full(n, v) for v, n in zip(values, sizes, strict=True)]
    unpicked = 0
    for seed in range(10):
        picks = np.random.Generator(np.random.PCG64(seed)).integers(0, 3, size=(4, 3))
        unpicked += sum(len(set(picks[:, j])) < 3 for j in range(3))
        means = [sum(values[k] * sizes[k] for k in row) / sum(sizes[k] for k in row)
                 for row in picks]
        _, lo, hi = hierarchical_bootstrap_ci(groups, confidence=1.0, n_resamples=4, seed=seed)
        assert (lo, hi) == pytest.approx((min(means), max(means)), abs=1e-12), seed
    assert unpicked > 0  # the case the test is for occurs


def test_paired_saving_with_one_seed_each_is_the_paired_episode_bootstrap() -> None:
    """One training seed per side: the seeds' stage draws nothing, so the interval is a
    bootstrap of the per-episode savings; the mean is the per-episode formula."""
    rng = np.random.default_rng(3)
    other = 20.0 + rng.normal(0, 1, 50)
    ours = other * 0.9 + rng.normal(0, 0.1, 50)
    m, lo, hi = paired_ci(ours[None], other[None], "saving")
    per_episode = 100.0 * (other - ours) / other
    assert m == pytest.approx(per_episode.mean())
    em, elo, ehi = bootstrap_ci(per_episode)
    assert lo == pytest.approx(elo, abs=0.1) and hi == pytest.approx(ehi, abs=0.1)
    assert lo > 0  # a steady 10 % saving


def test_paired_saving_covers_the_spread_between_training_seeds() -> None:
    """Three seeds on each side, an 8.3 % mean saving, but one of ours costlier than the other
    side: the episode-only interval is narrow and above 0, the two-stage one covers 0."""
    rng = np.random.default_rng(4)
    episode = 20.0 + rng.normal(0, 1, 50)
    other = np.stack([episode * f for f in (1.0, 1.01, 0.99)])
    ours = np.stack([episode * f for f in (0.75, 0.95, 1.05)])
    m, lo, hi = paired_ci(ours, other, "saving")
    _, elo, _ = bootstrap_ci(100.0 * (other.mean(0) - ours.mean(0)) / other.mean(0))
    assert m == pytest.approx(100.0 * (1.0 - (0.75 + 0.95 + 1.05) / 3), abs=0.1)
    assert elo > 7.0 and lo < 0 < hi
    with pytest.raises(ValueError, match="unknown paired statistic .ratio."):
        paired_ci(ours, other, "ratio")
    with pytest.raises(ValueError, match="same episodes"):
        paired_ci(ours, other[:, :10], "saving")


def test_paired_difference_is_the_mean_difference_with_the_same_two_stages() -> None:
    rng = np.random.default_rng(5)
    episode = rng.normal(-500, 30, 50)
    ours = np.stack([episode + d for d in (40.0, 50.0, 60.0)])
    other = np.stack([episode + d for d in (0.0, -5.0, 5.0)])
    m, lo, hi = paired_ci(ours, other)
    assert m == pytest.approx(50.0) and 38.0 < lo < 50.0 < hi < 62.0
    spread = np.stack([episode + d for d in (-40.0, 50.0, 140.0)])  # one seed below the other
    _, lo2, hi2 = paired_ci(spread, other)
    assert lo2 < 0 < hi2
