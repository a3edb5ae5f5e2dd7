"""``cacc-bench pareto``: the non-dominated set, the knobs' directions, determinism."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from run_marks import FULL

from analysis.pareto import PARETO_COLUMNS, non_dominated
from commands.cli import main as cli


def test_non_dominated_on_a_hand_made_set() -> None:
    pts = np.array([
        [1.0, 5.0],   # front
        [2.0, 3.0],   # front
        [3.0, 3.0],   # dominated by [2, 3] (equal in one, worse in the other)
        [4.0, 1.0],   # front
        [4.0, 4.0],   # dominated
        [0.5, 0.5],   # best of all, but not eligible (collided): dominates nothing
        [np.nan, 0.0],  # NaN: never marked
        [2.0, 3.0],   # a tie with a front point: neither dominates the other
    ])
    eligible = np.array([True, True, True, True, True, False, True, True])
    assert non_dominated(pts, eligible).tolist() == [True, True, False, True, False, False, False,
                                                    True]
    assert non_dominated(pts[:5]).tolist() == [True, True, False, True, False]


def _energy_and_gap(tmp_path: Path, controllers: str) -> pd.DataFrame:
    out = tmp_path / "r"
    assert cli(["run", "--controllers", controllers, "--scenarios", "catchup-v1", "--vehicles", "2",
                "--episodes", "1", "--out", str(out), "--quiet"]) == 0
    return pd.read_csv(out / "runs.csv").set_index("controller")


def test_more_energy_weight_spends_less_energy_in_mpc(tmp_path: Path) -> None:
    runs = _energy_and_gap(tmp_path, "mpc:energy_weight=0,mpc:energy_weight=2")
    e0 = runs.loc["mpc[energy_weight=0]", "energy_kwh_per_100km"]
    e2 = runs.loc["mpc[energy_weight=2]", "energy_kwh_per_100km"]
    assert e2 < e0 - 0.1


def test_input_weight_and_time_gap_trade_energy_for_spacing(tmp_path: Path) -> None:
    runs = _energy_and_gap(tmp_path, "mpc-qp:w_accel=0.01,mpc-qp:w_accel=3,"
                                     "cacc:time_gap_s=0.3,cacc:time_gap_s=1.2")
    lo, hi = runs.loc["mpc-qp[w_accel=0.01]"], runs.loc["mpc-qp[w_accel=3]"]
    assert hi["energy_kwh_per_100km"] < lo["energy_kwh_per_100km"]
    assert hi["gap_rmse_m"] > lo["gap_rmse_m"]
    short, long_ = runs.loc["cacc[time_gap_s=0.3]"], runs.loc["cacc[time_gap_s=1.2]"]
    assert long_["energy_kwh_per_100km"] < short["energy_kwh_per_100km"]
    assert long_["gap_rmse_m"] > short["gap_rmse_m"]


def _pareto(out: Path, executor: str) -> pd.DataFrame:
    assert cli(["pareto", "--families", "cacc,points", "--episodes", "2", "--vehicles", "2",
                "--out", str(out), "--executor", executor, "--workers", "2"]) == 0
    return pd.read_csv(out / "pareto.csv")


@FULL
def test_pareto_csv_is_identical_across_executors_and_reruns(tmp_path: Path) -> None:
    serial = _pareto(tmp_path / "a", "serial")
    assert list(serial.columns) == list(PARETO_COLUMNS)
    assert set(serial["family"]) == {"cacc (time gap)", "cacc (gain kp)", "ovm", "duty"}
    assert (serial["n_episodes"] == 2).all() and serial["non_dominated"].any()
    assert (tmp_path / "a" / "figures" / "pareto__catchup-v1__n2.png").stat().st_size > 0
    pd.testing.assert_frame_equal(_pareto(tmp_path / "b", "process"), serial)
    pd.testing.assert_frame_equal(_pareto(tmp_path / "c", "serial"), serial)


def test_pareto_counts_a_default_shared_by_two_sweeps_once(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 53: "7 settings x 1 scenarios x 1 episodes = 6 runs" (cacc's default lies in the
    time-gap and the gain sweep): the count says what runs."""
    assert cli(["pareto", "--families", "cacc", "--episodes", "1", "--vehicles", "2",
                "--out", str(tmp_path / "p"), "--executor", "serial"]) == 0
    assert ("pareto: 6 controllers (7 sweep points: a default lies in two sweeps) x 1 scenarios "
            "x 1 episodes = 6 runs") in capsys.readouterr().err


