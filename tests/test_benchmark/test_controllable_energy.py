"""Controllable energy (docs/controllable-energy.md): the followers' energy above what their
distances cost at steady cruise at the leader's mean speed, per run, in runs.csv, the
leaderboard, the Pareto fronts and the reproduction report."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from trajectories import hand_trajectory

from benchmark.export import LEADERBOARD_METRICS, RUN_COLUMNS, leaderboard_frame, runs_frame
from benchmark.metrics import controllable_energy_kwh, cruise_energy_kwh, run_metrics
from benchmark.rollout import Trajectory
from envs.energy import battery_power_kw

DT_S = 0.1


def _traj(speed_mps: np.ndarray, accel_mps2: np.ndarray, leader_speed_mps: np.ndarray,
          power_kw: np.ndarray | None = None) -> Trajectory:
    """A trajectory of rows 0..T (row 0 the initial state), powers from the shipped model."""
    return hand_trajectory(speed_mps, leader_speed_mps, accel_mps2=accel_mps2, power_kw=power_kw)


# ------------------------------------------------------------------------------ the metric
def test_a_platoon_cruising_at_the_leaders_constant_speed_controls_nothing() -> None:
    """Followers at exactly the leader's constant speed, no acceleration: the energy is the
    cruise floor itself, so the controllable energy is 0 to float precision."""
    rows, n = 601, 8
    t = _traj(np.full((rows, n), 15.0), np.zeros((rows, n)), np.full(rows, 15.0))
    m = run_metrics(t, 20.0, 15.0)
    assert m["energy_kwh"] == pytest.approx(float(battery_power_kw(15.0, 0.0)) * n * 60 / 3600)
    assert abs(m["controllable_energy_kwh"]) < 1e-12 * m["energy_kwh"]
    assert abs(m["controllable_energy_kwh_per_100km"]) < 1e-10


def test_an_accelerating_platoon_controls_a_positive_energy_worked_out_by_hand() -> None:
    """Followers accelerating at 0.5 m/s^2 from 15 m/s behind a leader at 15 m/s: above the
    cruise floor by exactly energy - P(15, 0) * distance / 15, and positive."""
    rows, n = 41, 3
    v = 15.0 + 0.5 * DT_S * np.arange(rows)[:, None] * np.ones((1, n))
    a = np.full((rows, n), 0.5)
    a[0] = 0.0
    t = _traj(v, a, np.full(rows, 15.0))
    energy = float(battery_power_kw(v[1:], a[1:]).sum()) * DT_S / 3600
    distance_m = float(v[1:].sum()) * DT_S
    cruise = float(battery_power_kw(15.0, 0.0)) * distance_m / 15.0 / 3600
    m = run_metrics(t, 20.0, 15.0)
    assert m["controllable_energy_kwh"] == pytest.approx(energy - cruise, rel=1e-12)
    assert m["controllable_energy_kwh"] > 0.0
    per_vehicle_km = distance_m / n / 1000
    assert m["controllable_energy_kwh_per_100km"] == pytest.approx(
        (energy - cruise) / n / per_vehicle_km * 100, rel=1e-12)


def test_the_hand_built_run_of_test_metrics() -> None:
    """T = 2, N = 2, powers 10, 20, 30, 40 kW (given, not from the model), speeds 15, 16, 17,
    14 m/s, leader at 15 m/s: 10 kJ against P(15, 0) x 6.2 m / 15 m/s."""
    t = _traj(np.array([[15.0, 15.0], [15.0, 16.0], [17.0, 14.0]]),
              np.array([[0.0, 0.0], [1.0, -1.0], [2.0, 0.0]]), np.full(3, 15.0),
              np.array([[0.0, 0.0], [10.0, 20.0], [30.0, 40.0]]))
    cruise = float(battery_power_kw(15.0, 0.0)) * 6.2 / 15.0 / 3600
    assert cruise_energy_kwh(t) == pytest.approx(cruise, rel=1e-12)
    m = run_metrics(t, 19.0, 15.0)
    assert m["controllable_energy_kwh"] == pytest.approx(10.0 / 3600 - cruise, rel=1e-12)
    assert m["controllable_energy_kwh_per_100km"] == pytest.approx(
        (10.0 / 3600 - cruise) / 2 / 0.0031 * 100, rel=1e-12)


def test_cruise_is_at_the_leaders_mean_speed_and_can_be_undercut() -> None:
    """The floor uses the leader's mean over rows 1..T (not the target, not row 0); followers
    that coast down from above it, regenerating, spend less than the floor: negative."""
    rows, n = 21, 2
    lead = np.concatenate([[99.0], np.linspace(14.0, 16.0, rows - 1)])  # row 0 is not counted
    v = np.linspace(18.0, 15.0, rows)[:, None] * np.ones((1, n))
    a = np.full((rows, n), -1.5)
    a[0] = 0.0
    t = _traj(v, a, lead)
    v_bar = float(lead[1:].mean())
    assert v_bar == pytest.approx(15.0)
    want = float(battery_power_kw(v_bar, 0.0)) * float(v[1:].sum()) * DT_S / v_bar / 3600
    assert cruise_energy_kwh(t) == pytest.approx(want, rel=1e-12)
    assert controllable_energy_kwh(t) < 0.0


def test_no_step_is_nothing_controlled_and_a_still_leader_is_unknown() -> None:
    none = run_metrics(_traj(np.full((1, 2), 15.0), np.zeros((1, 2)), np.full(1, 15.0)),
                       20.0, 15.0)
    assert none["controllable_energy_kwh"] == 0.0
    assert math.isnan(none["controllable_energy_kwh_per_100km"])
    still = _traj(np.full((5, 2), 1.0), np.zeros((5, 2)), np.zeros(5))
    assert math.isnan(cruise_energy_kwh(still))
    assert math.isnan(run_metrics(still, 20.0, 15.0)["controllable_energy_kwh"])


def test_a_real_run_splits_its_energy_into_cruise_and_controllable() -> None:
    """On a closed-loop run the two per-100-km columns differ by the cruise consumption at the
    leader's mean speed, P(v_bar, 0) / v_bar (the identity the docs state)."""
    from benchmark.rollout import rollout
    from controllers.registry import make_controller
    from envs.scenarios import make_scenario

    sc = make_scenario("catchup-v1")
    t = rollout(make_controller("cacc"), sc, 4, 2000)
    m = run_metrics(t, sc.target_gap_m, sc.target_speed_mps)
    v_bar = float(t.leader_speed_mps[1:].mean())
    floor_per_100km = float(battery_power_kw(v_bar, 0.0)) / v_bar * 1e5 / 3600
    assert m["energy_kwh_per_100km"] - m["controllable_energy_kwh_per_100km"] == pytest.approx(
        floor_per_100km, rel=1e-9)
    assert 0.0 < m["controllable_energy_kwh"] < 0.2 * m["energy_kwh"]


