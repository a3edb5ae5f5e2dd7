"""The training path parses its inputs once (issue 52, item 5): ``train`` and ``tune`` build
each scenario from its text once, at the command line, and check a learner's hidden size once,
where its config is built (a config filled in for a scenario, or a distiller's actor config,
is not checked again)."""

from __future__ import annotations

from pathlib import Path

import pytest

import envs.scenarios as scenarios_module
import infra.limits
from commands.cli import main as cli


@pytest.fixture
def counted(monkeypatch: pytest.MonkeyPatch) -> dict[str, list]:
    """The scenario texts :func:`envs.scenarios.make_scenario` parsed and the hidden sizes
    :func:`infra.limits.check_hidden` checked (after the learners' modules are imported: their
    default configs are built, and checked, once at import)."""
    import commands.train  # noqa: F401
    import marl.distill  # noqa: F401
    import marl.ppo  # noqa: F401
    import marl.selection  # noqa: F401

    calls: dict[str, list] = {"scenario": [], "hidden": []}
    parse, check = scenarios_module.parse_label, infra.limits.check_hidden

    def parsing(text: str, kind: str = "name") -> tuple[str, dict[str, str]]:
        calls["scenario"].append(text)
        return parse(text, kind)

    def checking(value: int, flag: str = "hidden") -> int:
        calls["hidden"].append(value)
        return check(value, flag)

    monkeypatch.setattr(scenarios_module, "parse_label", parsing)
    monkeypatch.setattr(infra.limits, "check_hidden", checking)
    return calls


@pytest.mark.parametrize("algo, options", [
    ("bdc", ["--steps", "1200", "--episodes-parallel", "2", "--set", "power_baseline_kw=none"]),
    ("distill", ["--steps", "600", "--set", "expert=cacc", "--set", "rounds=1", "--set",
                 "episodes_per_round=1", "--set", "grad_steps=10", "--set", "hidden=16"]),
])
def test_train_parses_its_scenario_and_checks_the_hidden_size_once(
        tmp_path: Path, counted: dict[str, list], algo: str, options: list[str]) -> None:
    assert cli(["train", "--algo", algo, "--scenario", "catchup-v1", "--vehicles", "3",
                *options, "--out", str(tmp_path)]) == 0
    assert counted["scenario"] == ["catchup-v1"]
    assert counted["hidden"] == [16 if algo == "distill" else 64]


def test_tune_carries_the_built_scenario_to_its_trials(tmp_path: Path,
                                                        counted: dict[str, list]) -> None:
    assert cli(["tune", "--algos", "ia2c", "--scenarios", "slowdown-v1", "--trials", "1",
                "--steps", "600", "--vehicles", "2", "--out", str(tmp_path)]) == 0
    assert counted["scenario"] == ["slowdown-v1"]
