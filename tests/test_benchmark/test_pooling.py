"""Pooling training seeds: the two-stage bootstrap and the pooled leaderboard row."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from benchmark.statistics import bootstrap_ci, hierarchical_bootstrap_ci
from commands.cli import main


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


def _runs(rows: list[tuple[str, str, str]]) -> pd.DataFrame:
    """A runs frame of (controller_name, family, options JSON) rows, labelled as the harness
    labels them."""
    return pd.DataFrame([{"controller": name if opts in ("", "{}") else f"{name}[{opts}]",
                          "controller_name": name, "family": fam, "options": opts}
                         for name, fam, opts in rows])


def test_pool_training_seeds_table() -> None:
    """Labels and ``train_seed`` by hand: a seed-less policy is seed 0, one row alone still
    gets its seed, rows of other families (in any position) stay as they are with an empty,
    numeric ``train_seed``, and empty options read as none."""
    from benchmark.export import pool_training_seeds

    runs = _runs([("ovm", "human", "{}"), ("bdc", "marl", "{}"), ("bdc", "marl", '{"seed": 1}'),
                  ("ia2c", "marl", ""), ("cacc", "linear", "")])
    out = pool_training_seeds(runs)
    assert out["controller"].tolist() == ["ovm", "bdc[seeds=0+1]", "bdc[seeds=0+1]", "ia2c",
                                          "cacc"]
    assert out["train_seed"].dtype == np.float64
    got = out["train_seed"].tolist()
    assert np.isnan(got[0]) and np.isnan(got[4]) and got[1:4] == [0.0, 1.0, 0.0]
    one = _runs([("bdc", "marl", '{"seed": 2}')])
    alone = pool_training_seeds(one)
    assert alone["train_seed"].tolist() == [2.0]
    assert alone["controller"].tolist() == one["controller"].tolist()  # one seed: no pooled label
    plain = pool_training_seeds(_runs([("ovm", "human", "{}")]))
    assert plain.columns.tolist()[-1] == "train_seed" and plain["train_seed"].isna().all()
    assert "train_seed" not in runs.columns  # the input is not modified
