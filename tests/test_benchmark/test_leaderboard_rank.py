"""The leaderboard's rank rule, as a table, and a golden leaderboard.csv."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd
import pytest

from benchmark.export import LEADERBOARD_METRICS, leaderboard_frame

GOLDEN = Path(__file__).resolve().parents[1] / "golden"


def _run(controller: str, reward: float, *, collision: bool = False, status: str = "ok",
         scenario: str = "catchup-v1", delay: float = 0.0, seed: int = 2000) -> dict:
    row = {"controller": controller, "scenario": scenario, "n_vehicles": 4, "comm_delay_s": delay,
           "packet_loss": 0.0, "lag_s": 0.0, "seed": seed, "status": status, "family": "test",
           "deterministic": True, "collision": collision, "solver_failures": 0,
           "string_stable": True}
    for m in LEADERBOARD_METRICS:
        row[m] = 1.0
    row["reward"] = reward if status == "ok" else math.nan
    return row


# controller -> (its runs' rewards, collided?, failed run?) and the rank it must get
RANK_TABLE = [
    # clean controllers first, by mean reward (higher is better)
    ("clean_best", [-100.0, -110.0], False, False, 1),
    ("clean_mid", [-200.0, -200.0], False, False, 2),
    # a tie in mean reward: the label's alphabetical order decides, stably
    ("tie_a", [-300.0, -300.0], False, False, 3),
    ("tie_b", [-250.0, -350.0], False, False, 4),
    # one collision puts a controller behind every clean one, whatever its reward
    ("collided_high", [-10.0, -20.0], True, False, 6),
    # a failed run too (failed vs collided: both unclean, then by reward)
    ("failed_one", [-5.0, None], False, True, 5),
    # no finite reward at all ranks last among the unclean
    ("all_failed", [None, None], False, True, 7),
]


def _table_runs() -> pd.DataFrame:
    rows = []
    for name, rewards, collided, _, _ in RANK_TABLE:
        for k, r in enumerate(rewards):
            rows.append(_run(name, r if r is not None else math.nan, collision=collided and k == 0,
                             status="ok" if r is not None else "failed", seed=2000 + 10 * k))
    return pd.DataFrame(rows)


def test_rank_rule_table() -> None:
    lb = leaderboard_frame(_table_runs()).set_index("controller")
    for name, rewards, collided, failed, rank in RANK_TABLE:
        row = lb.loc[name]
        assert int(row["rank"]) == rank, name
        assert int(row["collisions"]) == int(collided)
        assert int(row["failed"]) == sum(r is None for r in rewards)
        assert (int(row["failed"]) > 0) == failed
    assert lb.loc["failed_one", "reward_mean"] == -5.0  # the mean is over finished runs
    assert math.isnan(lb.loc["all_failed", "reward_mean"])


def test_ranks_are_per_setting() -> None:
    runs = pd.DataFrame([_run("a", -100.0), _run("b", -200.0),
                         _run("a", -300.0, delay=0.2), _run("b", -50.0, delay=0.2),
                         _run("a", -1.0, scenario="brake-v1")])
    lb = leaderboard_frame(runs)
    got = {(r["controller"], r["scenario"], r["comm_delay_s"]): int(r["rank"])
           for _, r in lb.iterrows()}
    assert got == {("a", "catchup-v1", 0.0): 1, ("b", "catchup-v1", 0.0): 2,
                   ("b", "catchup-v1", 0.2): 1, ("a", "catchup-v1", 0.2): 2,
                   ("a", "brake-v1", 0.0): 1}


def golden_leaderboard(runs: pd.DataFrame) -> pd.DataFrame:
    """The leaderboard of golden runs (timing zeroed: it is not part of a golden file)."""
    return leaderboard_frame(runs.assign(compute_ms_p50=0.0))


def test_golden_leaderboard(tmp_path: Path) -> None:
    """The leaderboard of the golden smoke runs (tests/golden/smoke_runs.csv) is
    tests/golden/smoke_leaderboard.csv: ranks, counts, means and bootstrap intervals."""
    path = tmp_path / "lb.csv"
    golden_leaderboard(pd.read_csv(GOLDEN / "smoke_runs.csv")).to_csv(
        path, index=False, float_format="%.10g")
    got = pd.read_csv(path)
    want = pd.read_csv(GOLDEN / "smoke_leaderboard.csv")
    pd.testing.assert_frame_equal(got, want, check_exact=False, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("name", ["clean_best", "tie_a"])
def test_rank_is_stable_under_row_order(name: str) -> None:
    runs = _table_runs()
    shuffled = runs.sample(frac=1.0, random_state=3).reset_index(drop=True)
    a = leaderboard_frame(runs).set_index("controller")["rank"]
    b = leaderboard_frame(shuffled).set_index("controller")["rank"]
    assert a[name] == b[name]
    pd.testing.assert_series_equal(a.sort_index(), b.sort_index())


def test_the_printed_table_never_cuts_a_label(tmp_path: Path) -> None:
    """Two settings whose labels share their first 22 characters stay two readable rows."""
    from analysis.tables import format_leaderboard

    runs = pd.read_csv(GOLDEN / "smoke_runs.csv")
    first = runs["controller"].iloc[0]
    one = runs[runs["controller"] == first]
    long_a, long_b = "mpc-qp[horizon=10,w_accel=0.01]", "mpc-qp[horizon=10,w_accel=0.03]"
    lb = golden_leaderboard(pd.concat([one.assign(controller=long_a),
                                       one.assign(controller=long_b)]))
    text = format_leaderboard(lb)
    assert long_a in text and long_b in text


def test_edges_of_the_leaderboard() -> None:
    """No run: an empty frame with the key columns; one run: one row; a controller whose runs
    all failed has no known determinism; missing solver-failure counts count as none."""
    import numpy as np

    from benchmark.export import GROUP_COLUMNS

    empty = leaderboard_frame(pd.DataFrame())
    assert len(empty) == 0 and empty.columns.tolist() == ["rank", *GROUP_COLUMNS]
    one = leaderboard_frame(pd.DataFrame([_run("solo", -42.0)]))
    assert one["controller"].tolist() == ["solo"] and one["reward_mean"].tolist() == [-42.0]
    assert one["rank"].tolist() == [1]
    lb = leaderboard_frame(_table_runs()).set_index("controller")
    assert lb.loc["all_failed", "deterministic"] is None
    assert lb.loc["clean_best", "deterministic"] == True  # noqa: E712 - a numpy bool
    runs = pd.DataFrame([_run("mpcish", -1.0, seed=s) for s in (2000, 2010, 2020)])
    runs["solver_failures"] = [np.nan, 2, np.nan]
    assert int(leaderboard_frame(runs)["solver_failures"].iloc[0]) == 2


@pytest.mark.parametrize("n_train_seeds", [2, 3])
def test_pooled_intervals_are_the_two_stage_bootstrap_over_the_training_seeds(n_train_seeds) -> None:
    """A policy pooled over 2 or 3 training seeds: every metric's interval is
    ``hierarchical_bootstrap_ci`` over the per-seed episode groups with the export's seed; one
    seed (and any deterministic controller) gets ``bootstrap_ci`` over its episodes."""
    import json

    import numpy as np

    from benchmark.export import BOOTSTRAP_SEED
    from benchmark.statistics import bootstrap_ci, hierarchical_bootstrap_ci

    rows, groups = [], []
    rng = np.random.default_rng(7)
    for t in range(n_train_seeds):
        rewards = (-100.0 * (t + 1) + 30.0 * rng.standard_normal(12)).tolist()
        groups.append(np.array(rewards))
        for k, r in enumerate(rewards):
            row = _run(f"bdc[seed={t}]", r, seed=2000 + 10 * k)
            row.update(family="marl", controller_name="bdc", options=json.dumps({"seed": t}))
            rows.append(row)
    lb = leaderboard_frame(pd.DataFrame(rows), pool_seeds=True)
    assert len(lb) == 1 and int(lb["n_train_seeds"].iloc[0]) == n_train_seeds
    assert len(leaderboard_frame(pd.DataFrame(rows))) == n_train_seeds  # no pooling by default
    want = hierarchical_bootstrap_ci(groups, seed=BOOTSTRAP_SEED)
    got = tuple(lb[f"reward_{k}"].iloc[0] for k in ("mean", "ci_low", "ci_high"))
    assert got == want
    assert want != bootstrap_ci(np.concatenate(groups), seed=BOOTSTRAP_SEED)
    plain = leaderboard_frame(pd.DataFrame(rows[:12]))
    got1 = tuple(plain[f"reward_{k}"].iloc[0] for k in ("mean", "ci_low", "ci_high"))
    assert got1 == bootstrap_ci(groups[0], seed=BOOTSTRAP_SEED)
    assert got1 != bootstrap_ci(groups[0])  # the export's own seed, not the default
