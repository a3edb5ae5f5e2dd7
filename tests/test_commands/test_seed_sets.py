"""The named seed sets (``docs/seed-sets.md``): disjoint, the test seeds refused by every
decision helper, and ``cacc-bench run --seed-set`` running on the chosen set."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pytest

from benchmark.suite import MAX_EPISODES, seeds_from_episodes, seeds_from_set
from commands.cli import main as cli
from envs.params import (
    EVAL_SEEDS,
    SEED_SETS,
    TEST_SEEDS,
    VALIDATION_SEEDS,
    check_decision_seeds,
)
from infra.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
#: training episode seeds are ``TRAIN_STRIDE (seed + 1) + k`` (marl.a2c, marl.ppo, marl.distill)
TRAIN_STRIDE = 10_000_000


# ---------------------------------------------------------------------------- the sets
def test_the_test_set_is_100_distinct_seeds_in_a_32_bit_range() -> None:
    assert len(TEST_SEEDS) == 100 and len(set(TEST_SEEDS)) == 100
    assert TEST_SEEDS == tuple(range(900_000, 900_100))
    assert all(0 <= s <= 2**31 - 1 for s in TEST_SEEDS)
    assert list(SEED_SETS) == ["eval", "test", "validation"]  # the default first
    assert SEED_SETS["test"] is TEST_SEEDS


def test_the_named_sets_are_disjoint() -> None:
    test, val, ev = set(TEST_SEEDS), set(VALIDATION_SEEDS), set(EVAL_SEEDS)
    extended = set(seeds_from_episodes(MAX_EPISODES))  # --episodes beyond the published 50
    assert ev <= extended
    assert not test & val and not test & ev and not test & extended and not val & extended
    # seeds used for the ad hoc measurements of issue 33 (5000..5019): none of the named sets
    assert not test & set(range(5000, 5020))


def test_the_training_seeds_never_reach_the_test_or_validation_seeds() -> None:
    # training seeds 0..99, episodes k < 1e6: each seed's stream is one interval
    lo, hi = min(TEST_SEEDS), max(TEST_SEEDS)
    for seed in range(100):
        first, last = TRAIN_STRIDE * (seed + 1), TRAIN_STRIDE * (seed + 1) + 10**6 - 1
        assert last < TRAIN_STRIDE * (seed + 2)  # streams of different seeds do not overlap
        assert first > hi or last < lo
        assert first > max(VALIDATION_SEEDS) and first > max(seeds_from_episodes(MAX_EPISODES))
    # and element-wise on the first episodes of every stream
    ks = np.arange(10_000)
    train = (TRAIN_STRIDE * (np.arange(100)[:, None] + 1) + ks).ravel()
    assert not set(train.tolist()) & (set(TEST_SEEDS) | set(VALIDATION_SEEDS) | set(EVAL_SEEDS))


def test_the_learners_build_training_seeds_by_that_formula() -> None:
    """Ties the formula above to the code: the one rule (``infra.limits.training_episode_seeds``)
    gives it, and every learner draws its episodes through that rule and spells no stride of its
    own."""
    from infra.limits import TRAIN_SEED_STRIDE, training_episode_seeds

    assert TRAIN_SEED_STRIDE == TRAIN_STRIDE
    np.testing.assert_array_equal(training_episode_seeds(3, 40, 5),
                                  TRAIN_STRIDE * 4 + 40 + np.arange(5))
    for path in ("marl/a2c.py", "marl/ppo.py", "marl/distill.py"):
        text = (ROOT / path).read_text()
        assert "training_episode_seeds(" in text and "10_000_000" not in text, path


def test_a_negative_training_seed_is_refused() -> None:
    """With seed >= 0 every training stream starts at 1e7, above every test seed."""
    from infra.limits import MAX_TRAIN_SEED, check_seeds

    with pytest.raises(ConfigError):
        check_seeds([-1], "--seed", MAX_TRAIN_SEED)


def test_no_code_names_a_test_seed_outside_envs_params() -> None:
    literal = re.compile(r"\b900_?0\d\d\b")
    hits = [str(p.relative_to(ROOT))
            for pkg in ("infra", "envs", "marl", "controllers", "benchmark", "analysis", "studies",
                        "commands")
            for p in sorted((ROOT / pkg).rglob("*.py"))
            if p.name != "params.py" and literal.search(p.read_text())]
    assert hits == []


# ---------------------------------------------------------------------------- the guard
def test_the_guard_accepts_decision_seeds() -> None:
    check_decision_seeds(VALIDATION_SEEDS, "test")
    check_decision_seeds(EVAL_SEEDS, "test")
    check_decision_seeds(np.arange(1, 33), "test")
    check_decision_seeds([], "test")


@pytest.mark.parametrize("seeds", [
    [1, 2, TEST_SEEDS[0]],
    (TEST_SEEDS[-1],),
    np.array([[3, TEST_SEEDS[7]]]),
    iter([TEST_SEEDS[3]]),
    list(TEST_SEEDS),
])
def test_the_guard_refuses_a_test_seed(seeds: object) -> None:
    with pytest.raises(ConfigError, match="docs/seed-sets.md") as info:
        check_decision_seeds(seeds, "my.helper")  # type: ignore[arg-type]
    assert "my.helper" in str(info.value) and "validation seeds" in str(info.value)


@pytest.mark.parametrize("algo", ["ia2c", "ippo"])
def test_validation_evaluator_refuses_test_seeds(algo: str) -> None:
    """Every learner's validation (the paper's and the shared ones: one evaluator)."""
    from benchmark.policy_eval import validation_evaluator

    validation_evaluator(algo, "catchup-v1", 8)  # default: the validation seeds
    with pytest.raises(ConfigError, match="validation_evaluator"):
        validation_evaluator(algo, "catchup-v1", 8, [1, TEST_SEEDS[0]])


def test_duty_refuses_to_choose_k_on_test_seeds() -> None:
    from benchmark.rollout import rollout_batch
    from controllers.duty import best_k, duty_scores

    for helper in (duty_scores, best_k):
        with pytest.raises(ConfigError, match="duty"):
            helper("catchup-v1", 2, 2, closed_loop=rollout_batch, seeds=TEST_SEEDS[:2])
        with pytest.raises(ConfigError, match="test seeds"):  # before the closed loop is asked
            helper("catchup-v1", 2, 2, seeds=[TEST_SEEDS[5]])


# ---------------------------------------------------------------------------- run --seed-set
def test_seeds_from_set() -> None:
    assert seeds_from_set("eval", None) == seeds_from_episodes(10)
    assert seeds_from_set("eval", 60) == seeds_from_episodes(60)
    assert seeds_from_set("test", None) == list(TEST_SEEDS)
    assert seeds_from_set("test", 3) == list(TEST_SEEDS[:3])
    assert seeds_from_set("validation", None) == list(VALIDATION_SEEDS)
    for name, k in (("test", 101), ("test", 0), ("validation", 33), ("nope", 1)):
        with pytest.raises(ConfigError):
            seeds_from_set(name, k)


def _seeds_in(runs_csv: Path) -> list[int]:
    with runs_csv.open() as fh:
        return sorted({int(r["seed"]) for r in csv.DictReader(fh)})


def _rows_without_timings(runs_csv: Path) -> list[dict[str, str]]:
    """The rows less the measured times (``wall_s``, ``compute_ms_*``), which vary run to run."""
    with runs_csv.open() as fh:
        return [{k: v for k, v in r.items() if k != "wall_s" and not k.startswith("compute_ms")}
                for r in csv.DictReader(fh)]


BASE = ["run", "--controllers", "ovm", "--scenarios", "catchup-v1", "--vehicles", "2",
        "--executor", "serial", "--quiet"]


def test_run_on_the_test_seeds(tmp_path: Path) -> None:
    out = tmp_path / "test"
    assert cli([*BASE, "--seed-set", "test", "--episodes", "2", "--out", str(out)]) == 0
    assert _seeds_in(out / "runs.csv") == list(TEST_SEEDS[:2])


def test_seed_set_eval_is_the_default(tmp_path: Path) -> None:
    a, b = tmp_path / "default", tmp_path / "eval"
    assert cli([*BASE, "--episodes", "2", "--out", str(a)]) == 0
    assert cli([*BASE, "--seed-set", "eval", "--episodes", "2", "--out", str(b)]) == 0
    assert _seeds_in(a / "runs.csv") == list(EVAL_SEEDS[:2])
    assert _rows_without_timings(a / "runs.csv") == _rows_without_timings(b / "runs.csv")


def _exit_code(argv: list[str]) -> int:
    try:
        return cli(argv)
    except SystemExit as exc:  # argparse's own errors
        return int(exc.code or 0)


@pytest.mark.parametrize("args", [
    ["--seed-set", "test", "--seeds", "1"],
    ["--seed-set", "eval", "--seeds", "2000"],
    ["--seed-set", "test", "--episodes", "101"],
    ["--seed-set", "test", "--episodes", "0"],
    ["--seed-set", "test", "--episodes", "-3"],
    ["--seed-set", "validation", "--episodes", "33"],
    ["--seed-set", "nope"],
    ["--seed-set", ""],
    ["--seed-set"],
])
def test_bad_seed_set_input_exits_2(args: list[str], tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert _exit_code([*BASE, *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip(), err
    assert not out.exists()
