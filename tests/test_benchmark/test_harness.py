"""The harness: sweeps, metrics, store, resume after SIGKILL, failures, executors, golden file."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from run_marks import FULL, representative

from analysis.stability import time_domain_string_gain as string_gain
from benchmark.metrics import TIMING_COLUMNS
from benchmark.rollout import rollout
from benchmark.suite import build_sweep, execute_run
from commands.cli import main
from controllers.base import Controller
from controllers.registry import (
    ControllerSpec,
    make_controller,
    parse_controller_list,
    register_controller,
)
from envs.scenarios import make_scenario
from infra.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parents[1] / "golden" / "smoke_runs.csv"
REQUIRED_RUN_COLUMNS = (
    "controller, family, scenario, n_vehicles, seed, status, error, steps, collision, min_gap_m, "
    "gap_mean_m, gap_std_m, gap_rmse_m, speed_mean_mps, speed_std_mps, speed_rmse_mps, "
    "accel_mean_mps2, accel_std_mps2, accel_rms_mps2, jerk_rms_mps3, energy_kwh, power_mean_kw, "
    "energy_kwh_per_100km, reward, tracking_reward, string_gain, string_stable, compute_ms_p50, "
    "compute_ms_p95, compute_ms_p99, compute_ms_first, solver_failures, comm_bits_per_s, "
    "comm_delay_s, packet_loss, lag_s, wall_s, version, git_sha"
).split(", ")
LEADERBOARD_METRICS = (
    "reward, tracking_reward, energy_kwh, power_mean_kw, gap_mean_m, gap_std_m, gap_rmse_m, "
    "speed_mean_mps, speed_std_mps, accel_std_mps2, jerk_rms_mps3, string_gain, compute_ms_p50, "
    "comm_bits_per_s"
).split(", ")


def _no_timing(path: Path) -> pd.DataFrame:
    df = pd.read_csv(path)
    return df.drop(columns=[c for c in df.columns if c in TIMING_COLUMNS or c.startswith("compute_ms")])


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "commands.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)


def test_controller_list_syntax() -> None:
    assert parse_controller_list("mpc:solver=ipopt,horizon=30,cacc") == [
        ("mpc", {"solver": "ipopt", "horizon": "30"}), ("cacc", {})]
    assert parse_controller_list("ovm") == [("ovm", {})]
    with pytest.raises(ConfigError):
        parse_controller_list("horizon=3")


def test_metrics_by_hand() -> None:
    """ovm on catchup-v1: energy = sum P dt, distance, reward = the env's reward."""
    sc = make_scenario("catchup-v1")
    traj = rollout(make_controller("ovm"), sc, 4, 2000)
    rec = execute_run(build_sweep([("ovm", {})], ["catchup-v1"], [4], [2000])[0])
    assert rec["status"] == "ok" and rec["steps"] == 600
    assert rec["energy_kwh"] == pytest.approx(traj.power_kw[1:].sum() * 0.1 / 3600)
    dist_km = traj.speed_mps[1:].sum() * 0.1 / 1000 / 4
    assert rec["energy_kwh_per_100km"] == pytest.approx(rec["energy_kwh"] / 4 / dist_km * 100)
    assert rec["reward"] == pytest.approx(traj.reward.mean())
    assert rec["min_gap_m"] == pytest.approx(traj.gap_m.min())
    assert rec["gap_rmse_m"] == pytest.approx(np.sqrt(np.mean((traj.gap_m[1:] - 20) ** 2)))
    assert rec["comm_bits_per_s"] == 0


def test_string_gain_by_hand() -> None:
    a = np.zeros((10, 3))
    a[:, 0] = 1.0
    a[:, 1] = 2.0
    a[:, 2] = 1.0
    assert string_gain(a) == pytest.approx(2.0)
    a[:, 0] = 0.0  # leader does not move: its pair is skipped
    assert string_gain(a) == pytest.approx(0.5)