# ------------------------------------------------------------------- runs.csv, leaderboard
def _record(seed: int, controllable: float | None) -> dict:
    rec = {"controller": "c", "name": "c", "family": "linear", "scenario": "catchup-v1",
           "n_vehicles": 4, "comm_delay_s": 0.0, "packet_loss": 0.0, "lag_s": 0.0, "seed": seed,
           "status": "ok", "error": "", "options": "{}", "deterministic": True, "steps": 600,
           "collision": False, "string_stable": True, "solver_failures": 0}
    for m in LEADERBOARD_METRICS:
        rec[m] = 1.0
    del rec["controllable_energy_kwh"], rec["controllable_energy_kwh_per_100km"]
    if controllable is not None:
        rec["controllable_energy_kwh"] = controllable
        rec["controllable_energy_kwh_per_100km"] = 10 * controllable
    return rec


def test_runs_csv_has_the_columns_and_an_old_record_reads_as_unknown_not_zero() -> None:
    assert {"controllable_energy_kwh", "controllable_energy_kwh_per_100km"} <= set(RUN_COLUMNS)
    runs = runs_frame([_record(2000, 0.02), _record(2010, None)])
    assert runs["controllable_energy_kwh"].tolist()[0] == 0.02
    assert math.isnan(runs["controllable_energy_kwh"].tolist()[1])
    assert math.isnan(runs["controllable_energy_kwh_per_100km"].tolist()[1])
    # the safety columns of the same records (absent too) still read as 0: no filter then
    assert runs["safety_interventions"].tolist() == [0.0, 0.0]


def test_an_old_record_without_the_columns_passes_the_store_schema() -> None:
    from benchmark.record_schema import RunRecord

    rec = _record(2000, None)
    rec.update(id="x", version="0", git_sha="0", wall_s=1.0)
    assert RunRecord.model_validate(rec).controllable_energy_kwh is None
    rec["controllable_energy_kwh"] = -0.3  # negative is a value (below the cruise floor)
    assert RunRecord.model_validate(rec).controllable_energy_kwh == -0.3


