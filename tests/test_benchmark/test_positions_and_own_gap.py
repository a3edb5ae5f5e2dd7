"""Positions in the run files, the gap against each controller's own spacing policy, and the
jerk without the start-up transient."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmark.export import (
    TRAJECTORY_CSV_COLUMNS,
    positions_m,
    read_trajectory_csv,
    trajectory_arrays,
    write_trajectory_csv,
)
from benchmark.metrics import run_metrics
from benchmark.rollout import rollout
from benchmark.suite import build_sweep, execute_run
from controllers.registry import make_controller
from envs.scenarios import make_scenario
from infra.errors import ConfigError


def test_positions_are_each_vehicles_own_integrated_speed() -> None:
    """Positions from the gaps (what the run files hold) equal each vehicle's own trapezoidal
    integral of its speed: the env moves gaps by the same trapezoid."""
    traj = rollout(make_controller("ovm"), make_scenario("brake-v1"), 5, 2003)
    x = positions_m(trajectory_arrays(traj))
    dt = traj.dt_s
    v = np.column_stack([traj.leader_speed_mps, traj.speed_mps])
    own = np.vstack([np.zeros((1, 6)), np.cumsum((v[1:] + v[:-1]) * dt / 2, axis=0)])
    np.testing.assert_allclose(x - x[0], own, atol=1e-9)
    np.testing.assert_allclose(x[0], -np.concatenate([[0.0], np.cumsum(traj.gap_m[0])]))


def test_the_trajectory_csv_has_positions_and_reads_back(tmp_path: Path) -> None:
    arrays = trajectory_arrays(rollout(make_controller("cacc"), make_scenario("catchup-v1"), 3,
                                       2000))
    path = tmp_path / "t.csv"
    write_trajectory_csv(path, arrays)
    df = pd.read_csv(path)
    assert tuple(df.columns) == TRAJECTORY_CSV_COLUMNS
    x = positions_m(arrays)
    np.testing.assert_allclose(df["position_m"].to_numpy().reshape(-1, 4), x, atol=1e-6)
    back = read_trajectory_csv(path)
    for key in ("gap_m", "speed_mps", "accel_mps2", "power_kw", "leader_speed_mps"):
        np.testing.assert_allclose(back[key], arrays[key], atol=1e-6)
    assert float(back["dt_s"]) == pytest.approx(0.1)
    df.iloc[:-1].to_csv(path, index=False)  # a row short: not a step x vehicle grid
    with pytest.raises(ConfigError, match="not one row per step and vehicle"):
        read_trajectory_csv(path)
    df.drop(columns=["speed_mps"]).to_csv(path, index=False)
    with pytest.raises(ConfigError, match="no column speed_mps"):
        read_trajectory_csv(path)


def test_gap_rmse_against_the_own_policy_and_the_published_target() -> None:
    sc = make_scenario("slowdown-v1")
    rec = execute_run(build_sweep([("cacc", {})], [sc], [4], [2000])[0])
    # Ploeg's law with h = 0.5 s aims at r + h v, r = d* - h v* = 20 - 0.5 * 15 = 12.5 m
    assert rec["spacing_standstill_m"] == 12.5 and rec["spacing_time_gap_s"] == 0.5
    traj = rollout(make_controller("cacc"), sc, 4, 2000)
    gap, v = traj.gap_m[1:], traj.speed_mps[1:]
    own = np.sqrt(np.mean((gap - (12.5 + 0.5 * v)) ** 2))
    published = np.sqrt(np.mean((gap - 20.0) ** 2))
    assert rec["gap_rmse_own_policy_m"] == pytest.approx(own, rel=1e-12)
    assert rec["gap_rmse_m"] == pytest.approx(published, rel=1e-12)
    assert own < published  # it tracks its own policy, not the reward's 20 m
    ovm = execute_run(build_sweep([("ovm", {})], [sc], [4], [2000])[0])
    assert ovm["gap_rmse_own_policy_m"] == ovm["gap_rmse_m"]  # no policy of its own
    assert "spacing_time_gap_s" not in ovm
    safe = execute_run(build_sweep([("safe:cacc", {})], [sc], [4], [2000])[0])
    assert safe["spacing_time_gap_s"] == 0.5  # the filter aims at the wrapped law's gap


def test_jerk_both_ways_on_the_slowdown_start_up_spike() -> None:
    """Issue 56's numbers for cacc on slowdown-v1, seed 2000 (N = 8): 4.11 m/s^3 with the
    published speed clip's step, far less without it."""
    traj = rollout(make_controller("cacc"), make_scenario("slowdown-v1"), 8, 2000)
    m = run_metrics(traj, 20.0, 15.0)
    assert m["jerk_rms_mps3"] == pytest.approx(4.11, abs=0.005)
    a = traj.accel_mps2
    assert a[1].min() < -10.5  # the spike is at step 1
    rows = [(a[t + 1] - a[t]) / 0.1 for t in range(2, traj.steps)]  # from row 2 on
    assert m["jerk_rms_after_start_mps3"] == pytest.approx(np.sqrt(np.mean(np.square(rows))))
    # the numbers docs/guide/plot.md quotes
    plot_md = " ".join(
        (Path(__file__).resolve().parents[2] / "docs" / "guide" / "plot.md").read_text().split())
    quoted = re.search(r"`cacc`, seed 2000, N = 8: (\d+\.\d\d) and (\d+\.\d\d)", plot_md)
    assert quoted is not None
    assert quoted.groups() == (f"{m['jerk_rms_mps3']:.2f}", f"{m['jerk_rms_after_start_mps3']:.2f}")
    assert "about -10.6 m/s^2 at step 1" in plot_md and f"{a[1].min():.1f}" == "-10.6"
    # a run without the spike: both agree to the one left-out jerk row
    calm = run_metrics(rollout(make_controller("cacc"), make_scenario("catchup-v1"), 8, 2000),
                       20.0, 15.0)
    assert calm["jerk_rms_after_start_mps3"] == pytest.approx(calm["jerk_rms_mps3"], rel=0.2)