def test_run_writes_files_with_contract_columns(tmp_path: Path) -> None:
    out = tmp_path / "r"
    code = main(["run", "--controllers", "ovm", "--scenarios", "catchup-v1,slowdown-v1",
                 "--vehicles", "3", "--episodes", "2", "--out", str(out), "--trajectories"])
    assert code == 0
    runs = pd.read_csv(out / "runs.csv")
    assert set(REQUIRED_RUN_COLUMNS) <= set(runs.columns)
    assert len(runs) == 4 and (runs["status"] == "ok").all()
    lb = pd.read_csv(out / "leaderboard.csv")
    for col in ("controller", "family", "scenario", "n_vehicles", "n_episodes", "collisions",
                "failed", "rank"):
        assert col in lb.columns
    for m in LEADERBOARD_METRICS:
        for suffix in ("mean", "ci_low", "ci_high"):
            assert f"{m}_{suffix}" in lb.columns
    assert (lb["rank"] == 1).all()
    traj = pd.read_csv(out / "trajectories" / "ovm__catchup-v1__n3__s2000.csv")
    assert list(traj.columns) == ["step", "time_s", "vehicle", "gap_m", "speed_mps", "accel_mps2",
                                  "power_kw", "position_m"]
    assert len(traj) == 601 * 4
    assert traj[traj.vehicle == 0]["gap_m"].isna().all()
    assert (traj[traj.step == 0]["accel_mps2"] == 0).all()


def test_rank_puts_collisions_last(tmp_path: Path) -> None:
    from benchmark.export import leaderboard_frame, runs_frame

    recs = []
    for ctrl, reward, coll in (("a", -10.0, True), ("b", -50.0, False), ("c", -20.0, False)):
        recs.append({"controller": ctrl, "name": ctrl, "family": "x", "scenario": "s",
                     "n_vehicles": 2, "seed": 1, "status": "ok", "collision": coll,
                     "reward": reward, "comm_delay_s": 0.0, "packet_loss": 0.0, "lag_s": 0.0,
                     "deterministic": True, "solver_failures": 0, "string_stable": True})
    lb = leaderboard_frame(runs_frame(recs)).set_index("controller")
    assert lb.loc["c", "rank"] == 1 and lb.loc["b", "rank"] == 2 and lb.loc["a", "rank"] == 3


