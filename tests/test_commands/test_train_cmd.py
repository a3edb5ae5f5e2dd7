"""Several training seeds through the harness executors give the same results as one by one."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import torch
from run_marks import FULL

from commands.cli import main


def _tensors(obj: object, prefix: str = "") -> dict[str, torch.Tensor]:
    """All tensors of a (nested) checkpoint, by path (metadata such as timings left out)."""
    out: dict[str, torch.Tensor] = {}
    if isinstance(obj, torch.Tensor):
        out[prefix] = obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            out.update(_tensors(v, f"{prefix}/{k}"))
    elif isinstance(obj, list | tuple):
        for i, v in enumerate(obj):
            out.update(_tensors(v, f"{prefix}/{i}"))
    return out


@FULL
def test_seeds_on_process_executor_equal_serial(tmp_path: Path) -> None:
    common = ["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--vehicles", "3",
              "--steps", "1500"]
    assert main([*common, "--seeds", "0,1", "--executor", "process", "--workers", "2",
                 "--out", str(tmp_path / "p")]) == 0
    assert main([*common, "--seed", "1", "--out", str(tmp_path / "s")]) == 0
    stem = "ia2c__catchup-v1__n3__s1"
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "p" / f"{stem}.curve.csv"),
                                  pd.read_csv(tmp_path / "s" / f"{stem}.curve.csv"))
    a = torch.load(tmp_path / "p" / f"{stem}.pt", weights_only=True)
    b = torch.load(tmp_path / "s" / f"{stem}.pt", weights_only=True)
    wa, wb = _tensors(a), _tensors(b)
    assert wa.keys() == wb.keys() and wa
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    assert (tmp_path / "p" / "ia2c__catchup-v1__n3__s0.pt").exists()


def test_bad_seeds_exit_2(tmp_path: Path) -> None:
    assert main(["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--seeds", "a,b",
                 "--out", str(tmp_path)]) == 2
    assert main(["train", "--algo", "nope", "--scenario", "catchup-v1",
                 "--out", str(tmp_path)]) == 2


def test_set_config_fields(tmp_path: Path, capsys) -> None:
    """``--set KEY=VALUE`` reaches the checkpoint's config, typed; bad pairs exit 2 with a
    message naming the key, before anything is trained."""
    assert main(["train", "--algo", "bdc", "--scenario", "catchup-v1", "--vehicles", "3",
                 "--steps", "700", "--out", str(tmp_path), "--set", "gamma=0.995",
                 "--set", "advantage_norm=true", "--set", "qsgd_bucket=none"]) == 0
    cfg = torch.load(tmp_path / "bdc__catchup-v1__n3__s0.pt", weights_only=True)["config"]
    assert cfg["gamma"] == 0.995 and cfg["advantage_norm"] is True and cfg["qsgd_bucket"] is None
    capsys.readouterr()
    for bad in ("nope=1", "gamma", "gamma=high", "advantage_norm=maybe", "gamma=2"):
        assert main(["train", "--algo", "bdc", "--scenario", "catchup-v1", "--set", bad,
                     "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert bad.split("=")[0] in err and "Traceback" not in err, bad
    assert not (tmp_path / "bad").exists()


def test_train_lists_and_resume(tmp_path: Path, capsys) -> None:
    """Comma lists of algorithms and scenarios make one run each; --resume skips finished runs
    and refuses a finished run of another config."""
    common = ["train", "--algo", "ia2c,wac", "--scenario", "catchup-v1,slowdown-v1",
              "--vehicles", "3", "--steps", "300", "--episodes-parallel", "2",
              "--out", str(tmp_path)]
    assert main(common) == 0
    finals = sorted(p.name for p in tmp_path.glob("*.final.pt"))
    assert len(finals) == 4
    stamp = {p: p.stat().st_mtime_ns for p in tmp_path.glob("*.final.pt")}
    capsys.readouterr()
    assert main([*common, "--resume"]) == 0
    assert "4 of 4 runs already finished" in capsys.readouterr().err
    assert stamp == {p: p.stat().st_mtime_ns for p in tmp_path.glob("*.final.pt")}
    assert main([*common, "--resume", "--set", "gamma=0.9"]) == 2
    assert "another config" in capsys.readouterr().err


def test_tuned_options(tmp_path: Path, capsys) -> None:
    import json

    from marl.config import TUNED_CONFIGS, tuned_options

    path = tmp_path / "tuned.json"
    path.write_text(json.dumps({"configs": {"bdc/catchup-v1": {
        "config": {"lr_scale": 2.0, "power_baseline_kw": None, "consensus_eps": 0.003}}}}))
    assert tuned_options("bdc", "catchup-v1", path) == {
        "lr_scale": 2.0, "power_baseline_kw": None, "consensus_eps": 0.003}
    import pytest

    from infra.errors import ConfigError

    with pytest.raises(ConfigError, match="no tuned config for ia2c"):
        tuned_options("ia2c", "catchup-v1", path)
    with pytest.raises(ConfigError, match="missing"):
        tuned_options("ia2c", "catchup-v1", tmp_path / "none.json")
    # every shipped entry builds a valid config of its algorithm; BDC is tuned on both
    shipped = json.loads(TUNED_CONFIGS.read_text())
    assert shipped["budget"] == {"trials": 8, "steps_per_trial": 200_000, "seed": 0, "vehicles": 8}
    assert {"bdc/catchup-v1", "bdc/slowdown-v1"} <= set(shipped["configs"])
    from marl.training import learner_config

    for key in shipped["configs"]:
        a, sc = key.split("/")
        learner_config(a, tuned_options(a, sc), key)


def test_tune_tiny_study_resumes(tmp_path: Path, capsys) -> None:
    """Two trials per study; the first is the default config; a rerun is refused, with
    --resume it adds nothing; the best configs file names every study; bad input exits 2."""
    import json

    args = ["tune", "--algos", "ia2c,dcea", "--scenarios", "catchup-v1", "--trials", "2",
            "--steps", "600", "--vehicles", "3", "--out", str(tmp_path)]
    assert main(args) == 0
    trials = pd.read_csv(tmp_path / "trials.csv")
    assert len(trials) == 4
    first = trials[trials["trial"] == 0]
    assert (first["lr_scale"] == 4.0).all() and (first["power_baseline"] == "paper").all()
    assert first[first["algo"] == "dcea"]["consensus_eps"].iloc[0] == 0.001
    best = json.loads((tmp_path / "tuned_configs.json").read_text())
    assert set(best["configs"]) == {"ia2c/catchup-v1", "dcea/catchup-v1"}
    assert best["budget"] == {"trials": 2, "steps_per_trial": 600, "seed": 0, "vehicles": 3}
    capsys.readouterr()
    assert main(args) == 2
    assert "add --resume to complete that command" in capsys.readouterr().err
    assert main([*args, "--resume"]) == 0
    assert pd.read_csv(tmp_path / "trials.csv").equals(trials)
    capsys.readouterr()
    assert main([*args[:-2], "--steps", "700", "--out", str(tmp_path), "--resume"]) == 2
    assert "--overwrite to tune it again" in capsys.readouterr().err
    assert main(["tune", "--algos", "nope"]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_tune_the_shared_learners_with_a_fixed_field(tmp_path: Path, capsys) -> None:
    """``ippo``/``mappo`` get the same budget over their own knobs; ``--set`` fixes a field in
    every trial and is recorded; the first trial is the default config."""
    import json

    args = ["tune", "--algos", "ippo", "--scenarios", "catchup-v1", "--trials", "2",
            "--steps", "2048", "--vehicles", "2", "--set", "prior=cacc", "--set", "rollout_steps=8",
            "--out", str(tmp_path)]
    assert main(args) == 0
    trials = pd.read_csv(tmp_path / "trials.csv")
    assert len(trials) == 2 and (trials["config.prior"] == "cacc").all()
    first = trials[trials["trial"] == 0].iloc[0]
    assert (first["lr"], first["n_envs"], first["gamma"]) == (0.001, 64, 0.99)
    best = json.loads((tmp_path / "tuned_configs.json").read_text())
    assert best["budget"]["fixed"] == {"prior": "cacc", "rollout_steps": "8"}
    assert best["configs"]["ippo/catchup-v1"]["config"]["prior"] == "cacc"
    capsys.readouterr()
    assert main([*args[:-4], "--out", str(tmp_path), "--resume"]) == 2  # without the field
    assert main(["tune", "--algos", "bdc", "--set", "prior=cacc", "--out", str(tmp_path / "b")]) == 2
    assert main(["tune", "--algos", "ippo", "--set", "nope=1", "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    from commands.tune import SHARED_TUNED

    assert "Traceback" not in err and f"--set fixes a field of {'/'.join(SHARED_TUNED)} only" in err


@FULL
def test_a_population_of_seeds_equals_separate_processes(tmp_path: Path, capsys) -> None:
    """``--seeds 0,1,2`` (serial: one population of three in one process) gives each seed the
    checkpoint and curve it gets trained alone (``--population 1``, process executor)."""
    common = ["train", "--algo", "fprint", "--scenario", "catchup-v1", "--vehicles", "3",
              "--steps", "900", "--episodes-parallel", "2"]
    assert main([*common, "--seeds", "0,1,2", "--out", str(tmp_path / "pop")]) == 0
    assert "(population of 3)" in capsys.readouterr().out
    assert main([*common, "--seeds", "0,2", "--population", "1", "--executor", "process",
                 "--workers", "2", "--out", str(tmp_path / "one")]) == 0
    assert "population of" not in capsys.readouterr().out
    for seed in (0, 2):
        stem = f"fprint__catchup-v1__n3__s{seed}"
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "pop" / f"{stem}.curve.csv"),
                                      pd.read_csv(tmp_path / "one" / f"{stem}.curve.csv"))
        for suffix in (".pt", ".final.pt"):
            a = _tensors(torch.load(tmp_path / "pop" / f"{stem}{suffix}", weights_only=True))
            b = _tensors(torch.load(tmp_path / "one" / f"{stem}{suffix}", weights_only=True))
            assert a.keys() == b.keys() and a
            for k in a:
                assert torch.equal(a[k], b[k]), (seed, suffix, k)
        assert "in a population of 3" in (tmp_path / "pop" / f"{stem}.log").read_text()
    assert main([*common, "--seeds", "0,1", "--population", "0", "--out", str(tmp_path)]) == 2


def test_populations_group_by_everything_but_the_seed() -> None:
    """Keys that differ only in their seed train together (up to the size asked); a
    shared-policy learner's runs each alone; a key pickles for the executors."""
    import pickle

    from commands.train import populations
    from envs.scenarios import make_scenario
    from marl.training import TrainingKey, learner_config

    sc = make_scenario("catchup-v1")

    def key(algo: str, seed: int) -> TrainingKey:
        return TrainingKey(algo, sc, 8, (seed,), 100, learner_config(algo, {}), Path("x"))

    keys = [key("ia2c", s) for s in range(5)] + [key("bdc", 0), key("ippo", 0), key("ippo", 1)]
    serial = populations(keys, None, "serial", 2)
    assert [(k.algo, k.seeds) for k in serial] == [
        ("ia2c", (0, 1, 2, 3, 4)), ("bdc", (0,)), ("ippo", (0,)), ("ippo", (1,))]
    split = populations(keys, None, "process", 2)
    assert [(k.algo, k.seeds) for k in split][:3] == [
        ("ia2c", (0, 1, 2)), ("ia2c", (3, 4)), ("bdc", (0,))]
    ones = populations(keys, 1, "serial", 2)
    assert [k.seeds for k in ones][:6] == [(0,), (1,), (2,), (3,), (4,), (0,)]
    assert pickle.loads(pickle.dumps(serial[0])) == serial[0]


