"""``cacc-bench heterogeneous`` (issue 55 item 6): the design, the study in small, the
refusals, and the committed report's numbers against its cells and peaks files."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pandas as pd
import pytest

from commands.cli import main as cli
from studies.heterogeneous import BASELINE, HUMANS, METRICS, ORDERS, Setting, design

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = ROOT / "docs" / "heterogeneous"


def test_the_design_crosses_orders_with_and_without_humans() -> None:
    settings = design(["brake-v1"])
    assert len(settings) == len(ORDERS) * 3
    heavy_first = Setting("brake-v1", "heavy first", "mixed").build()
    assert heavy_first.vehicle_classes(8)[0].name == "bus"
    assert heavy_first.arrangement(8).automated == tuple(
        i + 1 not in {int(k) for k in HUMANS.split("+")} for i in range(8))
    assert Setting("brake-v1", "heavy last", "all").build().arrangement(8).n_automated == 0
    spread = [c.name for c in Setting("brake-v1", "spread", "none").build().vehicle_classes(8)]
    assert spread.index("bus") == 2 and spread.index("van") == 5


def test_the_study_in_small(tmp_path: Path) -> None:
    out = tmp_path / "het"
    argv = ["heterogeneous", "--scenarios", "brake-v1", "--orders", "heavy first",
            "--controllers", "cacc", "--executor", "serial", "--out", str(out)]
    assert cli(argv) == 0
    table = pd.read_csv(out / "cells.csv")
    assert set(table["controller"]) == {"cacc", BASELINE}
    assert list(table["humans"]) == ["none", "mixed", "all"]
    runs = pd.read_csv(out / "runs" / "runs.csv")
    one = runs[(runs["controller"] == "cacc") & ~runs["scenario"].str.contains("humans")]
    assert table.loc[0, "energy_kwh_per_100km_bus"] == pytest.approx(
        float(one["energy_kwh_per_100km_bus"].iloc[0]))
    peaks = pd.read_csv(out / "head_to_tail.csv")
    assert (peaks["max_relative_difference"] < 0.02).all()
    report = (out / "README.md").read_text()
    assert "](figures/head-to-tail-peaks.png)" in report and str(tmp_path) not in report
    assert (out / "figures" / "head-to-tail-peaks.png").is_file()
    # a finished folder is refused without --resume, before any run
    assert cli(argv) == 2
    assert cli([*argv, "--resume"]) == 0


@pytest.mark.parametrize("argv", [
    ["--episodes", "0"], ["--scenarios", "nope"], ["--orders", "heavy middle"],
    ["--scenarios", "brake-v1:classes=bus+car*7"], ["--controllers", "idm"],
    ["--controllers", "bdc"],  # a per-agent policy on a heterogeneous string
])
def test_bad_input_is_refused_before_any_run(argv: list[str], tmp_path: Path) -> None:
    out = tmp_path / "het"
    assert cli(["heterogeneous", *argv, "--out", str(out)]) == 2
    assert not (out / "runs").exists()


def _fmt(x: float, spec: str = ".3g") -> str:
    return "n/a" if not math.isfinite(x) else format(x, spec)


def test_the_committed_report_quotes_its_cells_and_peaks() -> None:
    """Every row of the committed README's tables is its cells.csv / head_to_tail.csv row."""
    report = (COMMITTED / "README.md").read_text()
    cells = pd.read_csv(COMMITTED / "cells.csv")
    assert set(cells["scenario"]) == {"catchup-v1", "slowdown-v1", "brake-v1"}
    assert set(cells["order"]) == set(ORDERS)
    for _, r in cells.iterrows():
        line = (f"| {r['order']} | {r['humans']} | `{r['controller']}` | {r['runs']} | "
                f"{r['collisions']} | {_fmt(r['min_gap_m'])} | "
                + " | ".join(_fmt(r[c]) for c, _ in METRICS) + " |")
        assert line in report, line
    peaks = pd.read_csv(COMMITTED / "head_to_tail.csv")
    for _, r in peaks.iterrows():
        assert (f"| {r['order']} | {r['humans']} | `{r['controller']}` | "
                f"{_fmt(r['peak_analytic'], '.4g')} | {_fmt(r['peak_measured'], '.4g')} |"
                ) in report
    assert (peaks["max_relative_difference"] < 0.02).all()
    worst = float(peaks["max_relative_difference"].max())
    assert f"differ by at most {100 * worst:.2g} %" in report
    for fig in re.findall(r"\]\((figures/[^)]+)\)", report):
        assert (COMMITTED / fig).is_file(), fig


def test_the_readme_states_the_heterogeneous_finding() -> None:
    """The README's lines on the study are the committed files' numbers."""
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert "docs/heterogeneous/README.md" in readme
    peaks = pd.read_csv(COMMITTED / "head_to_tail.csv").set_index(["order", "humans",
                                                                     "controller"])
    cacc = {o: peaks.loc[(o, "none", "cacc"), "peak_analytic"] for o in ORDERS}
    homogeneous = peaks.loc[("homogeneous", "none", "cacc"), "peak_analytic"]
    assert (f"rises from {homogeneous:.2f} (homogeneous) to {cacc['heavy first']:.2f} (bus "
            f"first or spread) and {cacc['heavy last']:.2f} (bus last)") in readme
    assert f"{cacc['spread']:.2f}" == f"{cacc['heavy first']:.2f}"
    xiao = {f"{peaks.loc[(o, 'none', 'cacc[time_gap_rule=xiao]'), 'peak_analytic']:.2f}"
            for o in ORDERS}
    assert len(xiao) == 1 and f"brings it back to {xiao.pop()} in every order" in readme
    worst = float(pd.read_csv(COMMITTED / "head_to_tail.csv")["max_relative_difference"].max())
    assert worst < 0.005 and "measured sweep agree within 0.5 %" in readme
    mixed = pd.read_csv(COMMITTED / "head_to_tail.csv")
    mixed = mixed[(mixed["humans"] == "mixed")]
    assert (mixed["peak_analytic"] > 1).all() and (mixed["peak_measured"] > 1).all()
    cells = pd.read_csv(COMMITTED / "cells.csv")
    acc = cells[(cells["controller"] == "acc") & (cells["humans"] == "none")]
    assert f"`acc` collides in all {len(acc)} all-automated runs" in readme
    assert (acc["collisions"] == acc["runs"]).all()
    hits = cells[cells["humans"] == "mixed"].groupby("controller")["collisions"].sum()
    assert list(hits[hits == 0].index) == ["ippo[scenario=mixed-v2,variant=mixed-traffic]"]