def test_failed_run_is_stored_and_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    register_controller(ControllerSpec("failing", "linear", "none", "test only",
                                       "failing_controller:FailingController"))
    out = tmp_path / "f"
    code = main(["run", "--controllers", "failing,ovm", "--scenarios", "catchup-v1",
                 "--vehicles", "2", "--episodes", "2", "--out", str(out)])
    assert code == 1
    err = capsys.readouterr().err
    assert "2 run(s) failed" in err and "deliberate failure" in err
    runs = pd.read_csv(out / "runs.csv")
    failed = runs[runs.controller == "failing"]
    assert (failed["status"] == "failed").all()
    assert failed["error"].str.contains("deliberate failure at step 5").all()
    assert (runs[runs.controller == "ovm"]["status"] == "ok").all()
    lb = pd.read_csv(out / "leaderboard.csv").set_index("controller")
    assert lb.loc["failing", "failed"] == 2 and lb.loc["failing", "rank"] == 2


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--controllers", "nope"], "valid controllers are"),
        (["--scenarios", "nope-v1"], "valid scenarios are"),
        (["--vehicles", "1"], "followers"),
        (["--comm-delay", "-0.1"], "--comm-delay"),
        (["--packet-loss", "1.5"], "--packet-loss"),
        (["--lag", "-1"], "--lag"),
        (["--episodes", "0"], "--episodes"),
        (["--controllers", "ovm:alpha=abc"], "alpha"),
        (["--controllers", "ovm:gamma=1"], "no option"),
        (["--vehicles", "x"], "--vehicles"),
    ],
)
def test_bad_input_exit_2(tmp_path: Path, args: list[str], needle: str,
                          capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        sys.exit(main(["run", "--out", str(tmp_path / "x"), "--episodes", "1", *args]))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err
    assert "Traceback" not in err
    assert not (tmp_path / "x" / "runs.csv").exists()


def test_existing_results_need_resume(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["run", "--controllers", "ovm", "--scenarios", "catchup-v1", "--vehicles", "2",
            "--episodes", "1", "--out", str(tmp_path)]
    assert main(args) == 0
    assert main(args) == 2
    assert "--resume" in capsys.readouterr().err
    assert main([*args, "--resume"]) == 0
    with sqlite3.connect(tmp_path / "store.sqlite") as conn:
        assert conn.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 1


def test_unknown_command_and_help() -> None:
    assert main(["frobnicate"]) == 2
    assert main(["--help"]) == 0
    assert main(["leaderboard", "/nonexistent/dir"]) == 2


def test_cli_starts_without_heavy_imports() -> None:
    code = ("import sys, commands.cli as c, commands.list as l; l.main([]); "
            "heavy = [m for m in ('torch', 'control', 'cvxpy', 'casadi', 'pandas', 'ray', 'osqp') "
            "if m in sys.modules]; print(heavy)")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "[]"


SWEEP = ["--controllers", "ovm,ovm:alpha=0.4", "--scenarios", "catchup-v1,slowdown-v1",
         "--vehicles", "3", "--episodes", "6"]


def test_sigkill_then_resume_equals_uninterrupted(tmp_path: Path) -> None:
    full = tmp_path / "full"
    assert _cli("run", *SWEEP, "--out", str(full), "--quiet").returncode == 0
    part = tmp_path / "part"
    proc = subprocess.Popen([sys.executable, "-m", "commands.cli", "run", *SWEEP, "--out",
                             str(part), "--quiet"], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    store = part / "store.sqlite"
    deadline = time.monotonic() + 120
    n = 0
    while time.monotonic() < deadline:
        if store.exists():
            try:
                with sqlite3.connect(store, timeout=1) as conn:
                    n = conn.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
            except sqlite3.OperationalError:
                n = 0
            if n >= 3:
                break
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    with sqlite3.connect(store) as conn:
        stored = conn.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
    assert 3 <= stored < 24, "the kill should land mid-sweep"
    res = _cli("run", *SWEEP, "--out", str(part), "--resume", "--quiet")
    assert res.returncode == 0, res.stderr
    assert f"{stored} of 24 runs already stored" in res.stderr
    with sqlite3.connect(store) as conn:
        ids = [r[0] for r in conn.execute("SELECT id FROM runs")]
    assert len(ids) == len(set(ids)) == 24
    for name in ("runs.csv", "leaderboard.csv"):
        pd.testing.assert_frame_equal(_no_timing(part / name), _no_timing(full / name))


@FULL
def test_process_executor_equals_serial(tmp_path: Path) -> None:
    # senders under delay and loss (cacc, a sampled policy whose draws come from the episode
    # seed, not the process) and a controller that sends nothing (ovm)
    small = ["--controllers", "ovm,cacc,bdc:untrained=true", "--scenarios", "catchup-v1,brake-v1", "--vehicles", "3",
             "--episodes", "2", "--quiet", "--comm-delay", "0.1", "--packet-loss", "0.2"]
    assert main(["run", *small, "--out", str(tmp_path / "s")]) == 0
    assert main(["run", *small, "--out", str(tmp_path / "p"), "--executor", "process",
                 "--workers", "2"]) == 0
    assert main(["run", *small, "--out", str(tmp_path / "s2")]) == 0
    for name in ("runs.csv", "leaderboard.csv"):
        ref = _no_timing(tmp_path / "s" / name)
        pd.testing.assert_frame_equal(_no_timing(tmp_path / "p" / name), ref)
        pd.testing.assert_frame_equal(_no_timing(tmp_path / "s2" / name), ref)


@FULL
@pytest.mark.ray
def test_ray_executor_equals_serial(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    small = ["--controllers", "ovm", "--scenarios", "catchup-v1", "--vehicles", "3",
             "--episodes", "3", "--quiet"]
    assert main(["run", *small, "--out", str(tmp_path / "s")]) == 0
    assert main(["run", *small, "--out", str(tmp_path / "r"), "--executor", "ray",
                 "--workers", "2"]) == 0
    for name in ("runs.csv", "leaderboard.csv"):
        pd.testing.assert_frame_equal(_no_timing(tmp_path / "r" / name),
                                      _no_timing(tmp_path / "s" / name))


GOLDEN_ARGS = ["--controllers", "ovm,acc,cacc", "--scenarios", "catchup-v1,slowdown-v1,brake-v1,openacc-s-v1",
               "--vehicles", "4", "--seeds", "2000,2010", "--quiet"]
#: Degraded V2V: every communicating family under delay and loss together (a shipped policy, sampled).
DEGRADED_ARGS = ["--controllers", "cacc,mpc-qp,bdc", "--scenarios", "catchup-v1", "--vehicles", "8",
                 "--seeds", "2000", "--comm-delay", "0.2", "--packet-loss", "0.1", "--quiet"]
GOLDEN_FILES = {"smoke_runs.csv": GOLDEN_ARGS, "degraded_runs.csv": DEGRADED_ARGS}


def golden_frame(args: list[str], out: Path) -> pd.DataFrame:
    """runs.csv of a fixed sweep without timing and provenance (what a golden file holds)."""
    assert main(["run", *args, "--out", str(out)]) == 0
    return _no_timing(out / "runs.csv").drop(columns=["version", "git_sha"])


@pytest.mark.parametrize("name", sorted(GOLDEN_FILES))
def test_golden_runs(tmp_path: Path, name: str) -> None:
    """Fixed sweeps reproduce tests/golden/*.csv. The test only compares; regenerating is a
    deliberate act (``python tests/golden/regenerate.py``) whose diff a reviewer reads."""
    got = golden_frame(GOLDEN_FILES[name], tmp_path)
    want = pd.read_csv(GOLDEN.parent / name)
    pd.testing.assert_frame_equal(got, want, check_exact=False, rtol=1e-8, atol=1e-10)


def test_openacc_real_row_scores_the_recorded_followers(tmp_path: Path) -> None:
    from envs.openacc import load_window

    rec = execute_run(build_sweep([("openacc-real", {})], ["openacc-s-v1"], [4], [0])[0])
    assert rec["status"] == "ok", rec["error"]
    w = load_window("S")
    gaps = w.follower_gap_m[:601, :4]
    assert rec["min_gap_m"] == pytest.approx(gaps.min())
    assert rec["gap_mean_m"] == pytest.approx(gaps[1:].mean())
    v = w.follower_speed_mps[:601, :4]
    a = np.diff(v, axis=0) / 0.1
    # the polynomial is evaluated inside its fit domain, read from the shipped fit (not the code)
    import json

    from envs.energy import DEFAULT_POLYNOMIAL_FILE, load_power_polynomial

    fit = json.loads(DEFAULT_POLYNOMIAL_FILE.read_text())
    lo, hi = fit["grid"]["accel_range_mps2"]
    assert (a.min() < lo or a.max() > hi)  # the recorded data does leave the domain
    p = load_power_polynomial()(v[1:], np.clip(a, lo, hi))
    assert rec["energy_kwh"] == pytest.approx(p.sum() * 0.1 / 3600)


def test_openacc_real_needs_an_openacc_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--controllers", "openacc-real", "--scenarios", "catchup-v1",
                 "--episodes", "1", "--out", "/tmp/never-written"]) == 2
    assert "openacc-s-v1" in capsys.readouterr().err
    assert main(["run", "--controllers", "openacc-real", "--scenarios", "openacc-m-v1",
                 "--vehicles", "5", "--episodes", "1", "--out", "/tmp/never-written"]) == 2


class _RamController(Controller):
    """Follower 1 accelerates at the bound towards the leader, the others follow by OVM: it
    hits the leader after a time set by the seed's initial gap (catchup-v1: 30-50 m)."""

    name = "ram"
    family = "linear"
    deterministic = True
    needs_observation = False

    def reset(self, ctx) -> None:
        self.params = ctx.params

    def act(self, state, observation):
        from envs.dynamics import action_to_command_mps2

        b, n = state.gap_m.shape
        u = action_to_command_mps2(np.full((b, n), 3), state.gap_m, state.speed_mps,
                                   state.pred_speed_mps, self.params)
        u[:, 0] = 2.5
        return u


def test_batched_rollout_equals_separate_with_collisions_at_different_steps() -> None:
    """Episodes of one batch that collide at different steps give, each, exactly the trajectory
    and metrics of the same episode run alone (the ended ones frozen while the others go on)."""
    from benchmark.metrics import run_metrics
    from benchmark.rollout import rollout, rollout_batch
    from envs.scenarios import make_scenario

    sc = make_scenario("catchup-v1")
    seeds = [2000, 2010, 2020, 2030]
    batch = rollout_batch(_RamController(), sc, 3, seeds)
    assert all(t.collided for t in batch)
    assert len({t.steps for t in batch}) >= 3  # collisions at different steps
    for seed, tb in zip(seeds, batch, strict=True):
        alone = rollout(_RamController(), sc, 3, seed)
        assert alone.steps == tb.steps and alone.collided
        for field in ("gap_m", "speed_mps", "accel_mps2", "power_kw", "reward", "tracking_reward"):
            np.testing.assert_array_equal(getattr(tb, field), getattr(alone, field), err_msg=field)
        ma = run_metrics(alone, 20.0, 15.0)
        mb = run_metrics(tb, 20.0, 15.0)
        for key in ("reward", "energy_kwh", "gap_rmse_m", "min_gap_m", "steps", "collision"):
            assert ma[key] == mb[key], key


def _batch_invariant_names() -> list[str]:
    from controllers.registry import available_controllers, make_controller

    names = []
    for spec in available_controllers():
        try:
            ctrl = make_controller(spec.name)
        except Exception:  # noqa: BLE001 - a controller that needs options is not batched here
            continue
        if getattr(ctrl, "batch_invariant", False):
            names.append(spec.name)
    return names


def test_the_batch_invariant_controllers_are_the_cheap_laws() -> None:
    assert _batch_invariant_names() == ["ovm", "duty", "acc", "cacc", "idm", "followerstopper",
                                        "pi-saturation", "ia2c", "fprint", "dial",
                                        "commnet", "wac", "dcea", "bdc", "ippo", "mappo",
                                        "distill", "ippo-bdc", "ippo-gains"]


def _assert_each_record_equals_its_run_alone(keys, batched) -> None:
    """Every batched record equals :func:`execute_run` of its key to the last bit (NaN equal to
    NaN), except the wall and compute times."""
    for key, rec in zip(keys, batched, strict=True):
        alone = execute_run(key)
        for col, value in alone.items():
            if col in TIMING_COLUMNS or col == "wall_s":
                continue
            assert rec[col] == value or (value != value and rec[col] != rec[col]), (key.seed, col)


@pytest.mark.parametrize("name", representative(["ovm", "duty", "acc", "cacc"], {"acc", "cacc"}))
@pytest.mark.parametrize(("scenario", "delay", "loss", "lag"), [
    ("catchup-v1", 0.0, 0.0, 0.0), ("slowdown-v1", 0.2, 0.1, 0.2), ("brake-v1", 0.1, 0.3, 0.0),
])
def test_a_batch_gives_each_run_its_record_alone(name, scenario, delay, loss, lag) -> None:
    """:func:`execute_batch` steps the seeds of a batch-invariant controller together; every
    record equals the run alone to the last bit, except the wall times; acc collides on
    brake-v1 with a 30 % loss in some episodes and not others."""
    from benchmark.suite import execute_batch

    keys = build_sweep([(name, {})], [scenario], [5], [2000, 2010, 2020, 2030, 2040], [delay],
                       [loss], [lag])
    batched = execute_batch(keys)
    _assert_each_record_equals_its_run_alone(keys, batched)


@pytest.mark.parametrize(("name", "options", "scenario", "n", "delay", "loss", "mixed"), [
    ("bdc", {}, "slowdown-v1", 8, 0.0, 0.0, False),
    pytest.param("dial", {"mode": "greedy"}, "catchup-v1", 8, 0.2, 0.1, False, marks=FULL),
    pytest.param("commnet", {}, "catchup-v1", 8, 0.1, 0.3, False, marks=FULL),
    ("fprint", {"untrained": "true"}, "catchup-v1", 4, 0.1, 0.2, True),
    pytest.param("ia2c", {"untrained": "true"}, "slowdown-v1", 8, 0.0, 0.0, True, marks=FULL),
])
def test_a_batch_of_policy_runs_gives_each_run_its_record_alone(
    name, options, scenario, n, delay, loss, mixed
) -> None:
    """Policies are batched too (their network sees at least MIN_LANES rows, so no row's rounding
    depends on the batch): each record equals the run alone to the last bit, sampled and greedy,
    with messages under delay and loss, and where some episodes of the batch collide and others
    do not (``mixed``)."""
    from benchmark.suite import execute_batch

    keys = build_sweep([(name, options)], [scenario], [n], [2000, 2010, 2020, 2030], [delay],
                       [loss])
    batched = execute_batch(keys)
    if mixed:
        assert {r["collision"] for r in batched} == {True, False}
    _assert_each_record_equals_its_run_alone(keys, batched)


def test_the_auto_executor_uses_the_pool_only_for_several_batches_of_heavy_runs() -> None:
    from benchmark.executors import POOL_POLICY_EPISODES, resolve_executor

    cheap = build_sweep([("ovm", {}), ("cacc", {})], ["catchup-v1"], [4], [2000, 2010, 2020])
    mpc = build_sweep([("mpc-qp", {})], ["catchup-v1"], [4], [2000, 2010])
    policy = build_sweep([("bdc", {})], ["catchup-v1", "slowdown-v1"], [8], [2000])
    assert resolve_executor(cheap, "auto", 2) == "serial"  # cheap laws: a pool costs more
    assert resolve_executor(mpc, "auto", 2) == "process"
    assert resolve_executor(mpc[:1], "auto", 2) == "serial"  # one batch: nothing to share
    assert resolve_executor(mpc, "auto", 1) == "serial"
    # policies run batched: a pool pays off only for many episodes
    assert resolve_executor(policy, "auto", 2) == "serial"
    many = build_sweep([("bdc", {}), ("ia2c", {})], ["catchup-v1", "slowdown-v1"], [8],
                       list(range(2000, 2000 + 100)))
    assert len(many) == POOL_POLICY_EPISODES
    assert resolve_executor(many, "auto", 2) == "process"
    assert resolve_executor(many[1:] + cheap, "auto", 2) == "serial"
    for name in ("serial", "process", "ray"):
        assert resolve_executor(mpc, name, 2) == name


def test_a_failing_batch_records_each_run_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    """A batch that raises is run seed by seed, so the failure is stored with its own run."""
    import benchmark.rollout
    from benchmark.suite import execute_batch

    original = benchmark.rollout.rollout_batch

    def broken(controller, scenario, n, seeds, *args):
        if len(seeds) > 1:
            raise RuntimeError("batch broke")
        return original(controller, scenario, n, seeds, *args)

    monkeypatch.setattr(benchmark.rollout, "rollout_batch", broken)
    keys = build_sweep([("cacc", {})], ["catchup-v1"], [3], [2000, 2010])
    recs = execute_batch(keys)
    assert [r["seed"] for r in recs] == [2000, 2010]
    assert all(r["status"] == "ok" for r in recs)  # each alone: not broken
    assert [r["reward"] for r in recs] == [execute_run(k)["reward"] for k in keys]


def test_batches_group_seeds_of_one_setting() -> None:
    from benchmark.suite import MAX_BATCH, batch_keys

    keys = build_sweep([("ovm", {}), ("cacc", {})], ["catchup-v1"], [4],
                       list(range(2000, 2000 + 10 * 120, 10)))
    batches = batch_keys(keys, workers=2)
    assert sorted(k for b in batches for k in b) == sorted(keys)
    assert all(len({(k.controller, k.scenario) for k in b}) == 1 for b in batches)
    assert max(len(b) for b in batches) == MAX_BATCH
    one = build_sweep([("ovm", {})], ["catchup-v1"], [4], [2000, 2010, 2020, 2030])
    assert [len(b) for b in batch_keys(one, workers=2)] == [2, 2]  # every worker gets work
    # a controller that is not batch-invariant runs (and is stored) one run at a time
    mpc = build_sweep([("mpc-qp", {}), ("cmpc", {})], ["catchup-v1"], [4], [2000, 2010, 2020])
    assert [len(b) for b in batch_keys(mpc, workers=1)] == [1] * 6