def test_leaderboard_has_the_mean_and_interval_only_when_every_episode_has_a_value() -> None:
    full = leaderboard_frame(runs_frame([_record(2000, 0.02), _record(2010, 0.04)]))
    assert full["controllable_energy_kwh_mean"].tolist() == [pytest.approx(0.03)]
    assert full["controllable_energy_kwh_ci_low"].iloc[0] == pytest.approx(0.02)
    assert full["controllable_energy_kwh_ci_high"].iloc[0] == pytest.approx(0.04)
    assert full["controllable_energy_kwh_per_100km_mean"].tolist() == [pytest.approx(0.3)]
    part = leaderboard_frame(runs_frame([_record(2000, 0.02), _record(2010, None)]))
    for col in ("controllable_energy_kwh_mean", "controllable_energy_kwh_ci_low",
                "controllable_energy_kwh_per_100km_ci_high"):
        assert math.isnan(part[col].iloc[0])
    assert part["energy_kwh_mean"].iloc[0] == 1.0  # the other columns as before
    # a runs.csv written before the columns existed (no such column at all)
    old = runs_frame([_record(2000, 0.02)]).drop(columns=["controllable_energy_kwh",
                                                          "controllable_energy_kwh_per_100km"])
    lb = leaderboard_frame(old)
    assert math.isnan(lb["controllable_energy_kwh_mean"].iloc[0])
    assert lb["reward_mean"].iloc[0] == 1.0


def test_golden_runs_carry_the_columns() -> None:
    golden = Path(__file__).resolve().parents[1] / "golden"
    runs = pd.read_csv(golden / "smoke_runs.csv")
    assert runs["controllable_energy_kwh"].notna().all()
    lb = pd.read_csv(golden / "smoke_leaderboard.csv")
    assert lb["controllable_energy_kwh_per_100km_mean"].notna().all()


# -------------------------------------------------------------------------------- Pareto
def _pareto_runs() -> pd.DataFrame:
    """Three settings, two episodes each: ``a`` is best on total energy, ``b`` on controllable
    energy (its cruise floor is higher), ``c`` has one episode of unknown controllable energy."""
    rows = []
    for label, total, ctrl, gap in (("a", 10.0, 2.0, 1.0), ("b", 11.0, 1.0, 1.0),
                                    ("c", 9.0, 0.5, 1.0)):
        for k, seed in enumerate((2000, 2010)):
            rows.append({"scenario": "catchup-v1", "controller": label, "seed": seed,
                         "energy_kwh_per_100km": total,
                         "controllable_energy_kwh_per_100km": (math.nan if label == "c" and k
                                                               else ctrl),
                         "gap_rmse_m": gap, "speed_rmse_mps": 0.5, "string_gain": 1.0,
                         "collision": False})
    return pd.DataFrame(rows)


def _settings() -> list[dict]:
    return [{"label": x, "family": x, "controller": x, "knob": "", "knob_value": ""}
            for x in ("a", "b", "c")]


def test_pareto_on_controllable_energy_picks_its_own_front() -> None:
    from analysis.pareto import PARETO_COLUMNS, pareto_columns, pareto_frame

    total = pareto_frame(_pareto_runs(), _settings()).set_index("controller")
    assert list(pareto_frame(_pareto_runs(), _settings()).columns) == list(PARETO_COLUMNS)
    assert total["non_dominated"].to_dict() == {"a": False, "b": False, "c": True}
    ctrl = pareto_frame(_pareto_runs(), _settings(), "controllable")
    assert list(ctrl.columns) == list(pareto_columns("controllable"))
    ctrl = ctrl.set_index("controller")
    assert ctrl.loc["b", "controllable_energy_kwh_per_100km_mean"] == 1.0
    # c's unknown episode: no point, not a mean over the one it has
    assert math.isnan(ctrl.loc["c", "controllable_energy_kwh_per_100km_mean"])
    assert ctrl["non_dominated"].to_dict() == {"a": False, "b": True, "c": False}


