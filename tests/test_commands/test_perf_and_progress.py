"""``cacc-bench perf`` reports its keys; progress shows on a terminal and stays quiet otherwise."""

from __future__ import annotations

import io
import json

import pytest
from run_marks import FULL

from benchmark.progress import Progress
from commands.cli import main


def test_perf_json_keys(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["perf", "--quick", "--json", "--only", "env,harness,controllers",
                 "--controllers", "ovm"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["env_vehicle_steps_per_s"] > 0
    # the env with humans, timed beside the homogeneous one (a ratio, not a timing assertion)
    assert out["env_mixed_ratio"] == pytest.approx(
        out["env_mixed_vehicle_steps_per_s"] / out["env_vehicle_steps_per_s"])
    assert out["harness_steps_per_s"] > 0
    assert out["harness_sweep_20_s"] > 0  # 5 controllers x 2 scenarios x 2 seeds (quick)
    assert out["controller_ms_per_vehicle_step"]["ovm"] > 0


def test_perf_takes_run_controller_syntax_and_labels_like_run(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["perf", "--quick", "--json", "--only", "controllers",
                 "--controllers", "cacc:kp=0.3,ovm:alpha=0.5"]) == 0
    timing = json.loads(capsys.readouterr().out)["controller_ms_per_vehicle_step"]
    assert set(timing) == {"cacc[kp=0.3]", "ovm"}  # the default-valued option adds nothing


@FULL
def test_perf_train_key(capsys: pytest.CaptureFixture[str]) -> None:
    """The issue's key: one training rate per requested algorithm, with the runs behind it."""
    assert main(["perf", "--quick", "--json", "--only", "train", "--algos", "ia2c,bdc",
                 "--population", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["train_env_steps_per_s"]) == {"ia2c", "bdc"}
    for algo, rate in out["train_env_steps_per_s"].items():
        assert rate > 0 and out["train_env_steps_per_s_runs"][algo] == [rate]
    assert out["train_population_size"] == 2
    assert set(out["train_population_env_steps_per_s"]) == {"ia2c", "bdc"}
    assert all(r > 0 for r in out["train_population_env_steps_per_s"].values())


def test_perf_bad_part() -> None:
    assert main(["perf", "--only", "nothing"]) == 2


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_on_terminal_only() -> None:
    tty = _Tty()
    p = Progress(4, stream=tty)
    for _ in range(4):
        p.advance()
    p.close()
    lines = [ln for ln in tty.getvalue().replace("\r", "\n").splitlines() if ln.strip()]
    assert "4/4 runs 100%" in lines[-1] and "<00:00" in lines[-1]
    assert max(len(ln) for ln in lines) <= 80
    wide = _Tty()
    w = Progress(12345, "training runs", stream=wide)
    w.advance(5, note="bdc[checkpoint_dir=results/very/long/folder,seed=2] slowdown-v1 s2")
    w.close()
    assert all(len(ln) <= 80 for ln in wide.getvalue().replace("\r", "\n").splitlines())
    log = io.StringIO()
    q = Progress(4, stream=log)
    q.advance()
    q.close()
    assert log.getvalue() == ""


def test_perf_names_what_each_shared_learner_trains(capsys) -> None:
    """``ippo-bdc`` trains a network per follower: its perf line does not call it one shared
    policy."""
    from commands.perf import _print_table

    _print_table({"train_env_steps_per_s": {}, "train_device": "cpu",
                  "train_shared_env_steps_per_s": {"ippo": 7882.0, "ippo-bdc": 5768.0},
                  "train_shared_env_steps_per_s_runs": {"ippo": [7570.0, 7965.0],
                                                        "ippo-bdc": [5659.0, 6027.0]},
                  "train_shared_network_bound_env_steps_per_s": 12894.0})
    lines = capsys.readouterr().out.splitlines()
    assert "one policy shared by the followers" in lines[1] and lines[1].split()[0] == "ippo"
    assert "a network per follower" in lines[2] and "7,882" in lines[1] and "5,768" in lines[2]
    assert lines[3].split()[:2] == ["bound", "12,894"] and "networks alone" in lines[3]


def test_the_network_bound_times_an_update_of_the_given_config() -> None:
    """``marl.perf.shared_network_bound``: environment steps of one update over the median
    time of its networks' work; a tiny config gives a positive finite rate."""
    import math

    from marl.perf import shared_network_bound
    from marl.ppo_nets import PPOConfig

    rate = shared_network_bound(PPOConfig(n_envs=4, rollout_steps=4, minibatch_rows=32,
                                          hidden=8), n_vehicles=2, repeats=1)
    assert math.isfinite(rate) and rate > 0
