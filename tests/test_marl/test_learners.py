"""The one learner registry (``marl.learners``): every list of learners derives from it."""

from __future__ import annotations

from pathlib import Path

from controllers.registry import CONTROLLERS
from marl.learners import (
    LEARNER_FAMILIES,
    LEARNERS,
    PAPER_ALGORITHMS,
    PER_AGENT_SHARED,
    PPO_LEARNERS,
    SHARED_LEARNERS,
    load,
)

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("infra", "envs", "marl", "controllers", "benchmark", "analysis", "studies",
            "commands")


def test_the_derived_lists() -> None:
    assert PAPER_ALGORITHMS == ("ia2c", "fprint", "dial", "commnet", "wac", "dcea", "bdc")
    assert PPO_LEARNERS == ("ippo", "mappo", "ippo-bdc", "ippo-gains")
    assert SHARED_LEARNERS == ("ippo", "mappo", "distill", "ippo-bdc", "ippo-gains")
    assert PER_AGENT_SHARED == ("ippo-bdc",)
    assert {s.family for s in LEARNERS.values()} == set(LEARNER_FAMILIES)


def test_every_learner_is_a_controller_acting_with_its_checkpoints() -> None:
    for name, spec in LEARNERS.items():
        ctrl = CONTROLLERS[name]
        assert ctrl.family == "marl" and ctrl.target == "controllers.policy:PolicyController"
        assert ctrl.fixed == {"algo": name} and ctrl.description == spec.description
    assert [n for n, c in CONTROLLERS.items() if c.family == "marl"] == list(LEARNERS)


def test_every_learner_module_exists() -> None:
    for spec in LEARNERS.values():
        assert (ROOT / (spec.module.replace(".", "/") + ".py")).is_file(), spec.module


def test_every_entry_names_its_config_trainer_and_acting_class() -> None:
    from marl.acting import Acting
    from marl.config import algorithm

    for name, spec in LEARNERS.items():
        assert issubclass(load(spec.acting), Acting)
        if spec.family == "a2c":
            assert load(spec.config) is algorithm(name).config_cls
        elif spec.family == "ppo":
            assert load(spec.config)(algo=name).algo == name
            assert load(f"{spec.module}:TRAINER").__name__.endswith("Trainer")
        else:
            assert load(spec.config)().expert == "mpc"


def test_no_second_list_of_learners_in_the_code() -> None:
    """No module spells out one of the registry's lists again (a literal tuple or list holding
    the same names as every learner, the paper's algorithms, the PPO learners or the
    shared-policy learners); a study's own selection of a few (the paper's table columns, the
    algorithms with a consensus step size) is named for what it selects and may stand."""
    import ast

    derived = {frozenset(x) for x in (LEARNERS, PAPER_ALGORITHMS, PPO_LEARNERS, SHARED_LEARNERS)}
    found = []
    for pkg in PACKAGES:
        for py in (ROOT / pkg).rglob("*.py"):
            rel = py.relative_to(ROOT).as_posix()
            if rel == "marl/learners.py":
                continue
            for node in ast.walk(ast.parse(py.read_text())):
                if isinstance(node, ast.Tuple | ast.List) and len(node.elts) >= 2 and all(
                        isinstance(e, ast.Constant) and e.value in LEARNERS for e in node.elts):
                    names = frozenset(e.value for e in node.elts)  # type: ignore[attr-defined]
                    if names in derived:
                        found.append(f"{rel}:{node.lineno}")
    assert not found, found