def test_pareto_energy_objective_is_checked_and_an_old_runs_csv_has_no_points() -> None:
    from analysis.pareto import pareto_frame
    from infra.errors import UnknownNameError

    with pytest.raises(UnknownNameError, match="controllable"):
        pareto_frame(_pareto_runs(), _settings(), "kinetic")
    old = _pareto_runs().drop(columns=["controllable_energy_kwh_per_100km"])
    df = pareto_frame(old, _settings(), "controllable")
    assert df["controllable_energy_kwh_per_100km_mean"].isna().all()
    assert not df["non_dominated"].any()


def test_the_pareto_command_takes_energy_controllable(tmp_path: Path) -> None:
    from analysis.pareto import pareto_columns
    from commands.cli import main as cli

    out = tmp_path / "p"
    args = ["pareto", "--families", "points", "--episodes", "1", "--vehicles", "2", "--out",
            str(out), "--executor", "serial"]
    assert cli([*args, "--energy", "controllable"]) == 0
    df = pd.read_csv(out / "pareto-controllable.csv")
    assert list(df.columns) == list(pareto_columns("controllable"))
    assert (out / "figures" / "pareto-controllable__catchup-v1__n2.png").stat().st_size > 0
    runs = pd.read_csv(out / "runs" / "runs.csv").set_index("controller")
    got = df.set_index("controller")["controllable_energy_kwh_per_100km_mean"]
    for label in ("ovm", "duty"):
        assert got[label] == pytest.approx(runs.loc[label, "controllable_energy_kwh_per_100km"])
    assert not (out / "pareto.csv").exists()  # the default file is the total-energy front's
    assert cli([*args, "--resume"]) == 0
    assert "energy_kwh_per_100km_mean" in pd.read_csv(out / "pareto.csv").columns


# ------------------------------------------------------------------- the reproduction report
def _claim_runs(ctrl: dict[str, list[float]], power: dict[str, list[float]] | None = None
                ) -> pd.DataFrame:
    """One run per (label, episode) on catchup-v1 at N = 8, 600 steps, no collision."""
    rows = []
    for label, vals in ctrl.items():
        for k, c in enumerate(vals):
            p = (power or {}).get(label, [40.0] * len(vals))[k]
            rows.append({"controller": label, "scenario": "catchup-v1", "seed": 2000 + 10 * k,
                         "n_vehicles": 8, "status": "ok", "collision": False, "steps": 600,
                         "reward": -400.0, "power_mean_kw": p, "energy_kwh": p / 60,
                         "controllable_energy_kwh": c, "gap_mean_m": 20.0, "gap_std_m": 1.0,
                         "speed_mean_mps": 15.0, "speed_std_mps": 0.1, "accel_mean_mps2": 0.0,
                         "accel_std_mps2": 0.1, "energy_kwh_per_100km": 9.0})
    return pd.DataFrame(rows)


