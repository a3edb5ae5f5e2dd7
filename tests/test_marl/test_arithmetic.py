"""Portable arithmetic (marl.arithmetic): MKL's COMPATIBLE branch and AVX2 kernels in fresh
processes, the same weights on every processor measured, recorded in the checkpoint, checked on
resume, refused where it cannot hold."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from pinned_training import portable_pins, weights_hash, weights_hash_and_kernels
from run_marks import FULL

from benchmark.executors import map_jobs
from commands.cli import main
from envs.scenarios import make_scenario
from infra.errors import ConfigError
from marl import arithmetic
from marl.arithmetic_fingerprint import PINNED_ALGOS
from marl.training import PolicyJob, TrainingKey, learner_config


def test_portable_training_is_pinned_on_every_processor() -> None:
    """The serial executor runs items whose environment this process lacks in a worker process
    started with it; there the short trainings give the portable hashes, which an Intel Xeon
    and an AMD EPYC share."""
    assert arithmetic.current() == "native"  # this process: MKL's processor-specific kernels
    pins = portable_pins()
    names = list(PINNED_ALGOS)
    got = dict(zip(names, map_jobs(weights_hash, names, "serial",
                                   env=arithmetic.process_env("portable")), strict=True))
    assert {n: mode for n, (_, mode) in got.items()} == dict.fromkeys(names, "portable")
    assert {n: h for n, (h, _) in got.items()} == pins


def test_portable_hashes_hold_on_avx2_kernels() -> None:
    """MKL forced to its AVX2 kernels as well: the portable training gives the pinned hash
    (the libraries read these variables at start), whatever instruction sets MKL uses."""
    env = {**arithmetic.process_env("portable"), "MKL_ENABLE_INSTRUCTIONS": "AVX2",
           "ATEN_CPU_CAPABILITY": "avx2"}
    pins = portable_pins()
    got = list(map_jobs(weights_hash_and_kernels, ["bdc"], "serial", env=env))
    assert got == [(pins["bdc"], "portable", "AVX2")]


@FULL
def test_process_workers_start_portable() -> None:
    """Process workers hold the mode from their start: the serial executor's hash."""
    pins = portable_pins()
    got = list(map_jobs(weights_hash, ["dial"], "process", 1,
                        env=arithmetic.process_env("portable")))
    assert got == [(pins["dial"], "portable")]


@FULL
@pytest.mark.ray
def test_ray_workers_train_portably(tmp_path: Path) -> None:
    """Ray starts workers with the mode (a runtime environment): the checkpoints of a portable
    run on Ray record it and equal the serial executor's."""
    pytest.importorskip("ray")
    common = ["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--vehicles", "3",
              "--steps", "300", "--episodes-parallel", "2", "--arithmetic", "portable"]
    assert main([*common, "--out", str(tmp_path / "serial")]) == 0
    assert main([*common, "--executor", "ray", "--workers", "1",
                 "--out", str(tmp_path / "ray")]) == 0
    name = "ia2c__catchup-v1__n3__s0.final.pt"
    a, b = (torch.load(tmp_path / d / name, weights_only=True) for d in ("serial", "ray"))
    assert arithmetic.of_summary(b["curve_summary"]) == "portable"
    assert a["weights"].keys() == b["weights"].keys()
    assert all(torch.equal(a["weights"][k], b["weights"][k]) for k in a["weights"])


def test_the_portable_environment_pins_avx2_kernels_where_the_processor_has_them(
        monkeypatch) -> None:
    """MKL's branch everywhere; with AVX2 and FMA also PyTorch's, OpenBLAS's and numpy's AVX2
    kernels (numpy's AVX-512 targets named from numpy's own list); without, none of those."""
    from numpy._core import _multiarray_umath as umath

    features = umath.__cpu_features__
    monkeypatch.setitem(features, "AVX2", True)
    monkeypatch.setitem(features, "FMA3", True)
    monkeypatch.setattr(umath, "__cpu_dispatch__", ["X86_V3", "X86_V4", "AVX512_ICL"])
    assert arithmetic.portable_env.__wrapped__() == {
        "MKL_CBWR": "COMPATIBLE", "ATEN_CPU_CAPABILITY": "avx2", "OPENBLAS_CORETYPE": "Haswell",
        "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL"}
    monkeypatch.setitem(features, "AVX2", False)
    assert arithmetic.portable_env.__wrapped__() == {"MKL_CBWR": "COMPATIBLE"}


