"""Pooling training seeds: the two-stage bootstrap and the pooled leaderboard row."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from analysis.statistics import bootstrap_ci, hierarchical_bootstrap_ci
from benchmark.cli import main


def test_hierarchical_bootstrap_covers_seed_variation() -> None:
    """Three seeds whose episode means differ by far more than the episodes within a seed: the
    two-stage interval spans the seed means, the pooled plain bootstrap is much narrower."""
    rng = np.random.default_rng(0)
    groups = [m + 0.1 * rng.standard_normal(50) for m in (-10.0, 0.0, 10.0)]
    mean, lo, hi = hierarchical_bootstrap_ci(groups, seed=1)
    assert mean == pytest.approx(np.concatenate(groups).mean())
    _, plo, phi = bootstrap_ci(np.concatenate(groups), seed=1)
    assert hi - lo > 5 * (phi - plo)
    assert lo < -3 and hi > 3  # a third of the resamples miss one seed or repeat it
    assert (mean, lo, hi) == hierarchical_bootstrap_ci(groups, seed=1)  # seeded
    # one group: the plain bootstrap; identical groups: about the pooled interval
    assert hierarchical_bootstrap_ci([groups[0]], seed=2) == bootstrap_ci(groups[0], seed=2)
    same = [groups[0], groups[0].copy(), groups[0].copy()]
    _, slo, shi = hierarchical_bootstrap_ci(same, seed=3)
    _, blo, bhi = bootstrap_ci(np.concatenate(same), seed=3)
    assert shi - slo == pytest.approx(bhi - blo, rel=0.3)
    assert np.isnan(hierarchical_bootstrap_ci([[np.nan], []])[0])


def test_run_pools_training_seeds(tmp_path) -> None:
    out = tmp_path / "pool"
    ctrls = "bdc:untrained=true,seed=1,bdc:untrained=true,seed=2,ovm"
    assert main(["run", "--controllers", ctrls, "--scenarios", "catchup-v1", "--vehicles", "3",
                 "--episodes", "2", "--out", str(out), "--pool-seeds", "--quiet"]) == 0
    lb = pd.read_csv(out / "leaderboard.csv")
    runs = pd.read_csv(out / "runs.csv")
    assert set(lb["controller"]) == {"bdc[seeds=1+2,untrained=true]", "ovm"}
    row = lb[lb["controller"].str.startswith("bdc")].iloc[0]
    assert row["n_episodes"] == 4 and row["n_train_seeds"] == 2
    per_seed = runs[runs["controller"].str.startswith("bdc")]
    assert row["reward_mean"] == pytest.approx(per_seed["reward"].mean())
    # without pooling: one row per seed, rebuilt from the same store
    assert main(["leaderboard", str(out), "--quiet"]) == 0
    lb2 = pd.read_csv(out / "leaderboard.csv")
    assert {"bdc[seed=1,untrained=true]", "bdc[seed=2,untrained=true]"} <= set(lb2["controller"])