def test_ratio_saving_is_of_the_means_with_a_paired_interval() -> None:
    from benchmark.statistics import paired_ci

    def paired_ratio_saving_ci(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
        return paired_ci(a, b, "saving-of-means")

    assert paired_ratio_saving_ci(np.array([[1.0, 1.0]]), np.array([[2.0, 2.0]])) == (
        50.0, 50.0, 50.0)
    # a ratio of means: an episode near 0 on the other side does not dominate
    m, lo, hi = paired_ratio_saving_ci(np.array([[0.01, 0.09]]), np.array([[0.001, 0.199]]))
    assert m == pytest.approx(50.0) and lo <= m <= hi
    assert all(math.isnan(x) for x in paired_ratio_saving_ci(np.array([[1.0]]),
                                                             np.array([[-0.5]])))
    with pytest.raises(ValueError):
        paired_ratio_saving_ci(np.ones((1, 2)), np.ones((1, 3)))


def test_energy_claims_state_the_saving_on_controllable_energy_too() -> None:
    from studies import reproduction as rp

    labels = {"bdc": "bdc", "commnet": "commnet", "ia2c": "ia2c"}
    # total power: BDC 1 % below commnet; controllable: 0.03 against 0.06 kWh = 50 %
    runs = _claim_runs({"bdc": [0.03] * 4, "commnet": [0.06] * 4, "ia2c": [-0.02] * 4},
                       {"bdc": [39.6] * 4, "commnet": [40.0] * 4, "ia2c": [40.0] * 4})
    v = rp.energy_claim(runs, labels, "catchup-v1")
    assert "BDC's saving on total power vs ia2c +1.00 %" in v.measured
    assert "on controllable energy" in v.measured and "vs commnet +50.0 % [+50.0, +50.0]" in v.measured
    # ia2c's controllable energy is negative: no percent, the difference in kWh
    assert "vs ia2c: ia2c's is not positive, no % (bdc minus ia2c +0.0500 kWh" in v.measured
    m = rp.energy_magnitude_claim(runs, labels, "catchup-v1")
    assert "(paper 5.76 %)" in m.measured and "vs commnet +50.0 %" in m.measured
    # runs stored before the measure: said, not guessed
    old = runs.drop(columns=["controllable_energy_kwh"])
    assert "on controllable energy (above steady cruise at the leader's mean speed): not " \
           "measured in these runs" in rp.energy_claim(old, labels, "catchup-v1").measured
    # one episode of BDC unknown: no saving from part of the episodes
    part = runs.copy()
    part.loc[part.index[0], "controllable_energy_kwh"] = np.nan
    assert "vs commnet: not measured on every episode" in rp.energy_claim(
        part, labels, "catchup-v1").measured
    # every run of one episode unknown (the pivot drops that episode): said too
    gone = runs.copy()
    gone.loc[gone["seed"] == 2000, "controllable_energy_kwh"] = np.nan
    assert rp.controllable_saving_text(gone, labels, "catchup-v1", ["commnet"]).endswith(
        "not measured on every episode")


def test_controllable_power_and_table_two() -> None:
    from studies import reproduction as rp

    runs = _claim_runs({"bdc": [0.05, 0.07]})
    assert rp.controllable_power_kw(runs).tolist() == pytest.approx([3.0, 4.2])  # over 60 s
    t2 = rp.table_two(runs, {"bdc": "bdc"}).set_index("name")
    assert t2.loc["bdc", "controllable_power_kw_avg"] == pytest.approx(3.6)
    old = rp.table_two(runs.drop(columns=["controllable_energy_kwh"]), {"bdc": "bdc"})
    assert math.isnan(old["controllable_power_kw_avg"].iloc[0])


def test_power_basis_puts_the_papers_table_two_beside_ours() -> None:
    """Per vehicle (over N = 8) and relative to each model's cruise power: ours P(15, 0) from
    the power model, the paper's CommNet row (its closest to steady cruise)."""
    from studies import reproduction as rp
    from studies.paper import TABLE_II

    runs = _claim_runs({"bdc": [0.05] * 3, "commnet": [0.10] * 3, "cacc": [0.04] * 3},
                       {"bdc": [40.0] * 3, "commnet": [42.0] * 3, "cacc": [39.0] * 3})
    t2 = rp.table_two(runs, {"bdc": "bdc", "commnet": "commnet", "cacc": "cacc"})
    basis = rp.power_basis_table(t2, "catchup-v1", 8, 15.0).set_index("name")
    cruise = float(battery_power_kw(15.0, 0.0))
    assert basis["cruise_per_vehicle_kw"].tolist() == pytest.approx([cruise] * 3)
    paper_bdc, paper_commnet = TABLE_II["bdc"]["power_kw"][0], TABLE_II["commnet"]["power_kw"][0]
    bdc, commnet = basis.loc["bdc"], basis.loc["commnet"]
    assert bdc["paper_per_vehicle_kw"] == pytest.approx(paper_bdc / 8)
    assert bdc["paper_vs_cruise_pct"] == pytest.approx(100 * (paper_bdc / paper_commnet - 1))
    assert commnet["paper_vs_cruise_pct"] == 0.0
    assert commnet["paper_saving_pct"] == pytest.approx(
        100 * (paper_commnet - paper_bdc) / paper_commnet)  # the paper's 5.8 %
    assert bdc["per_vehicle_kw"] == pytest.approx(5.0)
    assert bdc["vs_cruise_pct"] == pytest.approx(100 * (5.0 / cruise - 1))
    assert commnet["saving_pct"] == pytest.approx(100 * 2 / 42)
    # controllable: 0.05 and 0.10 kWh over 60 s = 3 and 6 kW platoon, BDC saves 50 %
    assert bdc["controllable_per_vehicle_kw"] == pytest.approx(3.0 / 8)
    assert commnet["controllable_saving_pct"] == pytest.approx(50.0)
    assert basis.loc["cacc", "controllable_saving_pct"] == pytest.approx(100 * (2.4 - 3) / 2.4)
    assert math.isnan(basis.loc["cacc", "paper_power_kw"])  # not in the paper's table