def test_a_partly_portable_process_trains_natively_only(monkeypatch) -> None:
    """Part of the portable environment (a machine that sets ``OPENBLAS_CORETYPE`` for every
    process) is native arithmetic: a portable run is refused there, a native one is not."""
    from commands.train import train_job

    monkeypatch.setattr(arithmetic, "portable_env", lambda: {"MKL_CBWR": "COMPATIBLE",
                                                             "OPENBLAS_CORETYPE": "Haswell"})
    monkeypatch.delenv("MKL_CBWR", raising=False)
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Haswell")
    assert arithmetic.current() == "native"
    arithmetic.require("native")
    key = TrainingKey("ia2c", make_scenario("catchup-v1"), 3, (0,), 300, learner_config("ia2c", {}),
                      Path("unused"), "portable")
    with pytest.raises(ConfigError, match="a portable training run in a partly portable"):
        train_job(key)


def test_modes_and_their_records() -> None:
    assert arithmetic.process_env("native") == {}
    assert arithmetic.process_env("portable") == arithmetic.portable_env()
    assert arithmetic.portable_env()["MKL_CBWR"] == "COMPATIBLE"
    assert arithmetic.summary("native") == {}
    assert arithmetic.of_summary(arithmetic.summary("portable")) == "portable"
    assert arithmetic.of_summary({"wall_s": 1.0}) == "native"  # checkpoints from before
    with pytest.raises(ConfigError, match="expected one of native, portable"):
        arithmetic.check_mode("fast")


def test_a_portable_run_is_refused_in_a_native_process(monkeypatch) -> None:
    """The libraries read their settings once, at start or first use: a process started without
    them cannot train portably, and one started with them cannot train natively."""
    from dataclasses import replace

    from commands.train import train_job

    key = TrainingKey("ia2c", make_scenario("catchup-v1"), 3, (0,), 300, learner_config("ia2c", {}),
                      Path("unused"), "portable")
    for name in arithmetic.portable_env():  # whatever the machine sets for every process
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(ConfigError, match="portable training run in a native process"):
        train_job(key)
    for name, value in arithmetic.portable_env().items():
        monkeypatch.setenv(name, value)
    with pytest.raises(ConfigError, match="native training run in a portable process"):
        train_job(replace(key, arithmetic="native"))


def test_train_records_portable_arithmetic_and_resume_checks_it(tmp_path: Path, capsys) -> None:
    """``cacc-bench train --arithmetic portable`` (serial: one worker process) records the mode
    in the checkpoint; ``--resume`` in the other mode refuses the finished run (exit 2)."""
    common = ["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--vehicles", "3",
              "--steps", "300", "--episodes-parallel", "2", "--out", str(tmp_path)]
    assert main([*common, "--arithmetic", "portable"]) == 0
    for suffix in (".pt", ".final.pt"):
        data = torch.load(tmp_path / f"ia2c__catchup-v1__n3__s0{suffix}", weights_only=True)
        assert arithmetic.of_summary(data["curve_summary"]) == "portable"
    capsys.readouterr()
    assert main([*common, "--arithmetic", "portable", "--resume"]) == 0
    assert "1 of 1 runs already finished" in capsys.readouterr().err
    assert main([*common, "--resume"]) == 2
    err = capsys.readouterr().err
    assert "trained with portable arithmetic, not native" in err and "Traceback" not in err


def test_the_shared_learners_refuse_portable_arithmetic(tmp_path: Path, capsys) -> None:
    """They train in the command's own process, where MKL may have chosen its kernels."""
    assert main(["train", "--algo", "ippo", "--scenario", "catchup-v1", "--arithmetic",
                 "portable", "--out", str(tmp_path)]) == 2
    assert "shared-policy learners train natively" in capsys.readouterr().err


