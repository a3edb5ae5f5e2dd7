"""Inputs are parsed once, at the command line: a scenario's text is checked by one rule
(:func:`envs.scenarios.make_scenario`), once per item of ``--scenarios``; the harness takes the
built scenarios and never parses the text again (issue 35, item 3)."""

from __future__ import annotations

import pickle
from pathlib import Path

import pandas as pd
import pytest

import envs.scenarios as scenarios_module
from benchmark.suite import KEY_COLUMNS, RunKey, build_sweep, execute_run
from commands.cli import main as cli
from commands.cli import scenarios_argument
from envs.scenarios import as_scenario, make_scenario, parse_scenarios
from infra.errors import ConfigError


@pytest.fixture
def parsed(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The texts :func:`make_scenario` parsed (its first step reads the label: every build of a
    scenario from text, whoever calls it, passes here once)."""
    from benchmark import sweep

    sweep._sine_base.cache_clear()  # the sweep's own leader is built once per process
    calls: list[str] = []
    real = scenarios_module.parse_label

    def counting(text: str, kind: str = "name") -> tuple[str, dict[str, str]]:
        calls.append(text)
        return real(text, kind)

    monkeypatch.setattr(scenarios_module, "parse_label", counting)
    return calls


def test_a_run_parses_each_scenario_once(tmp_path: Path, parsed: list[str]) -> None:
    out = tmp_path / "r"
    assert cli(["run", "--controllers", "ovm,cacc", "--scenarios",
                "catchup-v1,sine-v1:amplitude_mps=2", "--vehicles", "3,4", "--episodes", "2",
                "--lag", "0,0.1", "--executor", "serial", "--out", str(out), "--quiet"]) == 0
    # 2 controllers x 2 scenarios x 2 sizes x 2 lags x 2 seeds = 32 runs, 2 scenarios built;
    # then the standard frequency sweep's own leader (benchmark.sweep), once for the command
    assert parsed == ["catchup-v1", "sine-v1", "sine-v1"]
    runs = pd.read_csv(out / "runs.csv")
    assert len(runs) == 32 and (runs["status"] == "ok").all()
    assert sorted(set(runs["scenario"])) == ["catchup-v1", "sine-v1[amplitude_mps=2.0]"]


def test_a_resumed_run_parses_each_scenario_once(tmp_path: Path, parsed: list[str]) -> None:
    argv = ["run", "--controllers", "ovm", "--scenarios", "brake-v1", "--vehicles", "3",
            "--episodes", "1", "--executor", "serial", "--out", str(tmp_path / "r"), "--quiet"]
    assert cli(argv) == 0
    assert cli([*argv, "--episodes", "2", "--resume"]) == 0
    # once per command, and the standard sweep's own leader once per process (benchmark.sweep)
    assert parsed == ["brake-v1", "sine-v1", "brake-v1"]


def test_the_argument_builds_one_scenario_per_label(parsed: list[str]) -> None:
    built = scenarios_argument("sine-v1:amplitude_mps=2,catchup-v1,sine-v1[amplitude_mps=2.0]")
    assert [sc.label for sc in built] == ["sine-v1[amplitude_mps=2.0]", "catchup-v1"]
    assert len(parsed) == 3  # one per item, never again below
    keys = build_sweep([("ovm", {})], built, [3], [2000, 2010])
    assert {k.scenario for k in keys} == {"sine-v1[amplitude_mps=2.0]", "catchup-v1"}
    assert all(k.built is not None for k in keys) and len(parsed) == 3
    assert as_scenario(built[0]) is built[0] and len(parsed) == 3
    with pytest.raises(ConfigError, match=r"^--scenarios: no scenario named$"):
        scenarios_argument(" , ")
    with pytest.raises(ConfigError, match=r"^--scenario: no scenario named$"):
        scenarios_argument("", "--scenario")


def test_a_key_carries_its_scenario_to_a_worker_and_is_stored_by_label(parsed: list[str]
                                                                       ) -> None:
    (sc,) = parse_scenarios("sine-v1:frequency_hz=0.5")
    (key,) = build_sweep([("ovm", {})], [sc], [3], [2000])
    shipped = pickle.loads(pickle.dumps(key))  # as the process executor sends it
    assert shipped == key and shipped.built == sc and shipped.built.label == sc.label
    del parsed[:]
    rec = execute_run(shipped)
    assert parsed == [] and rec["status"] == "ok"
    # the record holds the label, not the scenario; a key read back from it builds from the
    # label (the only case the harness builds one) and gives the same run
    assert "built" not in rec and rec["scenario"] == "sine-v1[frequency_hz=0.5]"
    again = RunKey(**{k: rec[k] for k in KEY_COLUMNS}, name=rec["name"], options=rec["options"])
    assert again == key and again.id == rec["id"] and again.built is None
    rec2 = execute_run(again)
    assert parsed == ["sine-v1[frequency_hz=0.5]"]
    for col in ("gap_rmse_m", "speed_rmse_mps", "reward", "energy_kwh_per_100km"):
        assert rec2[col] == rec[col]


def test_a_scenario_pickles_with_its_label() -> None:
    sc = make_scenario("mixed-v1", kinds="brake+sine", gap_spread=0.1)
    back = pickle.loads(pickle.dumps(sc))
    assert back == sc and back.label == sc.label == "mixed-v1[gap_spread=0.1,kinds=brake+sine]"
    a = back.episodes([2000, 2010], 3)
    b = sc.episodes([2000, 2010], 3)
    assert (a.leader_speed_mps == b.leader_speed_mps).all() and (a.gap_m == b.gap_m).all()


def test_the_label_is_the_one_scenario_label_gives() -> None:
    for text in ("catchup-v1", "sine-v1:amplitude_mps=1", "sine-v1[frequency_hz=0.5,amplitude_mps=2]",
                 "mixed-v1:kinds=catchup+slowdown+brake+sine", "slowdown-v2"):
        assert make_scenario(text).label == scenarios_module.scenario_label(text)
    assert make_scenario("sine-v1", amplitude_mps=2).label == "sine-v1[amplitude_mps=2.0]"
    # an option named like the id's parameter is an unknown option, not a TypeError
    with pytest.raises(ConfigError, match="has no option 'scenario_id'"):
        make_scenario("sine-v1", **{"scenario_id": "1"})


UNKNOWN = ("cacc-bench: error: unknown scenario 'nope'; valid scenarios are: brake-v1, "
           "catchup-v1, mixed-v1, mixed-v2, openacc-l-v1, openacc-m-v1, openacc-s-v1, "
           "openacc-train-l-v1, "
           "openacc-train-m-v1, openacc-train-s-v1, ring-v1, sine-v1, slowdown-v1, slowdown-v2; "
           "or a ScenarioSpec of your own as package.module:NAME (docs/contributing.md, Add a "
           "scenario)\n")
NO_OPTION = ("cacc-bench: error: scenario sine-v1 has no option 'nope'; its options are: "
             "amplitude_mps, frequency_hz; and the arrangement of every scenario: humans, "
             "cav_fraction, cavs, placement, placement_seed, human_model, reaction_delay_s, "
             "human_noise_mps2, classes, class_mix, class_seed, drag_saving\n")


@pytest.mark.parametrize("argv", [
    ["run", "--scenarios"], ["pareto", "--scenarios"], ["tune", "--scenarios"],
    ["reproduce", "--scenarios"], ["sensitivity", "--scenarios"],
    ["compare-learned", "--scenarios"], ["train", "--algo", "bdc", "--scenario"],
], ids=lambda a: a[0])
@pytest.mark.parametrize("item, message", [("catchup-v1,nope", UNKNOWN),
                                           ("sine-v1:nope=1", NO_OPTION)])
def test_a_bad_scenario_exits_2_with_one_message_on_every_command(
    argv: list[str], item: str, message: str, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert cli([*argv, item, "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == message
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name, key, value, kind", [
    ("bdc", "untrained", "maybe", "bool"), ("bdc", "seed", "x", "int"),
    ("ippo", "seed", "1.5", "int"), ("ippo", "vehicles", "x", "int"),
])
def test_learned_controllers_coerce_options_by_the_one_rule(name: str, key: str, value: str,
                                                            kind: str) -> None:
    from controllers.registry import make_controller

    with pytest.raises(ConfigError,
                       match=rf"^option {key} of {name} must be of type {kind}, got '{value}'$"):
        make_controller(name, **{key: value})
    assert make_controller("bdc", untrained="yes", seed="2").untrained is True


def test_a_scenario_family_is_its_id_without_the_version() -> None:
    from envs.scenarios import SCENARIOS, scenario_family

    assert scenario_family("slowdown-v2") == "slowdown"
    assert scenario_family("openacc-train-s-v1") == "openacc-train-s"
    for bad in ("catchup", "catchup-vx", "-v1", "catchup-1"):
        with pytest.raises(ValueError):
            scenario_family(bad)
    assert all(scenario_family(s) for s in SCENARIOS)
