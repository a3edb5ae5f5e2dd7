"""Every column of run_metrics on a hand-built trajectory, against numbers worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark.metrics import run_metrics
from benchmark.rollout import Trajectory


def _traj(steps: int = 2) -> Trajectory:
    """T = 2 steps, N = 2 followers, dt = 0.1 s (row 0 is the initial state)."""
    return Trajectory(
        gap_m=np.array([[20.0, 20.0], [21.0, 19.0], [22.0, 18.0]])[: steps + 1],
        speed_mps=np.array([[15.0, 15.0], [15.0, 16.0], [17.0, 14.0]])[: steps + 1],
        accel_mps2=np.array([[0.0, 0.0], [1.0, -1.0], [2.0, 0.0]])[: steps + 1],
        power_kw=np.array([[0.0, 0.0], [10.0, 20.0], [30.0, 40.0]])[: steps + 1],
        leader_speed_mps=np.full(steps + 1, 15.0),
        leader_accel_mps2=np.zeros(steps + 1),
        reward=np.array([-1.0, -3.0])[:steps],
        tracking_reward=np.array([-0.5, -1.5])[:steps],
        command_mps2=np.array([[1.0, -1.0], [2.0, 0.0]])[:steps],
        compute_s=np.array([0.004, 0.002])[:steps],
        collided=False, steps=steps, bits_sent=400, solver_failures=3, dt_s=0.1,
    )


def test_every_metric_by_hand() -> None:
    m = run_metrics(_traj(), target_gap_m=19.0, target_speed_mps=15.0)
    # rows 1..T: gaps 21, 19, 22, 18; speeds 15, 16, 17, 14; accel 1, -1, 2, 0
    assert m["steps"] == 2 and m["collision"] is False
    assert m["min_gap_m"] == 18.0
    assert m["gap_mean_m"] == pytest.approx(20.0)
    assert m["gap_std_m"] == pytest.approx(math.sqrt(2.5))  # deviations 1, -1, 2, -2
    assert m["gap_rmse_m"] == pytest.approx(math.sqrt((4 + 0 + 9 + 1) / 4))
    assert m["speed_mean_mps"] == pytest.approx(15.5)
    assert m["speed_std_mps"] == pytest.approx(math.sqrt((0.25 + 0.25 + 2.25 + 2.25) / 4))
    assert m["speed_rmse_mps"] == pytest.approx(math.sqrt((0 + 1 + 4 + 1) / 4))
    assert m["accel_mean_mps2"] == pytest.approx(0.5)
    assert m["accel_std_mps2"] == pytest.approx(math.sqrt((0.25 + 2.25 + 2.25 + 0.25) / 4))
    assert m["accel_rms_mps2"] == pytest.approx(math.sqrt((1 + 1 + 4 + 0) / 4))
    # jerk: accel differences between steps 1 and 2 only (1, 1) over dt
    assert m["jerk_rms_mps3"] == pytest.approx(10.0)
    # energy: (10 + 20 + 30 + 40) kW x 0.1 s = 10 kJ; platoon power: mean of 30 and 70 kW
    assert m["energy_kwh"] == pytest.approx(10.0 / 3600)
    assert m["power_mean_kw"] == pytest.approx(50.0)
    # per vehicle: 5 kJ over (15 + 16 + 17 + 14) x 0.1 / 2 = 3.1 m
    assert m["energy_kwh_per_100km"] == pytest.approx((5.0 / 3600) / 0.0031 * 100)
    assert m["reward"] == pytest.approx(-2.0)
    assert m["tracking_reward"] == pytest.approx(-1.0)
    # act times 4 ms and 2 ms for the platoon: 2 and 1 ms per vehicle; the first apart
    assert m["compute_ms_first"] == pytest.approx(2.0)
    for q in ("p50", "p95", "p99"):
        assert m[f"compute_ms_{q}"] == pytest.approx(1.0)
    assert m["solver_failures"] == 3
    assert m["comm_bits_per_s"] == pytest.approx(400 / (2 * 2 * 0.1))


def test_string_stability_follows_the_gain_and_its_tolerance() -> None:
    from benchmark.string_gain import STRING_GAIN_TOL

    m = run_metrics(_traj(), 19.0, 15.0)
    assert m["string_stable"] == (m["string_gain"] <= 1.0 + STRING_GAIN_TOL)


def test_a_run_that_ends_at_its_first_step_and_one_with_none() -> None:
    one = run_metrics(_traj(1), 20.0, 15.0)
    assert one["jerk_rms_mps3"] == 0.0  # no second step: no jerk
    assert one["reward"] == -1.0 and one["compute_ms_first"] == pytest.approx(2.0)
    assert math.isnan(one["compute_ms_p50"])  # nothing after the first call
    none = run_metrics(_traj(0), 20.0, 15.0)
    assert none["steps"] == 0 and math.isnan(none["reward"])
    assert math.isnan(none["tracking_reward"]) and math.isnan(none["compute_ms_first"])
    assert none["comm_bits_per_s"] == 0.0 and math.isnan(none["energy_kwh_per_100km"])
    assert none["gap_mean_m"] == 20.0  # the initial state is all there is


def test_a_collision_is_reported() -> None:
    t = _traj()
    t.collided = True
    assert run_metrics(t, 20.0, 15.0)["collision"] is True


def test_string_gains_leave_out_the_first_step_and_use_every_later_one() -> None:
    """Rows 2..T only: a transient at step 1 is ignored, step 2 counts (hand-computed norms)."""
    t = _traj()
    rows = 5  # T = 4
    t.steps = 4
    t.leader_accel_mps2 = np.array([0.0, 9.0, 0.5, 1.0, 1.0])
    t.accel_mps2 = np.array([[0, 0], [50, 50], [2, 1], [2, 1], [2, 1]], dtype=float)
    t.gap_m = 20.0 + np.array([[0, 0], [80, 80], [2, 1], [1, 1], [1, 1]], dtype=float)
    t.speed_mps = np.full((rows, 2), 15.0)
    t.power_kw = np.ones((rows, 2))
    t.reward, t.tracking_reward = np.ones(4), np.ones(4)
    t.command_mps2, t.compute_s = np.zeros((4, 2)), np.ones(4)
    m = run_metrics(t, 20.0, 15.0)
    # follower 1 against the leader: sqrt(4 + 4 + 4) / sqrt(0.25 + 1 + 1); follower 2: 0.5
    assert m["string_gain"] == pytest.approx(math.sqrt(12) / 1.5)
    assert m["string_stable"] is False
    # spacing errors of follower 2 against follower 1: sqrt(3) / sqrt(4 + 1 + 1)
    assert m["spacing_string_gain"] == pytest.approx(math.sqrt(3 / 6))


def _four_steps(leader_accel: list[float], accel: list[list[float]]) -> Trajectory:
    t = _traj()
    t.steps = 4
    t.leader_accel_mps2 = np.array(leader_accel)
    t.accel_mps2 = np.array(accel, dtype=float)
    t.gap_m = np.full((5, 2), 20.0) + np.arange(10.0).reshape(5, 2)
    t.speed_mps = np.full((5, 2), 15.0)
    t.power_kw = np.ones((5, 2))
    t.reward, t.tracking_reward = np.ones(4), np.ones(4)
    t.command_mps2 = np.zeros((4, 2))
    t.compute_s = np.array([0.010, 0.001, 0.002, 0.003])  # per vehicle: 5, 0.5, 1, 1.5 ms
    return t


def test_compute_percentiles_after_the_first_call() -> None:
    m = run_metrics(_four_steps([0, 1, 1, 1, 1], [[0, 0], [1, 1], [1, 1], [1, 1], [1, 1]]),
                    20.0, 15.0)
    # numpy's linear percentiles of 0.5, 1, 1.5 ms
    assert m["compute_ms_p50"] == pytest.approx(1.0)
    assert m["compute_ms_p95"] == pytest.approx(1.45)
    assert m["compute_ms_p99"] == pytest.approx(1.49)
    assert m["compute_ms_first"] == pytest.approx(5.0)


def test_a_gain_of_exactly_one_is_stable_and_an_undefined_gain_is_not() -> None:
    same = run_metrics(_four_steps([0, 1, 1, 1, 1], [[0, 0], [1, 1], [1, 1], [1, 1], [1, 1]]),
                       20.0, 15.0)
    assert same["string_gain"] == pytest.approx(1.0) and same["string_stable"] is True
    still = run_metrics(_four_steps([0, 0, 0, 0, 0], [[0, 0]] * 5), 20.0, 15.0)
    assert math.isnan(still["string_gain"]) and still["string_stable"] is False


def test_a_gain_of_one_and_a_half_is_unstable() -> None:
    m = run_metrics(_four_steps([0, 1, 1, 1, 1], [[0, 0]] + [[1.5, 1.5]] * 4), 20.0, 15.0)
    assert m["string_gain"] == pytest.approx(1.5) and m["string_stable"] is False


def test_a_gain_of_exactly_one_plus_the_tolerance_is_stable() -> None:
    """The tolerance is inclusive: a gain equal to 1 + STRING_GAIN_TOL (1.01, exactly in
    floating point here) counts as string stable."""
    from benchmark.string_gain import STRING_GAIN_TOL

    m = run_metrics(_four_steps([0, 1, 1, 1, 1], [[0, 0]] + [[1.01, 1.01]] * 4), 20.0, 15.0)
    assert m["string_gain"] == 1.0 + STRING_GAIN_TOL  # the premise, to the last bit
    assert m["string_stable"] is True