def test_a_shared_learner_trains_through_the_executors_as_a_population_of_one(
        tmp_path: Path, capsys) -> None:
    """``ippo`` on the process executor gives the checkpoint and curve of the serial run; its
    curve has every learner's columns (sampled validation only); --resume skips it."""
    from marl.checkpoint import CURVE_COLUMNS

    common = ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--vehicles", "2",
              "--steps", "64", "--set", "rollout_steps=8", "--episodes-parallel", "4",
              "--set", "eval_every_steps=32"]
    assert main([*common, "--out", str(tmp_path / "s")]) == 0
    assert main([*common, "--executor", "process", "--workers", "1",
                 "--out", str(tmp_path / "p")]) == 0
    stem = "ippo__catchup-v1__n2__s0"
    curve = pd.read_csv(tmp_path / "s" / f"{stem}.curve.csv")
    assert tuple(curve.columns) == CURVE_COLUMNS and len(curve) == 3
    assert curve["eval_reward_sampled"].notna().all() and curve["episode"].isna().all()
    pd.testing.assert_frame_equal(curve, pd.read_csv(tmp_path / "p" / f"{stem}.curve.csv"))
    a, b = (_tensors(torch.load(tmp_path / d / f"{stem}.pt", weights_only=True)) for d in "sp")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert "done:" in (tmp_path / "s" / f"{stem}.log").read_text()
    capsys.readouterr()
    assert main([*common, "--out", str(tmp_path / "s"), "--resume"]) == 0
    assert "1 of 1 runs already finished" in capsys.readouterr().err


@FULL
@pytest.mark.ray
def test_populations_on_ray_equal_serial(tmp_path: Path, capsys) -> None:
    """Two Ray tasks (one run each, split over the workers) give the checkpoints of the serial
    population of both seeds."""
    pytest.importorskip("ray")
    common = ["train", "--algo", "dcea", "--scenario", "catchup-v1", "--vehicles", "3",
              "--steps", "700", "--episodes-parallel", "2", "--seeds", "3,4"]
    assert main([*common, "--out", str(tmp_path / "serial")]) == 0
    assert main([*common, "--executor", "ray", "--workers", "2", "--out", str(tmp_path / "ray")]) == 0
    for seed in (3, 4):
        for suffix in (".pt", ".final.pt"):
            name = f"dcea__catchup-v1__n3__s{seed}{suffix}"
            a = _tensors(torch.load(tmp_path / "serial" / name, weights_only=True))
            b = _tensors(torch.load(tmp_path / "ray" / name, weights_only=True))
            assert a.keys() == b.keys() and a
            for k in a:
                assert torch.equal(a[k], b[k]), (name, k)