def test_pareto_bad_family_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(["pareto", "--families", "mpc,nope"]) == 2
    assert "nope" in capsys.readouterr().err


def test_marl_sweep_uses_the_shipped_w5_variants(tmp_path: Path, monkeypatch) -> None:
    import controllers.policy as policy
    from commands.pareto import settings_for, w5_variant

    assert [w5_variant(w) for w in (0.0, -1.0, -20.0, 2.5)] == ["w5_0", "w5_m1", "w5_m20",
                                                                 "w5_2.5"]
    monkeypatch.setattr(policy, "VARIANT_DIR", tmp_path)
    (tmp_path / "w5_m1").mkdir()
    (tmp_path / "w5_m1" / "bdc__catchup-v1__n8__s0.pt").write_bytes(b"")
    settings = settings_for(["marl"], ["catchup-v1"], 8)
    bdc = [s for s in settings if s["family"] == "marl bdc (power weight w5)"]
    assert [(s["label"], s["knob_value"]) for s in bdc] == [("bdc[variant=w5_m1]", -1.0),
                                                             ("bdc", -10.0)]
    # a variant missing on one scenario is left out rather than failing the sweep
    assert [s["label"] for s in settings_for(["marl"], ["catchup-v1", "slowdown-v1"], 8)
            if s["controller"] == "bdc"] == ["bdc"]
    assert {s["family"] for s in settings} >= {"marl wac", "marl ia2c (power weight w5)"}


def test_the_marl_family_shows_the_shared_learners_and_the_ippo_variants() -> None:
    """Every shipped shared-policy learner is a point, and so is each shipped ``ippo`` variant
    (the time-aware residual among them), on both published scenarios."""
    from commands.pareto import settings_for
    from controllers.policy import IPPO_VARIANTS
    from marl.learners import SHARED_LEARNERS

    labels = [s["label"] for s in settings_for(["marl"], ["catchup-v1", "slowdown-v1"], 8)]
    assert set(SHARED_LEARNERS) <= set(labels)
    assert [f"ippo[variant={v}]" for v in IPPO_VARIANTS] == [
        x for x in labels if x.startswith("ippo[variant=")]


def test_the_committed_reading_of_the_shared_learners_is_its_csv() -> None:
    """The reading in ``docs/pareto/README.md`` quotes the committed ``pareto.csv``: the front's
    size, and each shared learner's energy and spacing, the residuals on the front."""
    docs = Path(__file__).resolve().parents[2] / "docs" / "pareto"
    text = " ".join((docs / "README.md").read_text().split())
    front = pd.read_csv(docs / "pareto.csv")
    assert f"({int(front['non_dominated'].sum())} points, none collided)" in text
    assert front["collisions"].sum() == 0
    row = front.set_index("controller")
    for label in ("ippo", "mappo", "ippo-bdc", "distill", "ippo[variant=residual-cacc]",
                  "ippo[variant=residual-timed]", "ippo[variant=ovm-gain]"):
        energy, gap = row.loc[label, ["energy_kwh_per_100km_mean", "gap_rmse_m_mean"]]
        assert f"{energy:.2f}" in text and f"{gap:.2f} m" in text, label
        on_front = bool(row.loc[label, "non_dominated"])
        assert on_front == label.startswith("ippo[variant=residual"), label
