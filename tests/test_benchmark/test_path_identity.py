"""Paths do not change identities (issue 32, item 5): a run's key and label never hold a
folder's spelling; resuming with the folder spelled differently (absolute, relative, through a
link) or after moving it reruns nothing; reports print paths relative to their folder."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pandas as pd
import pytest

from benchmark.work_folder import command_text
from commands.cli import main as cli

STUDY = ["sensitivity", "--scenarios", "catchup-v1", "--knobs", "v2v", "--steps", "1800",
         "--validation-episodes", "2", "--episodes", "2"]


def test_a_sensitivity_study_resumes_under_any_spelling_of_its_folder(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    assert cli([*STUDY, "--out", "study"]) == 0  # relative
    capsys.readouterr()
    table = pd.read_csv(tmp_path / "study" / "sensitivity.csv")
    runs = pd.read_csv(tmp_path / "study" / "runs" / "runs.csv")
    labels = set(runs["controller"])
    assert "bdc[checkpoint_dir=checkpoints/base]" in labels
    assert not any(str(tmp_path) in label or "study" in label for label in labels)
    report = (tmp_path / "study" / "report.md").read_text()
    assert str(tmp_path) not in report and "--out OUT" in report
    os.symlink(tmp_path / "study", tmp_path / "link")
    shutil.move(tmp_path / "study", tmp_path / "moved")  # the link now dangles
    (tmp_path / "link").unlink()
    os.symlink(tmp_path / "moved", tmp_path / "link")
    for spelling in (str(tmp_path / "moved"), "link", "./moved/../link"):
        assert cli([*STUDY, "--out", spelling, "--resume"]) == 0, spelling
        err = capsys.readouterr().err
        assert "0 to train" in err and "0 to run" in err, (spelling, err)
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "moved" / "sensitivity.csv"), table)
    assert set(pd.read_csv(tmp_path / "moved" / "runs" / "runs.csv")["controller"]) == labels
    assert Path.cwd() == tmp_path  # the command's working folder is restored


def test_reproduction_labels_name_checkpoint_folders_relative_to_the_output() -> None:
    """reproduce plans inside its --out: labels read ``checkpoint_dir=checkpoints[/name]``."""
    from commands.reproduce import _train_plan, eval_keys
    from studies.paper import BUDGETS, STUDIES

    jobs = _train_plan(["bdc"], ["catchup-v1"], BUDGETS["quick"], Path("."), set(STUDIES))
    keys, names = eval_keys(jobs, ["catchup-v1"], BUDGETS["quick"])
    dirs = {opt.split("=", 1)[1] for k in keys for opt in k.controller.strip("]").split("[")[-1]
            .split(",") if opt.startswith("checkpoint_dir=")}
    assert dirs == {"checkpoints", "checkpoints/bdc-noqsgd"}
    assert all('"checkpoint_dir": "checkpoints' in k.options for k in keys
               if "checkpoint_dir" in k.options)
    assert {"bdc", "bdc-noqsgd"} <= set(names.values())


@pytest.mark.parametrize("argv, text", [
    (["--budget", "paper", "--out", "/abs/results/paper", "--resume"],
     "cacc-bench reproduce --budget paper --out OUT --resume"),
    (["--out=rel/x", "--algos", "bdc"], "cacc-bench reproduce --out=OUT --algos bdc"),
    (["--algos", "bdc"], "cacc-bench reproduce --algos bdc"),
])
def test_a_report_prints_the_command_without_its_folder(argv: list[str], text: str) -> None:
    assert command_text("cacc-bench reproduce", argv) == text
