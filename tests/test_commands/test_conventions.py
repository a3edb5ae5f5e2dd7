"""Command-line conventions: options at their defaults, scenario options, default N, listing."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from commands.cli import main as cli
from controllers.registry import canonical_options, controller_label, controller_options
from envs.scenarios import ARRANGEMENT_DEFAULTS, make_scenario, parse_scenario_list, scenario_label
from infra.errors import ConfigError
from infra.naming import format_label, parse_label, parse_named_list


@pytest.mark.parametrize("name, opts, label", [
    ("ovm", {"alpha": "0.5"}, "ovm"),
    ("ovm", {"alpha": "0.50", "beta": "0.4"}, "ovm[beta=0.4]"),
    ("bdc", {"seed": "0", "mode": "sampled"}, "bdc"),
    ("bdc", {"seed": "1", "mode": "greedy"}, "bdc[mode=greedy,seed=1]"),
    ("cacc", {"feedforward": "true", "kp": "0.2"}, "cacc"),
    ("acc", {"feedforward": "true"}, "acc[feedforward=true]"),
    ("mpc", {"energy_weight": "0.25", "solver": "sqp"}, "mpc"),
    ("duty", {"k": "none"}, "duty"),
])
def test_an_option_at_its_default_adds_nothing_to_the_label(name: str, opts: dict, label: str
                                                            ) -> None:
    assert controller_label(name, opts) == label


def test_a_bad_value_is_kept_for_the_controller_to_refuse() -> None:
    assert canonical_options("ovm", {"alpha": "abc"}) == {"alpha": "abc"}


def test_controller_options_come_from_the_config_with_defaults() -> None:
    assert controller_options("ovm") == {"alpha": 0.5, "beta": 0.5}
    assert controller_options("bdc")["mode"] == "sampled"
    assert "algo" not in controller_options("bdc")  # fixed by the registry, not an option


def test_named_lists_and_labels_round_trip() -> None:
    items = parse_named_list("mpc:horizon=30,solver=ipopt,cacc,sine-v1[amplitude_mps=2.0]", "x")
    assert items == [("mpc", {"horizon": "30", "solver": "ipopt"}), ("cacc", {}),
                     ("sine-v1", {"amplitude_mps": "2.0"})]
    for name, opts in items:
        assert parse_label(format_label(name, opts)) == (name, opts)
    with pytest.raises(ConfigError, match="comes before any x"):
        parse_named_list("k=1,mpc", "x")


def test_scenario_options_on_the_command_line_and_in_labels() -> None:
    assert parse_scenario_list("catchup-v1,sine-v1:amplitude_mps=2,frequency_hz=0.2") == [
        "catchup-v1", "sine-v1[amplitude_mps=2.0]"]
    assert scenario_label("sine-v1:amplitude_mps=1") == "sine-v1"  # the default
    sc = make_scenario("sine-v1[amplitude_mps=2.0,frequency_hz=0.5]")
    assert sc.id == "sine-v1" and sc.options == {"amplitude_mps": 2.0, "frequency_hz": 0.5,
                                                 **ARRANGEMENT_DEFAULTS}
    with pytest.raises(ConfigError, match="has no option 'nope'"):
        parse_scenario_list("sine-v1:nope=1")


def test_run_uses_scenario_labels_default_n_and_one_row_per_setting(tmp_path: Path) -> None:
    out = tmp_path / "r"
    assert cli(["run", "--controllers", "ovm,ovm:alpha=0.5,ovm:beta=0.4", "--scenarios",
                "sine-v1:amplitude_mps=2,openacc-s-v1", "--episodes", "1", "--out", str(out),
                "--quiet"]) == 0
    runs = pd.read_csv(out / "runs.csv")
    assert sorted(set(runs["controller"])) == ["ovm", "ovm[beta=0.4]"]
    by_scenario = runs.groupby("scenario")["n_vehicles"].first().to_dict()
    assert by_scenario == {"openacc-s-v1": 4, "sine-v1[amplitude_mps=2.0]": 8}
    wave = runs[runs["scenario"] == "sine-v1[amplitude_mps=2.0]"]
    # the leader's swing is in the scenario: a larger amplitude, a larger speed spread
    assert cli(["run", "--controllers", "ovm", "--scenarios", "sine-v1", "--episodes", "1",
                "--out", str(tmp_path / "s"), "--quiet"]) == 0
    plain = pd.read_csv(tmp_path / "s" / "runs.csv")
    assert wave["speed_std_mps"].iloc[0] > plain["speed_std_mps"].iloc[0]


def test_list_shows_every_controller_option_with_its_default(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(["list"]) == 0
    out = capsys.readouterr().out
    assert "options: alpha=0.5, beta=0.5" in out
    assert "energy_weight=0.25" in out and "mode=sampled" in out
    assert "N=4 by default" in out


def test_the_energy_modules_are_split_by_purpose_and_small() -> None:
    """Runtime power, the physical models, the vehicle data and the offline fit are separate
    modules, each under 400 lines; the runtime module does not import the fit."""
    folder = Path(__file__).resolve().parents[2] / "envs" / "energy"
    sizes = {p.name: len(p.read_text().splitlines()) for p in folder.glob("*.py")}
    assert set(sizes) == {"__init__.py", "vehicle.py", "map_model.py", "horner.py", "power.py",
                          "fit.py", "classes.py"}
    assert max(sizes.values()) < 400, sizes
    assert "envs.energy.fit" not in (folder / "power.py").read_text()


@pytest.mark.parametrize(("value", "kind", "expected"), [
    ("true", bool, True), ("Off", bool, False), ("3", int, 3), ("2.5", float, 2.5),
    ("none", float | None, None), ("1e-3", float | None, 1e-3), ("ipopt", str, "ipopt"),
    (0.5, float, 0.5),
])
def test_one_coercion_rule_for_every_option(value: object, kind: object, expected: object
                                            ) -> None:
    from infra.naming import coerce_option

    assert coerce_option(value, kind, "k", "owner") == expected


@pytest.mark.parametrize(("value", "kind"), [("maybe", bool), ("2.5", int), ("nan", float),
                                             ("inf", float | None), ("x", float)])
def test_the_coercion_rule_refuses_with_the_option_and_its_owner(value: str, kind: object
                                                                 ) -> None:
    from infra.naming import coerce_option

    with pytest.raises(ConfigError, match=f"^option k of owner must be of type .*got '{value}'$"):
        coerce_option(value, kind, "k", "owner")


def test_every_document_the_code_cites_is_in_the_repository() -> None:
    """Docstrings and messages cite files of this repository only (``docs/...``)."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    cited = set()
    for pkg in ("infra", "envs", "controllers", "marl", "benchmark", "analysis", "studies",
                "commands"):
        for py in (root / pkg).rglob("*.py"):
            text = py.read_text()
            cited |= set(re.findall(r"docs/[\w./-]+\.md", text))
            assert not re.search(r"(?<!docs/)\bspec/\w+\.md", text), py
    assert "docs/spec/energy.md" in cited
    missing = sorted(c for c in cited if not (root / c).is_file())
    assert not missing, missing
