"""Mixed-traffic metrics (docs/concepts/metrics.md#mixed-traffic): head-to-tail gain, speed
swings, braking events, the energy of humans and automated vehicles apart, on hand-built
trajectories with numbers worked out by hand, and on one real ring run."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from trajectories import hand_trajectory

from benchmark.export import MIXED_COLUMNS, RUN_COLUMNS, leaderboard_frame, runs_frame
from benchmark.metrics import (
    BRAKING_REARM_MPS2,
    BRAKING_THRESHOLD_MPS2,
    braking_onsets,
    controllable_energy_kwh,
    mixed_traffic_metrics,
    run_metrics,
)
from benchmark.record_schema import RunRecord
from benchmark.rollout import Trajectory, rollout_batch
from envs.energy import battery_power_kw

DT_S = 0.1
ROOT = Path(__file__).resolve().parents[2]


def _traj(speed_mps: np.ndarray, leader_speed_mps: np.ndarray, **kwargs: object) -> Trajectory:
    return hand_trajectory(speed_mps, leader_speed_mps, **kwargs)  # type: ignore[arg-type]


def _sine(rows: int, amplitude_mps: float, period_steps: int = 50, phase: float = 0.0,
          mean_mps: float = 15.0) -> np.ndarray:
    t = np.arange(rows)
    return mean_mps + amplitude_mps * np.sin(2 * np.pi * t / period_steps + phase)


# ------------------------------------------------------------------------ head-to-tail gain
def test_a_tail_swinging_half_as_much_as_the_leader_has_gain_one_half() -> None:
    """Leader 15 + 2 sin, last follower 15 + 1 sin (delayed) over whole periods: the stds are
    2/sqrt(2) and 1/sqrt(2), the gain 0.5; the middle followers do not enter."""
    rows = 1 + 400  # rows 1..400: eight whole periods of 50 steps
    speed = np.stack([_sine(rows, 3.0, phase=0.3), _sine(rows, 1.0, phase=1.1)], axis=1)
    speed[0] = 15.0
    m = run_metrics(_traj(speed, _sine(rows, 2.0)), 20.0, 15.0)
    assert m["head_to_tail_gain"] == pytest.approx(0.5, rel=1e-9)
    assert m["speed_std_last_mps"] == pytest.approx(1.0 / math.sqrt(2.0), rel=1e-9)


def test_on_a_ring_the_head_is_follower_one() -> None:
    """On a ring the first vehicle is follower 1 (there is no leader; the leader array, which
    records follower N, is not the head)."""
    rows = 1 + 400
    speed = np.stack([_sine(rows, 4.0), _sine(rows, 3.0), _sine(rows, 1.0)], axis=1)
    m = mixed_traffic_metrics(_traj(speed, speed[:, -1].copy(), ring=True))
    assert m["head_to_tail_gain"] == pytest.approx(0.25, rel=1e-9)


def test_a_constant_leader_has_no_head_to_tail_gain() -> None:
    rows = 1 + 100
    speed = np.stack([_sine(rows, 1.0)] * 2, axis=1)
    m = mixed_traffic_metrics(_traj(speed, np.full(rows, 15.0)))
    assert math.isnan(m["head_to_tail_gain"])
    assert m["speed_std_last_mps"] == pytest.approx(1.0 / math.sqrt(2.0), rel=1e-9)


def test_the_settle_rows_are_left_out() -> None:
    """The first 100 steps swing hard; after them the tail's sine has amplitude 1: with
    ``settle_steps = 100`` only rows 101..T count."""
    rows = 1 + 100 + 400
    tail = _sine(rows, 1.0)
    tail[:101] = 15.0 + 5.0 * np.cos(np.arange(101))
    speed = np.stack([_sine(rows, 2.0), tail], axis=1)
    lead = _sine(rows, 2.0)
    settled = mixed_traffic_metrics(_traj(speed, lead, settle_steps=100))
    assert settled["speed_std_last_mps"] == pytest.approx(1.0 / math.sqrt(2.0), rel=1e-9)
    assert settled["head_to_tail_gain"] == pytest.approx(0.5, rel=1e-9)
    whole = mixed_traffic_metrics(_traj(speed, lead))
    assert whole["speed_std_last_mps"] > 1.0


# --------------------------------------------------------------------------- braking events
#: Vehicle 0: onsets at rows 2 (-1.5), 5 (-1.1, after -0.2 re-armed it) and 8 (-2.0); -0.6 at
#: row 9 lies in the hysteresis band, so row 10's -1.5 is the same braking. Vehicle 1: one
#: onset at row 3.
ACCEL = np.array([
    [0.0, 0.0], [-0.5, 0.0], [-1.5, -0.9], [-1.2, -1.01], [-0.2, -1.5], [-1.1, -0.4],
    [-1.3, 0.0], [0.0, 0.2], [-2.0, 0.0], [-0.6, 0.0], [-1.5, 0.0], [0.0, 0.0],
])


def test_braking_events_are_onsets_not_steps_below() -> None:
    assert BRAKING_THRESHOLD_MPS2 == 1.0 and BRAKING_REARM_MPS2 == 0.5
    assert braking_onsets(ACCEL).tolist() == [3, 1]
    # without hysteresis every crossing from above counts: row 10 too
    assert braking_onsets(ACCEL, rearm_mps2=0.0).tolist() == [4, 1]
    # a vehicle already braking on the row before the window starts no event at its first row
    assert braking_onsets(np.array([[-1.5], [-1.5], [-0.1], [-1.2]])).tolist() == [1]
    assert braking_onsets(ACCEL[:1]).tolist() == [0, 0]


def test_braking_events_split_by_seat_and_per_vehicle_hour() -> None:
    rows = len(ACCEL)
    speed = np.full((rows, 2), 15.0)
    t = _traj(speed, np.full(rows, 15.0), accel_mps2=ACCEL, automated=np.array([True, False]))
    m = mixed_traffic_metrics(t)
    assert (m["braking_events"], m["braking_events_cavs"], m["braking_events_humans"]) == (4, 3, 1)
    hours = (rows - 1) * DT_S / 3600.0
    assert m["braking_events_per_veh_h"] == pytest.approx(4 / (2 * hours))
    # after a settle of 3 steps (rows 4..11 counted, row 3 the one before): vehicle 0's onsets
    # at rows 5 and 8; vehicle 1 was braking at row 3 and its row 4 is no onset
    late = mixed_traffic_metrics(_traj(speed, np.full(rows, 15.0), accel_mps2=ACCEL,
                                       automated=np.array([True, False]), settle_steps=3))
    assert (late["braking_events_cavs"], late["braking_events_humans"]) == (2, 0)


# ----------------------------------------------------------------------------- energy split
def test_the_energy_split_sums_to_the_platoon_energy() -> None:
    """Without a settle time the two groups' energies (and controllable energies) add up to
    ``energy_kwh`` (``controllable_energy_kwh``)."""
    rows = 1 + 300
    speed = np.stack([_sine(rows, a, phase=0.4 * a) for a in (1.0, 2.0, 0.5, 1.5)], axis=1)
    t = _traj(speed, _sine(rows, 1.0), automated=np.array([True, False, False, True]))
    m = run_metrics(t, 20.0, 15.0)
    per_seat = t.power_kw[1:].sum(axis=0) * DT_S / 3600.0
    assert m["energy_cavs_kwh"] == pytest.approx(per_seat[0] + per_seat[3], rel=1e-12)
    assert m["energy_humans_kwh"] == pytest.approx(per_seat[1] + per_seat[2], rel=1e-12)
    assert m["energy_humans_kwh"] + m["energy_cavs_kwh"] == pytest.approx(m["energy_kwh"],
                                                                          rel=1e-12)
    assert (m["controllable_energy_humans_kwh"] + m["controllable_energy_cavs_kwh"]
            == pytest.approx(controllable_energy_kwh(t), rel=1e-9, abs=1e-12))
    assert m["speed_std_humans_mps"] == pytest.approx((2.0 + 0.5) / 2 / math.sqrt(2.0), rel=1e-6)
    assert m["cav_share"] == 0.5


def test_the_controllable_split_uses_the_window_mean_of_the_leader_array() -> None:
    """Followers cruising exactly at the leader's constant speed after the settle rows cost the
    cruise floor itself: their controllable energy is 0, whatever happened before."""
    rows = 1 + 50 + 200
    speed = np.full((rows, 2), 12.0)
    speed[:51] = 12.0 + np.linspace(3, 0, 51)[:, None]  # slowing to 12 by row 50
    t = _traj(speed, np.full(rows, 12.0), automated=np.array([False, True]), settle_steps=50)
    m = mixed_traffic_metrics(t)
    assert m["controllable_energy_humans_kwh"] == pytest.approx(0.0, abs=1e-12)
    assert m["controllable_energy_cavs_kwh"] == pytest.approx(0.0, abs=1e-12)
    assert m["energy_humans_kwh"] == pytest.approx(
        float(battery_power_kw(12.0, 0.0)) * 200 * DT_S / 3600.0, rel=1e-12)


# -------------------------------------------------------------------------------- NaN rules
def test_empty_groups_sum_to_zero_and_average_to_nan() -> None:
    rows = 1 + 100
    speed = np.stack([_sine(rows, 1.0)] * 3, axis=1)
    homogeneous = mixed_traffic_metrics(_traj(speed, _sine(rows, 2.0)))  # automated None
    assert homogeneous["cav_share"] == 1.0
    assert math.isnan(homogeneous["speed_std_humans_mps"])
    assert homogeneous["energy_humans_kwh"] == 0.0
    assert homogeneous["controllable_energy_humans_kwh"] == 0.0
    assert homogeneous["braking_events_humans"] == 0
    humans = mixed_traffic_metrics(_traj(speed, _sine(rows, 2.0), automated=np.zeros(3, bool)))
    assert humans["cav_share"] == 0.0
    assert humans["energy_cavs_kwh"] == 0.0 and humans["braking_events_cavs"] == 0
    assert math.isfinite(humans["speed_std_humans_mps"])


def test_a_run_that_ends_before_the_settle_time_has_no_window() -> None:
    rows = 1 + 30
    speed = np.stack([_sine(rows, 1.0)] * 2, axis=1)
    m = mixed_traffic_metrics(_traj(speed, _sine(rows, 2.0), automated=np.array([True, False]),
                                    settle_steps=600))
    for col in ("head_to_tail_gain", "speed_std_last_mps", "speed_std_humans_mps",
                "braking_events_per_veh_h"):
        assert math.isnan(m[col]), col
    assert m["braking_events"] == 0 and m["energy_humans_kwh"] == 0.0
    assert m["controllable_energy_cavs_kwh"] == 0.0


# ------------------------------------------------------------------------------ real runs
def test_the_ring_with_one_automated_vehicle_makes_waves() -> None:
    """ring-v1 (21 IDM humans, one ``acc``): after its first minute the last follower's speed
    swings by more than 1 m/s (std), the humans brake, and the rollout tells the metrics which
    seat is automated and how long the settle is."""
    from controllers.registry import make_controller
    from envs.scenarios import as_scenario

    sc = as_scenario("ring-v1")
    for traj in rollout_batch(make_controller("acc"), sc, 22, [2000, 2010]):
        assert traj.ring and traj.settle_steps == 600 and traj.steps > 600
        assert traj.automated is not None and int(traj.automated.sum()) == 1
        m = run_metrics(traj, sc.target_gap_m, sc.target_speed_mps)
        assert m["cav_share"] == pytest.approx(1 / 22)
        assert m["speed_std_last_mps"] >= 1.0
        assert m["speed_std_humans_mps"] >= 1.0
        assert math.isfinite(m["head_to_tail_gain"]) and m["head_to_tail_gain"] > 0
        assert m["braking_events_humans"] > 0
        assert m["braking_events"] == m["braking_events_humans"] + m["braking_events_cavs"]


def test_a_leader_scenario_marks_its_human_seats() -> None:
    from controllers.registry import make_controller
    from envs.scenarios import as_scenario

    mixed = as_scenario("catchup-v1:cav_fraction=0.5")
    (traj,) = rollout_batch(make_controller("acc"), mixed, 8, [2000])
    assert not traj.ring and traj.settle_steps == 0
    assert traj.automated is not None and int(traj.automated.sum()) == 4
    assert run_metrics(traj, 20.0, 15.0)["cav_share"] == 0.5
    (alone,) = rollout_batch(make_controller("acc"), as_scenario("catchup-v1"), 4, [2000])
    assert alone.automated is not None and alone.automated.all()


# -------------------------------------------------------------------- runs.csv, leaderboard
def _record(scenario: str, n: int, seed: int, **metrics: float) -> dict:
    return {"controller": "acc", "name": "acc", "family": "classical", "scenario": scenario,
            "n_vehicles": n, "comm_delay_s": 0.0, "packet_loss": 0.0, "lag_s": 0.0,
            "seed": seed, "status": "ok", "collision": False, "solver_failures": 0,
            "string_stable": True, "deterministic": True, "reward": -1.0, **metrics}


def test_runs_csv_and_the_leaderboard_carry_the_columns() -> None:
    assert set(MIXED_COLUMNS) <= set(RUN_COLUMNS)
    assert set(MIXED_COLUMNS) <= set(RunRecord.model_fields)
    new = _record("ring-v1", 22, 2000, cav_share=1 / 22, speed_std_last_mps=2.0,
                  braking_events_per_veh_h=10.0)
    # a record stored before the columns: cav_share from its label, the rest unknown
    old = _record("catchup-v1[cav_fraction=0.5]", 8, 2000)
    failed = {**_record("catchup-v1[cav_fraction=0.5]", 8, 2010), "status": "failed"}
    runs = runs_frame([new, old, failed])
    by_scenario = runs.set_index(["scenario", "seed"])
    assert by_scenario.loc[("catchup-v1[cav_fraction=0.5]", 2000), "cav_share"] == 0.5
    assert by_scenario.loc[("catchup-v1[cav_fraction=0.5]", 2010), "cav_share"] == 0.5
    assert math.isnan(by_scenario.loc[("catchup-v1[cav_fraction=0.5]", 2000),
                                      "speed_std_last_mps"])
    lb = leaderboard_frame(runs).set_index("scenario")
    assert lb.loc["ring-v1", "cav_share"] == pytest.approx(1 / 22)
    assert lb.loc["ring-v1", "speed_std_last_mps_mean"] == 2.0
    assert lb.loc["catchup-v1[cav_fraction=0.5]", "cav_share"] == 0.5
    assert math.isnan(lb.loc["catchup-v1[cav_fraction=0.5]", "braking_events_per_veh_h_mean"])


def test_the_docs_define_every_column() -> None:
    for doc in ("docs/concepts/metrics.md", "docs/spec/benchmark.md",
                "docs/guide/result-files.md"):
        text = (ROOT / doc).read_text()
        for col in MIXED_COLUMNS:
            assert col in text, (doc, col)
