"""The committed SUMO report (docs/sumo, ``cacc-bench sumo-compare``): its tables hold the
stated tolerances, and its numbers are what the study computes (recomputed in small form by
default, in full with ``-m full``). Skipped without the sumo extra."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.run_marks import FULL

pytest.importorskip("libsumo", reason="the SUMO report needs the sumo extra: "
                                      "pip install -e '.[sumo]'")

from studies import sumo_compare as sc  # noqa: E402

REPORT = Path(__file__).resolve().parents[2] / "docs" / "sumo"
SEEDS = [2000, 2010, 2020]  # the report's: --episodes 3


def _csv(name: str) -> pd.DataFrame:
    return pd.read_csv(REPORT / f"{name}.csv")


def test_the_committed_tables_hold_the_stated_tolerances() -> None:
    agree = _csv("agreement")
    matched = agree[agree["simulator"] == "sumo"]
    assert set(matched["controller"]) == set(sc.AGREEMENT_CONTROLLERS)
    laws = matched[matched["controller"] != "mpc-qp"]
    assert (laws["max_gap_diff_m"] < sc.MATCHED_GAP_TOL_M).all()
    assert (laws["max_speed_diff_mps"] < sc.MATCHED_SPEED_TOL_MPS).all()
    mpc = matched[matched["controller"] == "mpc-qp"]
    assert (mpc[["max_gap_diff_m", "max_speed_diff_mps"]] < sc.MATCHED_MPC_TOL).all().all()
    assert (agree[agree["simulator"] == "sumo-euler"]["max_gap_diff_m"] > 1e-3).all()
    ploeg = _csv("ploeg")
    replica = ploeg[ploeg["ours"].str.contains("Euler")]
    unbounded = replica[replica["speed_bound_mps"] == sc.UNBOUNDED_SPEED_MPS]
    assert (unbounded["max_gap_diff_m"] < sc.PLOEG_REPLICA_TOL).all()
    energy = _csv("energy")
    assert set(energy["scenario"]) == set(sc.ENERGY_SCENARIOS)
    assert (energy["poly_vs_mmpevem_pct_of_throughput"].abs() < sc.ENERGY_TOL_PCT).all()
    humans = _csv("humans")
    assert (humans["max_gap_diff_m"] < sc.HUMAN_TOL).all()
    ring = humans[humans["scenario"] == sc.RING].iloc[0]
    for key in ("amplitude_mps", "speed_std_mps", "wave_speed_mps"):
        assert ring[f"{key}_builtin"] == pytest.approx(ring[f"{key}_sumo"], rel=1e-3)
    families = _csv("families")
    assert set(families["family"]) >= {"human", "linear", "mpc", "marl"}
    both = families.dropna(subset=["reward_builtin", "reward_sumo"])
    np.testing.assert_allclose(both["reward_builtin"], both["reward_sumo"], rtol=1e-6)
    report = (REPORT / "report.md").read_text()
    assert "cacc-bench sumo-compare --out docs/sumo --episodes 3" in report


def test_the_energy_row_of_catchup_is_recomputed() -> None:
    row = sc.energy_comparison(SEEDS, scenarios=("catchup-v1",)).iloc[0]
    committed = _csv("energy").set_index("scenario").loc["catchup-v1"]
    for key in ("energy_poly_kwh", "energy_map_kwh", "energy_mmpevem_kwh"):
        assert row[key] == pytest.approx(committed[key], rel=1e-5)


@FULL
def test_the_ploeg_and_human_tables_are_recomputed() -> None:
    for name, fresh in (("ploeg", sc.ploeg_comparison(SEEDS)),
                        ("humans", sc.human_comparison(SEEDS))):
        committed = _csv(name)
        num = [c for c in committed.columns if committed[c].dtype.kind == "f"
               and "diff" not in c]
        np.testing.assert_allclose(fresh[num].to_numpy(float), committed[num].to_numpy(float),
                                   rtol=1e-5, err_msg=name)


def test_the_readme_states_what_the_committed_report_shows() -> None:
    """The README's SUMO paragraph: its tolerances are the study's, and the committed tables
    hold them (matched trajectories, the MPC's, the energy models; Plexe's Ploeg reproduced by
    our law with Plexe's Euler filter step)."""
    readme = " ".join((Path(__file__).resolve().parents[2] / "README.md").read_text().split())
    part = readme[readme.index("## In SUMO"):readme.index("## Where the rest lives")]
    assert "within 1e-8 m (the MPC's within 1e-3 m)" in part
    assert (1e-8, 1e-3) == (sc.MATCHED_GAP_TOL_M, sc.MATCHED_MPC_TOL)
    assert f"within {sc.ENERGY_TOL_PCT:g} % of the battery's throughput" in part
    docs = Path(__file__).resolve().parents[2] / "docs" / "sumo"
    agree = pd.read_csv(docs / "agreement.csv")
    matched = agree[agree["simulator"] == "sumo"]
    mpc = matched["controller"] == "mpc-qp"
    assert (matched[~mpc]["max_gap_diff_m"] <= sc.MATCHED_GAP_TOL_M).all()
    assert (matched[mpc]["max_gap_diff_m"] <= sc.MATCHED_MPC_TOL).all()
    energy = pd.read_csv(docs / "energy.csv")
    assert (energy["poly_vs_mmpevem_pct_of_throughput"].abs() <= sc.ENERGY_TOL_PCT).all()
    assert "Plexe's Euler filter step, which reproduces" in part
    ploeg = pd.read_csv(docs / "ploeg.csv")
    assert "once our 30 m/s speed bound is lifted" in part
    euler = ploeg[ploeg["ours"].str.contains("Euler")]
    bounded_slowdown = (euler["scenario"] == "slowdown-v1") & (euler["speed_bound_mps"] == 30)
    assert (euler[~bounded_slowdown]["max_gap_diff_m"] <= sc.PLOEG_REPLICA_TOL).all()
    assert (euler[bounded_slowdown]["max_gap_diff_m"] > 1.0).all()  # why the README says so
