"""``cacc-bench generalise`` and :mod:`studies.generalisation`: the cell rule on hand-made
runs, the command in small form, every shipped checkpoint a row or a stated reason, and the
committed matrix: reproduced by the command, its report written from its CSV, its rows the
command's rows."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from run_marks import FULL

from commands.cli import main
from commands.generalise import _available
from controllers.policy import CHECKPOINT_DIR
from studies.generalisation import (
    COLUMNS,
    MODEL_BASED,
    NOT_IN_MATRIX,
    Column,
    Row,
    cell_frame,
    learned_rows,
    unrun_checkpoints,
    with_safety_filter,
    write_report,
)

DOCS = Path(__file__).resolve().parents[2] / "docs" / "generalise"


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


def test_a_policy_trained_at_n4_fills_the_n4_cell_with_its_one_seed(tmp_path: Path) -> None:
    """The BDC policies trained at N = 4 (one seed shipped each) act in the N = 4 column only;
    the N = 8 BDC rows are "n/a" there; nothing runs for a cell marked "n/a"."""
    out = tmp_path / "g"
    argv = ["generalise", "--controllers", "bdc", "--columns", "catchup N=4,brake",
            "--episodes", "1", "--no-safety-filter", "--executor", "serial", "--out", str(out)]
    assert main(argv) == 0
    cells = pd.read_csv(out / "matrix.csv").set_index(["row", "column"])
    for sc in ("catchup-v1", "openacc-train-s-v1", "openacc-train-m-v1", "openacc-train-l-v1"):
        row = f"bdc ({sc}, N=4, seed 0)"
        assert cells.loc[(row, "catchup N=4"), "applicable"]
        assert cells.loc[(row, "catchup N=4"), "episodes"] == 1
        assert not cells.loc[(row, "brake"), "applicable"]
    for sc in ("catchup-v1", "slowdown-v1"):
        assert not cells.loc[(f"bdc ({sc})", "catchup N=4"), "applicable"]
        assert cells.loc[(f"bdc ({sc})", "brake"), "episodes"] == 3
    runs = pd.read_csv(out / "runs" / "runs.csv")
    assert len(runs) == 4 + 2 * 3 and set(runs["n_vehicles"]) == {4, 8}
    line = next(x for x in (out / "report.md").read_text().splitlines()
                if x.startswith("| `bdc (openacc-train-m-v1, N=4, seed 0)` |"))
    n4, brake = line.rstrip(" |").split(" | ")[1:3]
    assert n4.split(",")[0] in ("0/1", "1/1") and brake == "n/a"


def test_every_shipped_checkpoint_is_a_row_or_has_a_stated_reason() -> None:
    """A learned policy shipped in ``controllers/checkpoints`` (a new training scenario, family,
    N or variant) fails this test until a row runs it or :data:`NOT_IN_MATRIX` says why not;
    a row pools exactly the training seeds shipped for it, and every reason still applies."""
    rows = learned_rows(_available)
    unrun = unrun_checkpoints(CHECKPOINT_DIR, rows)
    assert "no row and no reason" not in unrun, unrun.get("no row and no reason")
    assert set(unrun) == {why for _, why in NOT_IN_MATRIX}  # no reason is stale
    for row in rows:
        first = CHECKPOINT_DIR / row.checkpoints()[0]
        stem = first.name.rsplit("__s", 1)[0]
        shipped = sorted(int(f.stem.rsplit("__s", 1)[1]) for f in first.parent.glob(f"{stem}__s*.pt"))
        assert tuple(shipped) == row.seeds, (row.label, shipped)
        assert len(row.seeds) == 3 or f"seed {row.seeds[0]})" in row.label
    safe = with_safety_filter(rows[-1])
    assert safe.checkpoints() == rows[-1].checkpoints() and safe.seeds == rows[-1].seeds


def test_the_committed_matrix_has_every_row_and_marks_what_cannot_run() -> None:
    """The committed rows are the command's rows today, in order; a cell is "n/a" exactly where
    the row's N is not the column's, and every other cell holds 10 test episodes per training
    seed."""
    committed = json.loads((DOCS / "rows.json").read_text())
    learned = learned_rows(_available)
    rows = [*learned, *(with_safety_filter(r) for r in learned),
            *(Row(name, name, (), False) for name in MODEL_BASED)]
    assert [r["label"] for r in committed] == [r.label for r in rows]
    by_label = {r.label: r for r in rows}
    cells = pd.read_csv(DOCS / "matrix.csv")
    assert list(dict.fromkeys(cells["row"])) == [r.label for r in rows]
    n_of = {c.name: c.n_vehicles for c in COLUMNS}
    for _, c in cells.iterrows():
        row = by_label[c["row"]]
        assert c["applicable"] == (row.only_n is None or row.only_n == n_of[c["column"]])
        if c["applicable"]:
            assert c["episodes"] == 10 * (len(row.seeds) if row.learned else 1), (row.label, c)
        else:
            assert np.isnan(c["episodes"])


def test_the_committed_report_is_written_from_its_csv(tmp_path: Path) -> None:
    """``report.md`` is what :func:`write_report` makes of the committed ``matrix.csv``, with the
    command its first line names and the shipped checkpoints no row runs."""
    committed = (DOCS / "report.md").read_text()
    command = committed.split("Made by `", 1)[1].split(" --out FOLDER`", 1)[0]
    cells = pd.read_csv(DOCS / "matrix.csv")
    cells["applicable"] = cells["applicable"].astype(bool)
    unrun = unrun_checkpoints(CHECKPOINT_DIR, learned_rows(_available))
    path = write_report(cells, tmp_path, command, 10, COLUMNS, unrun)
    assert path.read_text() == committed


@FULL
def test_the_committed_matrix_is_what_the_command_gives(tmp_path: Path) -> None:
    """The brake-v1 column of every ``ippo`` row, rerun by the command from the shipped
    checkpoints on the same test seeds, is the committed one."""
    committed = pd.read_csv(DOCS / "matrix.csv")
    argv = ["generalise", "--controllers", "ippo", "--columns", "brake", "--episodes", "10",
            "--no-safety-filter", "--executor", "serial", "--out", str(tmp_path)]
    assert main(argv) == 0
    ours = pd.read_csv(tmp_path / "matrix.csv").set_index(["row", "column"])
    theirs = committed.set_index(["row", "column"]).loc[ours.index]
    for col in ("episodes", "collisions"):
        np.testing.assert_array_equal(ours[col].to_numpy(), theirs[col].to_numpy(), err_msg=col)
    # bit-exact on the CPU that made the report; float32 kernels of other CPUs round otherwise
    # (the shared policies' cells moved by up to 3.2e-9 between an AMD EPYC and an Intel Xeon)
    for col in ("reward", "reward_ci_low", "reward_ci_high", "gap_rmse_m"):
        np.testing.assert_allclose(ours[col].to_numpy(float), theirs[col].to_numpy(float),
                                   rtol=1e-6, err_msg=col)
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
    one_scenario = [r for r in learned if "(mixed-" not in r]
    assert (f"Of the {len(one_scenario)} learned rows trained on one scenario or one "
            f"OpenACC-like family, {sum(r in colliding for r in one_scenario)} collide "
            "somewhere") in text
    at_n4 = [r for r in learned if "N=4" in r]
    assert len(at_n4) == 4 and "the four trained at N = 4 collide in none" in text
    assert all(m[m["row"] == r]["collisions"].sum() == 0 for r in at_n4)
    assert all(len(m[m["row"] == r]) == 4 for r in at_n4)  # the N = 4 columns, OpenACC's included
    assert "on fourteen test conditions" in text and len(COLUMNS) == 14
    for family in ("mixed-v1", "mixed-v2"):
        mixed = m[m["row"] == f"ippo ({family})"]
        assert mixed["collisions"].sum() == 0 and len(mixed) == len(COLUMNS)
    cell = m.set_index(["row", "column"])["reward"]
    for row, column, value in (("ippo (mixed-v1)", "brake", "-657.7"), ("duty", "brake", "-775.3"),
                               ("cacc", "brake", "-609.6"), ("ippo (mixed-v2)", "brake", "-737.8"),
                               ("ippo (mixed-v2)", "OpenACC S", "-391.6"),
                               ("ippo (mixed-v1)", "OpenACC S", "-366.4")):
        assert f"{cell[(row, column)]:.1f}" == value and value in text, (row, column)
    # "no better on the OpenACC windows": every OpenACC column, at N = 8 and at N = 4
    for column in (c.name for c in COLUMNS if c.name.startswith("OpenACC")):
        assert cell[("ippo (mixed-v2)", column)] <= cell[("ippo (mixed-v1)", column)], column
    assert "the time-aware residual on `cacc` and `ippo-gains` nowhere" in text
    assert all(m[m["row"] == f"{row} ({sc})"]["collisions"].sum() == 0
               for row in ("ippo residual-timed", "ippo-gains")
               for sc in ("catchup-v1", "slowdown-v1"))
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
    cell = pd.read_csv(DOCS / "matrix.csv").set_index(["row", "column"])["reward"]
    flat = " ".join(part.split())
    for family in ("mixed-v1", "mixed-v2"):
        for column in ("OpenACC S", "OpenACC M", "OpenACC L", "brake"):
            assert f"{cell[(f'ippo ({family})', column)]:.1f}" in flat, (family, column)
    for family, seed in ((f, s) for f in ("mixed-v1", "mixed-v2") for s in (0, 1, 2)):
        data = load_checkpoint(checkpoint_path("ippo", family, 8, seed))
        assert f"{data['curve_summary']['best_reward']:.2f}" in part
        assert (data["config"]["vehicles_min"], data["config"]["vehicles_max"]) == (4, 12)
        assert (data["config"]["comm_delay_max_s"], data["config"]["packet_loss_max"]) == (0.2, 0.3)
