"""``run --simulator sumo`` and ``sumo-compare``: refused with the install command without the
extra (exit 2), and, with it, the issue's command in small form: SUMO's runs keep rows of their
own (``cacc@sumo``), the built-in runs' keys and labels are unchanged."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
import pytest

from commands.cli import main

HAS_SUMO = importlib.util.find_spec("libsumo") is not None


@pytest.mark.parametrize("argv", [
    ["run", "--simulator", "sumo", "--controllers", "cacc", "--episodes", "1"],
    ["sumo-compare", "--episodes", "1"],
])
def test_without_the_extra_sumo_is_refused_with_the_install_command(
        argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    import envs.sumo

    monkeypatch.setattr(envs.sumo, "sumo_available", lambda: False)
    out = tmp_path / "r"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "pip install -e '.[sumo]'" in err and "Traceback" not in err
    assert not out.exists()


def test_a_builtin_key_and_label_are_unchanged_by_the_simulator_field() -> None:
    from benchmark.suite import build_sweep

    builtin = build_sweep([("cacc", {})], ["catchup-v1"], [8], [2000])[0]
    assert builtin.id == "cacc|catchup-v1|n8|d0.0|l0.0|tau0.0|s2000"
    assert builtin.file_stem == "cacc__catchup-v1__n8__s2000"
    sumo = build_sweep([("cacc", {})], ["catchup-v1"], [8], [2000], simulator="sumo")[0]
    assert sumo.controller == "cacc@sumo" and sumo.id != builtin.id and sumo != builtin


@pytest.mark.skipif(not HAS_SUMO, reason="needs the sumo extra: pip install -e '.[sumo]'")
def test_the_issues_command_runs_in_small_form(tmp_path: Path) -> None:
    out = tmp_path / "r"
    assert main(["run", "--simulator", "sumo", "--controllers", "acc,cacc,mpc-qp,bdc,plexe:ploeg",
                 "--scenarios", "catchup-v1,slowdown-v1", "--episodes", "1", "--quiet",
                 "--out", str(out)]) == 0
    runs = pd.read_csv(out / "runs.csv")
    assert sorted(set(runs["controller"])) == ["acc@sumo", "bdc@sumo", "cacc@sumo",
                                               "mpc-qp@sumo", "plexe:ploeg@sumo"]
    assert (runs["status"] == "ok").all() and not runs["collision"].any()
    board = pd.read_csv(out / "leaderboard.csv")
    assert len(board) == 10
    # the built-in runs of the same settings are other rows with the same numbers
    assert main(["run", "--controllers", "cacc", "--scenarios", "catchup-v1", "--episodes", "1",
                 "--quiet", "--out", str(out), "--resume"]) == 0
    runs = pd.read_csv(out / "runs.csv").set_index("controller")
    assert runs.loc["cacc", "reward"] == pytest.approx(
        runs[runs["scenario"] == "catchup-v1"].loc["cacc@sumo", "reward"], rel=1e-9)


@pytest.mark.skipif(not HAS_SUMO, reason="needs the sumo extra: pip install -e '.[sumo]'")
def test_a_plexe_model_without_sumo_simulator_is_refused(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--controllers", "plexe:ploeg", "--episodes", "1",
                 "--out", str(tmp_path / "r")]) == 2
    assert "add --simulator sumo" in capsys.readouterr().err
