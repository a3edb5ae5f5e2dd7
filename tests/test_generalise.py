"""``cacc-bench generalise`` and :mod:`analysis.generalisation`: the cell rule on hand-made
runs, the command in small form, and the committed matrix reproduced by the command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from analysis.generalisation import COLUMNS, MODEL_BASED, Column, Row, cell_frame
from commands.cli import main

DOCS = Path(__file__).resolve().parents[1] / "docs" / "generalise"


def test_a_cell_pools_the_training_seeds_and_marks_what_cannot_run() -> None:
    rows = [Row("ippo-bdc (catchup-v1)", "ippo-bdc", (("scenario", "catchup-v1"),), True, 8)]
    recs = []
    for seed in (0, 1, 2):
        label = f"ippo-bdc[scenario=catchup-v1{',seed=' + str(seed) if seed else ''}]"
        for k in range(4):
            recs.append({"status": "ok", "controller": label, "scenario": "catchup-v1",
                         "n_vehicles": 8, "comm_delay_s": 0.0, "packet_loss": 0.0,
                         "reward": -400.0 - 10 * seed - k, "collision": seed == 2 and k == 0,
                         "gap_rmse_m": 1.0 + seed, "safety_interventions": 0.0,
                         "energy_kwh_per_100km": 9.0})
    cols = [COLUMNS[0], Column("catchup N=4", "catchup-v1", n_vehicles=4)]
    cells = cell_frame(pd.DataFrame(recs), rows, cols).set_index("column")
    assert cells.loc["catchup", "episodes"] == 12 and cells.loc["catchup", "collisions"] == 1
    assert cells.loc["catchup", "reward"] == pytest.approx(-400 - 10 - 1.5)
    assert cells.loc["catchup", "reward_ci_low"] < cells.loc["catchup", "reward"]
    assert cells.loc["catchup", "gap_rmse_m"] == pytest.approx(2.0)
    assert not cells.loc["catchup N=4", "applicable"]


def test_the_command_in_small_form(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "g"
    argv = ["generalise", "--controllers", "cacc,ippo-bdc,safe:ippo-bdc", "--columns",
            "catchup N=4,brake", "--episodes", "1", "--executor", "serial", "--out", str(out)]
    assert main(argv) == 0
    report = (out / "report.md").read_text()
    assert str(tmp_path) not in report and "n/a" in report
    cells = pd.read_csv(out / "matrix.csv")
    assert set(cells["row"]) == {"cacc", "ippo-bdc (catchup-v1)", "ippo-bdc (slowdown-v1)",
                                 "safe:ippo-bdc (catchup-v1)", "safe:ippo-bdc (slowdown-v1)"}
    bdc = cells[cells["row"].str.startswith("ippo-bdc")]
    assert not bdc[bdc["column"] == "catchup N=4"]["applicable"].any()
    assert (out / "figures" / "generalisation.png").exists()
    capsys.readouterr()
    assert main(["generalise", "--controllers", "nope", "--out", str(tmp_path / "x")]) == 2
    assert main(["generalise", "--columns", "moon", "--out", str(tmp_path / "x")]) == 2
    assert main(["generalise", "--episodes", "101", "--out", str(tmp_path / "x")]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_the_committed_matrix_is_what_the_command_gives(tmp_path: Path) -> None:
    """The brake-v1 column of every ``ippo`` row, rerun by the command from the shipped
    checkpoints on the same test seeds, is the committed one."""
    committed = pd.read_csv(DOCS / "matrix.csv")
    argv = ["generalise", "--controllers", "ippo", "--columns", "brake", "--episodes", "10",
            "--no-safety-filter", "--executor", "serial", "--out", str(tmp_path)]
    assert main(argv) == 0
    ours = pd.read_csv(tmp_path / "matrix.csv").set_index(["row", "column"])
    theirs = committed.set_index(["row", "column"]).loc[ours.index]
    for col in ("episodes", "collisions", "reward", "reward_ci_low", "reward_ci_high",
                "gap_rmse_m"):
        np.testing.assert_allclose(ours[col].to_numpy(float), theirs[col].to_numpy(float),
                                   rtol=1e-9, err_msg=col)
    rows = json.loads((DOCS / "rows.json").read_text())
    assert {r["label"] for r in rows} == set(committed["row"])


def test_the_readme_reading_is_the_committed_matrix() -> None:
    readme = (DOCS.parents[1] / "README.md").read_text()
    text = " ".join(readme[readme.index("## Off the training scenario"):
                           readme.index("## Where the rest lives")].split())
    m = pd.read_csv(DOCS / "matrix.csv")
    m = m[m["applicable"]]
    learned = [r for r in dict.fromkeys(m["row"]) if not r.startswith("safe:")
               and r not in MODEL_BASED]
    colliding = [r for r in learned if m[m["row"] == r]["collisions"].sum() > 0]
    one_scenario = [r for r in learned if "mixed-v1" not in r]
    assert (f"Of the {len(one_scenario)} learned rows trained on one scenario, "
            f"{sum(r in colliding for r in one_scenario)} collide somewhere") in text
    mixed = m[m["row"] == "ippo (mixed-v1)"]
    assert mixed["collisions"].sum() == 0 and len(mixed) == 11
    cell = m.set_index(["row", "column"])["reward"]
    for row, value in (("ippo (mixed-v1)", "-657.7"), ("duty", "-775.3"), ("cacc", "-609.6")):
        assert f"{cell[(row, 'brake')]:.1f}" == value and value in text
    assert m[m["row"].str.startswith("safe:")]["collisions"].sum() == 0
    cost = pd.read_csv(DOCS / "filter_cost.csv")
    for x in (cost["reward_change"].min(), cost["reward_change"].max()):
        assert f"{x:+.1f}".lstrip("+") in text
    for x in (cost["energy_change_kwh_per_100km"].min(), cost["energy_change_kwh_per_100km"].max()):
        assert f"{x:+.3f}".lstrip("+") in text


def test_the_mixed_training_reading_of_the_docs_is_the_checkpoints() -> None:
    from controllers.policy import checkpoint_path
    from marl.checkpoint import load_checkpoint

    text = (DOCS.parent / "learned-control.md").read_text()
    part = text[text.index("## Training on a distribution"):text.index("## Equal tuning")]
    for seed in (0, 1, 2):
        data = load_checkpoint(checkpoint_path("ippo", "mixed-v1", 8, seed))
        assert f"{data['curve_summary']['best_reward']:.2f}" in part
        assert (data["config"]["vehicles_min"], data["config"]["vehicles_max"]) == (4, 12)
        assert (data["config"]["comm_delay_max_s"], data["config"]["packet_loss_max"]) == (0.2, 0.3)
