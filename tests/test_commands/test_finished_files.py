"""Issue 53, "a finished file changes only when asked": ``train`` and ``tune`` refuse a folder
holding finished work of the command unless ``--resume`` or ``--overwrite`` says what to do
(as ``run`` refuses a folder of stored runs), train's default output is never the shipped
``controllers/checkpoints``, ``--steps`` binds ``distill``, and ``tune`` on a full disk ends
in one line."""

from __future__ import annotations

import hashlib
import shlex
from pathlib import Path

import pytest
import torch

from commands.cli import main as cli

ROOT = Path(__file__).resolve().parents[2]
#: A tiny shared-policy training (seconds).
IPPO = ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--vehicles", "2", "--steps", "64",
        "--set", "rollout_steps=8", "--episodes-parallel", "4", "--set", "eval_every_steps=32"]
STEM = "ippo__catchup-v1__n2__s0"


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.iterdir()) if p.is_file() and p.name != "store.lock"}


def _shipped() -> dict[str, int]:
    return {str(p): p.stat().st_mtime_ns for p in (ROOT / "controllers" / "checkpoints").rglob("*")}


def test_train_writes_to_results_refuses_a_second_run_and_overwrites_when_asked(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    shipped = _shipped()
    assert cli(IPPO) == 0  # default --out: results/checkpoints here, never the shipped folder
    out = tmp_path / "results" / "checkpoints"
    assert (out / f"{STEM}.pt").exists() and _shipped() == shipped
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == ("evaluate with: cacc-bench run --controllers "
                    "ippo:checkpoint_dir=results/checkpoints,vehicles=2 --scenarios catchup-v1 "
                    "--vehicles 2")
    run = shlex.split(last.removeprefix("evaluate with: "))[1:]
    assert cli([*run, "--episodes", "1", "--quiet", "--out", str(tmp_path / "r")]) == 0
    before = _digests(out)
    capsys.readouterr()
    assert cli(IPPO) == 2  # run twice: refused, nothing changed
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [
        "cacc-bench: error: results/checkpoints already holds 1 finished run of this command "
        f"({STEM}); add --resume to complete that command (finished runs are kept), "
        "--overwrite to do it all again (a run's files are replaced when it finishes), or "
        "choose another --out"]
    assert _digests(out) == before
    assert cli([*IPPO, "--resume", "--overwrite"]) == 2
    assert "exclude each other" in capsys.readouterr().err and _digests(out) == before
    stamp = (out / f"{STEM}.pt").stat().st_mtime_ns
    assert cli([*IPPO, "--overwrite"]) == 0
    err = capsys.readouterr().err
    assert [ln for ln in err.splitlines() if "--overwrite" in ln] == [
        f"--overwrite: results/checkpoints holds 1 finished run of this command ({STEM}); "
        "doing it all again: a run's files are replaced when it finishes"]
    assert (out / f"{STEM}.pt").stat().st_mtime_ns != stamp and _shipped() == shipped


@pytest.mark.parametrize("algo, held", [("bdc", ".pt"), ("bdc", ".final.pt"),
                                        ("distill", ".pt"), ("mappo", ".curve.csv")])
def test_any_finished_file_of_a_run_is_refused_for_every_family(
        algo: str, held: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A file of the run (a shipped paper learner's .pt has no .final.pt) is finished work."""
    path = tmp_path / f"{algo}__catchup-v1__n2__s0{held}"
    path.write_bytes(b"finished")
    assert cli(["train", "--algo", algo, "--scenario", "catchup-v1", "--vehicles", "2",
                "--steps", "64", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "already holds 1 finished run" in err and len(err.strip().splitlines()) == 1
    assert path.read_bytes() == b"finished" and not list(tmp_path.glob("*.log"))


def test_steps_bind_distill(tmp_path: Path) -> None:
    """``train --algo distill --steps`` ignored --steps (its rounds decided): now collecting
    stops at --steps (the round in progress is fitted and is the last)."""
    assert cli(["train", "--algo", "distill", "--scenario", "catchup-v1", "--vehicles", "2",
                "--steps", "1000", "--set", "expert=cacc", "--set", "grad_steps=20",
                "--set", "episodes_per_round=2", "--out", str(tmp_path)]) == 0
    data = torch.load(tmp_path / "distill__catchup-v1__n2__s0.pt", weights_only=True)
    assert data["steps"] == 1000 and data["config"]["rounds"] == 5  # rounds: 6,000 steps
    assert data["curve_summary"]["budget_steps"] == 1000


def test_tune_on_a_full_disk_says_so_in_one_line(tmp_path: Path) -> None:
    """Its study file could not be written: 90 lines of SQLAlchemy's error, now one
    (RLIMIT_FSIZE stands in for a full disk)."""
    import resource
    import signal
    import subprocess
    import sys

    def limited() -> None:  # files may not grow past 60 kB: the study file cannot be made
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))

    proc = subprocess.run([sys.executable, "-m", "commands", "tune", "--algos", "ippo",
                           "--scenarios", "catchup-v1", "--vehicles", "2", "--trials", "1",
                           "--steps", "2048", "--set", "rollout_steps=8",
                           "--out", str(tmp_path / "tu")], capture_output=True, text=True,
                          timeout=300, cwd=ROOT, preexec_fn=limited)
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1, proc.stderr
    assert "could not be written" in err[0] and "rerun with --resume" in err[0]
    assert "ippo__catchup-v1__n2.sqlite3" in err[0]


def test_tune_overwrite_starts_its_studies_again(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A tuned folder: refused without an option; --overwrite deletes this command's study
    and results first and says so in one line."""
    (tmp_path / "studies").mkdir()
    study = tmp_path / "studies" / "ippo__catchup-v1__n2.sqlite3"
    study.write_bytes(b"not a study")
    (tmp_path / "tuned_configs.json").write_text("{}")
    args = ["tune", "--algos", "ippo", "--scenarios", "catchup-v1", "--vehicles", "2",
            "--trials", "1", "--steps", "2048", "--set", "rollout_steps=8",
            "--set", "eval_every_steps=2048", "--out", str(tmp_path)]
    assert cli(args) == 2
    assert "already holds 2 tuning results" in capsys.readouterr().err
    assert study.read_bytes() == b"not a study"
    assert cli([*args, "--overwrite"]) == 0
    err = capsys.readouterr().err
    assert len([ln for ln in err.splitlines() if ln.startswith("--overwrite:")]) == 1
    assert study.read_bytes() != b"not a study"
    assert "ippo/catchup-v1" in (tmp_path / "tuned_configs.json").read_text()
