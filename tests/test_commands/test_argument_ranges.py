"""Refused before any work, exit 2, one line (issue 32, item 4): numbers outside the ranges
that keep the work finite and allocatable, empty strings, paths that cannot be written, and a
policy that cannot run in the asked setting."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from commands.cli import main as cli
from infra.limits import MAX_SEED, MAX_TRAIN_SEED

TRAIN = ["train", "--algo", "bdc", "--scenario", "catchup-v1", "--vehicles", "2",
         "--steps", "10"]
TUNE = ["tune", "--algos", "bdc", "--scenarios", "catchup-v1", "--trials", "1", "--steps", "10"]
RUN = ["run", "--controllers", "cacc", "--scenarios", "catchup-v1", "--episodes", "1"]

CASES = {
    "run --comm-delay 1e9": ([*RUN, "--comm-delay", "1e9"], "--comm-delay must lie in [0, 60] s"),
    "stability --delay 1e308": (["stability", "--controllers", "cacc", "--delay", "1e308"],
                                "--delay must lie in [0, 60] s"),
    "stability --n-omega 1e8": (["stability", "--controllers", "cacc", "--empirical",
                                 "--n-omega", "100000000"], "--n-omega must lie in 1..1000"),
    "stability --omega-min tiny": (["stability", "--controllers", "cacc", "--empirical",
                                    "--omega-min", "1e-300"], "lower --n-omega or raise"),
    "train --seed huge": ([*TRAIN, "--seed", "99999999999999"],
                          f"--seed must lie in 0..{MAX_TRAIN_SEED}"),
    "train --seed past the episode seeds": ([*TRAIN, "--seed", str(MAX_TRAIN_SEED + 1)],
                                            f"--seed must lie in 0..{MAX_TRAIN_SEED}"),
    "train --seeds huge": ([*TRAIN, "--seeds", "0,99999999999999999999"],
                           "--seeds must lie in 0.."),
    "train --episodes-parallel 1e6": ([*TRAIN, "--episodes-parallel", "1000000"],
                                      "--episodes-parallel must lie in 1..4096"),
    "train --steps 1e12": ([*TRAIN[:-2], "--steps", "1000000000000"], "--steps must lie in 1.."),
    "tune --seed huge": ([*TUNE, "--seed", "99999999999999999999"],
                         f"--seed must lie in 0..{MAX_TRAIN_SEED}"),
    "tune --trials 1e9": ([*TUNE[:-4], "--trials", "1000000000", "--steps", "10"],
                          "--trials must lie in 1..1000"),
    "sensitivity --seeds huge": (["sensitivity", "--seeds", "99999999999999999999"],
                                 f"--seeds must lie in 0..{MAX_TRAIN_SEED}"),
    "perf --only empty": (["perf", "--only", ""], "--only: no part named"),
    "perf --population huge": (["perf", "--only", "train", "--population", "1000000"],
                               "--population must lie in 0..256"),
    "run --out empty": ([*RUN, "--out", ""], "--out is empty"),
    "train --out empty": ([*TRAIN, "--out", ""], "--out is empty"),
    "fit-power --figure empty": (["fit-power", "--figure", ""], "--figure is empty"),
    "run --out 300 characters": ([*RUN, "--out", "x" * 300], "choose a shorter --out"),
    "train --out 300 characters": ([*TRAIN, "--out", "d/" + "x" * 300], "choose a shorter --out"),
    "stability --out 300 characters": (["stability", "--controllers", "cacc", "--out",
                                        "x" * 300], "choose a shorter --out"),
    **{f"{argv[0]} --ray-address that does not answer": (
        [*argv, "--executor", "ray", "--ray-address", "127.0.0.1:1"], "does not answer")
       for argv in (TRAIN, TUNE, ["reproduce"], ["sensitivity"], ["pareto"])},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_refused_before_any_work_in_one_line(
        case: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    argv, message = CASES[case]
    monkeypatch.chdir(tmp_path)
    if "--out" not in argv and argv[0] not in ("perf", "fit-power"):
        argv = [*argv, "--out", str(tmp_path / "out")]
    assert cli(argv) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert "Traceback" not in err
    lines = [line for line in err.strip().splitlines() if not line.startswith("DEBUG")]
    assert len(lines) == 1, err
    assert not list(tmp_path.iterdir())  # nothing written, not even into the current folder


def test_the_seed_bounds_are_the_generators() -> None:
    """A training seed's episode seeds (1e7 (seed + 1) + episode) stay in a 32-bit generator's
    range for the longest run; every other seed is a 31-bit one."""
    from infra.limits import MAX_EPISODES_PARALLEL, MAX_TRAIN_STEPS, TRAIN_SEED_STRIDE

    assert MAX_SEED == 2**31 - 1
    top = TRAIN_SEED_STRIDE * (MAX_TRAIN_SEED + 1) + MAX_TRAIN_STEPS + MAX_EPISODES_PARALLEL
    assert top < 2**32 <= top + TRAIN_SEED_STRIDE


def test_the_largest_training_seed_trains(tmp_path: Path) -> None:
    assert cli(["train", "--algo", "bdc", "--scenario", "catchup-v1", "--vehicles", "2",
                "--steps", "400", "--seed", str(MAX_TRAIN_SEED),
                "--out", str(tmp_path)]) == 0
    assert (tmp_path / f"bdc__catchup-v1__n2__s{MAX_TRAIN_SEED}.pt").exists()


def test_a_policy_without_a_sine_checkpoint_is_refused_naming_the_option_that_works(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert cli(["stability", "--controllers", "bdc", "--empirical", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--controllers bdc:scenario=catchup-v1" in err and "Traceback" not in err
    assert not out.exists()  # refused at the preflight, before any sweep or figure


@pytest.mark.parametrize("target", ["file", "file-parent", "no-permission"])
def test_an_output_folder_that_cannot_be_written_is_refused(
        target: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """As a folder (an existing file, a file on the way) or without permission (injected: root
    passes every permission check)."""
    (tmp_path / "f").write_text("x")
    out = {"file": tmp_path / "f", "file-parent": tmp_path / "f" / "sub",
           "no-permission": tmp_path / "locked" / "sub"}[target]
    if target == "no-permission":
        import tempfile

        def denied(*a: object, **k: object) -> str:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))

        monkeypatch.setattr(tempfile, "mkdtemp", denied)
    assert cli([*TRAIN, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not list(tmp_path.rglob("*.pt"))


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("results") / "r"
    assert cli(["run", "--controllers", "ovm,cacc", "--scenarios", "catchup-v1",
                "--episodes", "1", "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize("target", ["file", "file-parent", "empty"])
def test_plot_refuses_an_output_that_cannot_be_a_folder(
        results: Path, tmp_path: Path, target: str, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "f").write_text("x")
    out = {"file": str(tmp_path / "f"), "file-parent": str(tmp_path / "f" / "sub"),
           "empty": ""}[target]
    assert cli(["plot", str(results), "--out", out]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "f").read_text() == "x"


@pytest.mark.parametrize("name", ["runs.csv", "leaderboard.csv", "store.lock"])
def test_a_folder_where_a_results_file_belongs_is_refused(
        results: Path, tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    folder = tmp_path / "r"
    shutil.copytree(results, folder)
    target = folder / name
    target.unlink(missing_ok=True)
    target.mkdir()
    argv = (["run", "--controllers", "ovm,cacc", "--scenarios", "catchup-v1", "--episodes",
             "1", "--out", str(folder), "--resume"] if name == "store.lock"
            else ["leaderboard", str(folder)])
    assert cli(argv) == 2
    err = capsys.readouterr().err
    assert f"{target} is a folder" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert target.is_dir()


@pytest.mark.parametrize("name", ["runs.csv", "leaderboard.csv"])
def test_a_folder_where_a_csv_belongs_refuses_a_sweep_before_any_run(
        results: Path, tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]) -> None:
    """`run --resume` with runs left to do used to run and store them, then stop at the CSV;
    now the sweep is refused first and the store is not touched."""
    import hashlib
    import shutil

    folder = tmp_path / "r"
    shutil.copytree(results, folder)
    (folder / name).unlink()
    (folder / name).mkdir()
    store = hashlib.sha256((folder / "store.sqlite").read_bytes()).hexdigest()
    assert cli(["run", "--controllers", "ovm,cacc", "--scenarios", "catchup-v1", "--episodes",
                "2", "--out", str(folder), "--resume", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{folder / name} is a folder" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and "resuming" not in err
    assert hashlib.sha256((folder / "store.sqlite").read_bytes()).hexdigest() == store


def test_a_closed_pipe_ends_list_quietly() -> None:
    """`cacc-bench list | head`: the reader went away; no BrokenPipeError traceback, status
    128 + SIGPIPE (deterministic: the pipe's reading end is closed before the command starts)."""
    import signal
    import subprocess
    import sys

    read, write = os.pipe()
    os.close(read)
    try:
        proc = subprocess.run([sys.executable, "-m", "commands", "list"], stdout=write,
                              stderr=subprocess.PIPE, text=True, timeout=120,
                              cwd=Path(__file__).resolve().parents[2])
    finally:
        os.close(write)
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr
    assert proc.returncode == 128 + signal.SIGPIPE


def test_a_packet_loss_is_checked_by_one_rule(monkeypatch: pytest.MonkeyPatch) -> None:
    """The channel and `run --packet-loss` both go through infra.limits.check_packet_loss."""
    import infra.limits
    from commands.cli import main as cli
    from envs.channel import ChannelConfig

    calls: list[str] = []
    real = infra.limits.check_packet_loss

    def spy(value: float, flag: str = "the packet loss") -> float:
        calls.append(flag)
        return real(value, flag)

    monkeypatch.setattr(infra.limits, "check_packet_loss", spy)
    ChannelConfig(0.0, 0.3)
    assert cli(["run", "--packet-loss", "1.5", "--out", "/nonexistent/x"]) == 2
    assert calls == ["the packet loss", "--packet-loss"]


def test_the_hidden_width_has_one_rule_for_every_learner() -> None:
    """``infra.limits.check_hidden``: the paper's learners, the shared ones and the distiller
    refuse the same widths with the same message."""
    from infra.errors import ConfigError
    from infra.limits import MAX_HIDDEN
    from marl.config import A2CConfig
    from marl.distill import DistillConfig
    from marl.ppo_nets import PPOConfig

    for cls in (A2CConfig, PPOConfig, DistillConfig):
        for bad in (0, MAX_HIDDEN + 1):
            with pytest.raises(ConfigError, match=f"hidden must lie in 1..{MAX_HIDDEN:,}"):
                cls(hidden=bad)
        assert cls(hidden=MAX_HIDDEN).hidden == MAX_HIDDEN