def test_the_training_stage_records_portable_runs(tmp_path: Path) -> None:
    """``reproduce``'s and ``sensitivity``'s training stage trains portably when asked, and its
    ``source.json`` says so; the report says what a reader's rerun gives."""
    from types import SimpleNamespace

    from commands.policy_training import train_stage
    from studies.reproduction_report import _arithmetic_sentence

    job = PolicyJob("ia2c", make_scenario("catchup-v1"), 3, (0,), 300,
                    learner_config("ia2c", {"episodes_parallel": 2}), tmp_path,
                    validation_episodes=2, name="ia2c", study="main")
    args = SimpleNamespace(executor="serial", workers=1, ray_address=None, population=None,
                           arithmetic="portable")
    train_stage([job], args, reuse_shipped=False)
    assert json.loads(job.file(".source.json").read_text())["arithmetic"] == "portable"
    assert "same weights and evaluates the same numbers on an Intel Xeon" in _arithmetic_sentence(
        "portable")
    assert "holds them on every processor measured" in _arithmetic_sentence("native")
    assert "`--arithmetic portable`" in _arithmetic_sentence("native")


def test_a_reproduction_folder_from_before_is_native(tmp_path: Path, capsys) -> None:
    """A manifest without ``arithmetic`` was trained natively: resuming it portably (the
    default) is another setting, refused before anything trains."""
    settings = {"budget": "quick", "algos": ["bdc"], "scenarios": ["catchup-v1"],
                "studies": []}
    (tmp_path / "reproduce.json").write_text(json.dumps({"settings": settings}))
    assert main(["reproduce", "--budget", "quick", "--algos", "bdc", "--scenarios",
                 "catchup-v1", "--skip", "ablations,sizes,openacc", "--out", str(tmp_path),
                 "--resume"]) == 2
    assert "other settings" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reproduce.json"]


def test_portable_arithmetic_is_refused_on_a_gpu() -> None:
    from commands.train import check_arithmetic

    check_arithmetic("portable", "cpu")
    check_arithmetic("native", "cuda")
    with pytest.raises(ConfigError, match="portable arithmetic is the CPU's"):
        check_arithmetic("portable", "cuda:0")


@pytest.mark.parametrize("mode", ["portable", "native"])
def test_reproduce_evaluates_with_its_training_arithmetic(monkeypatch, tmp_path: Path,
                                                          mode: str) -> None:
    """The evaluation workers hold the training's arithmetic from their start: MKL's kernels
    also round the policies' sampled actions (with its AVX2 kernels forced, one episode of the
    paper report's 4,950 came out otherwise, natively)."""
    from types import SimpleNamespace

    import commands.run
    from commands.reproduce import eval_stage
    from envs.scenarios import as_scenario
    from studies.paper import BUDGETS

    seen: dict = {}

    def sweep(keys, out, **options):
        seen.update(options, n=len(keys))
        return 0

    monkeypatch.setattr(commands.run, "execute_sweep", sweep)
    args = SimpleNamespace(executor="serial", workers=1, ray_address=None, arithmetic=mode)
    eval_stage([], [as_scenario("catchup-v1")], BUDGETS["quick"], args, tmp_path)
    assert seen["n"] > 0 and seen["env"] == arithmetic.process_env(mode)


class _Evaluated(Exception):
    """Raised by a stand-in evaluation, to stop the command there."""


@pytest.mark.parametrize("mode", ["portable", "native"])
def test_sensitivity_evaluates_with_its_training_arithmetic(monkeypatch, tmp_path: Path,
                                                            mode: str) -> None:
    import commands.policy_training
    import commands.run

    seen: dict = {}

    def sweep(keys, out, **options):
        seen.update(options)
        raise _Evaluated

    monkeypatch.setattr(commands.policy_training, "train_stage", lambda *a, **k: None)
    monkeypatch.setattr(commands.run, "execute_sweep", sweep)
    with pytest.raises(_Evaluated):
        main(["sensitivity", "--scenarios", "catchup-v1", "--knobs", "qsgd_levels",
              "--steps", "1800", "--episodes", "2", "--arithmetic", mode,
              "--out", str(tmp_path)])
    assert seen["env"] == arithmetic.process_env(mode)
