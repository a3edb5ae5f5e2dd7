"""``cacc-bench penetration``: the design, the cells and the report in small, the refusals, and
the committed study's cells recomputed."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from run_marks import FULL

from commands.cli import main as cli
from studies.penetration import BASELINE, SHARES, controllers_for, design

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = ROOT / "docs" / "penetration"


def test_the_design_crosses_every_share_with_placements_for_the_mixed_ones() -> None:
    settings = design(["catchup-v1", "ring-v1"], placements=3)
    assert len(settings) == 2 * (2 + 4 * 3)
    shares = {s.share.name for s in settings}
    assert shares == {s.name for s in SHARES}
    ring = [s.build().arrangement(22) for s in settings if s.scenario == "ring-v1"]
    counts = sorted({a.n_automated for a in ring})
    assert counts == [0, 1, 6, 11, 17, 22]  # none, one, 0.25, 0.5, 0.75 (half up), all
    # the placements are other arrangements of the same share
    half = {s.build().arrangement(8).automated for s in settings
            if s.scenario == "catchup-v1" and s.share.name == "0.5"}
    assert len(half) == 3
    families = [("acc", {}), ("ippo", {"variant": "mixed-traffic"})]
    assert controllers_for(SHARES[0], families) == [(BASELINE, {})]
    assert controllers_for(SHARES[3], families) == families


def test_the_study_in_small(tmp_path: Path) -> None:
    out = tmp_path / "pen"
    assert cli(["penetration", "--episodes", "2", "--placements", "2", "--scenarios",
                "catchup-v1", "--controllers", "acc,followerstopper", "--executor", "serial",
                "--out", str(out)]) == 0
    table = pd.read_csv(out / "cells.csv")
    base = table[table["controller"] == BASELINE]
    assert list(base["share"].astype(str)) == ["0"] and base["cav_share"].iloc[0] == 0.0
    fam = table[table["controller"] == "acc"]
    assert list(fam["share"].astype(str)) == ["one vehicle", "0.25", "0.5", "0.75", "1"]
    # mixed shares pool two placements of two episodes, the others one arrangement
    assert list(fam["runs"]) == [4, 4, 4, 4, 2]
    runs = pd.read_csv(out / "runs" / "runs.csv")
    one = runs[(runs["controller"] == "acc") & (runs["cav_share"] == 0.125)]
    assert len(one) == 4 and table.loc[fam.index[0], "energy_cavs_kwh"] == pytest.approx(
        one["energy_cavs_kwh"].mean())
    report = (out / "report.md").read_text()
    assert "](figures/penetration-catchup-v1.png)" in report and str(tmp_path) not in report
    assert (out / "figures" / "penetration-catchup-v1.png").is_file()


@pytest.mark.parametrize("argv", [
    ["--placements", "0"], ["--episodes", "0"], ["--scenarios", "nope"],
    ["--controllers", "bdc"],  # a per-agent policy on a mixed string: refused before any run
])
def test_bad_input_is_refused_before_any_run(argv: list[str], tmp_path: Path) -> None:
    out = tmp_path / "pen"
    assert cli(["penetration", *argv, "--out", str(out)]) == 2
    assert not (out / "runs").exists()


@FULL
def test_the_committed_cells_are_what_the_command_computes(tmp_path: Path) -> None:
    """Two cells of the committed study on ring-v1 (the all-human string and one wave damper
    among 21 humans), recomputed by the command from scratch."""
    committed = pd.read_csv(COMMITTED / "cells.csv")
    out = tmp_path / "pen"
    assert cli(["penetration", "--scenarios", "ring-v1", "--controllers", "followerstopper",
                "--placements", "1", "--executor", "serial", "--out", str(out)]) == 0
    fresh = pd.read_csv(out / "cells.csv")
    for controller, share in ((BASELINE, "0"), ("followerstopper", "1")):
        def row(t: pd.DataFrame, c: str = controller, s: str = share) -> pd.Series:
            m = t[(t["scenario"] == "ring-v1") & (t["controller"] == c)
                  & (t["share"].astype(str) == s)]
            assert len(m) == 1
            return m.iloc[0]
        a, b = row(committed), row(fresh)
        for col in ("runs", "collisions", "speed_std_humans_mps", "braking_events_per_veh_h",
                    "energy_kwh_per_100km", "head_to_tail_gain"):
            assert a[col] == pytest.approx(b[col], rel=1e-9, nan_ok=True), col


def _cell(t: pd.DataFrame, scenario: str, controller: str, share: str) -> pd.Series:
    m = t[(t["scenario"] == scenario) & (t["controller"] == controller)
          & (t["share"].astype(str) == share)]
    assert len(m) == 1, (scenario, controller, share)
    return m.iloc[0]


def test_the_readme_quotes_the_committed_study() -> None:
    readme = (ROOT / "README.md").read_text()
    t = pd.read_csv(COMMITTED / "cells.csv")
    base = _cell(t, "ring-v1", BASELINE, "0")
    fs = _cell(t, "ring-v1", "followerstopper", "one vehicle")
    pi = _cell(t, "ring-v1", "pi-saturation", "one vehicle")

    def pct(new: float, old: float) -> str:
        return f"{100 * (new - old) / old:+.0f} %".replace("+", "")

    assert (f"from {base['speed_std_humans_mps']:.2f} to {fs['speed_std_humans_mps']:.2f} m/s "
            f"({pct(fs['speed_std_humans_mps'], base['speed_std_humans_mps'])})") in readme
    assert f"{base['braking_events_per_veh_h']:.1f} per vehicle-hour to none" in readme
    assert fs["braking_events_per_veh_h"] == 0 and pi["braking_events_per_veh_h"] == 0
    assert fs["collisions"] == 0 and pi["collisions"] == 0
    saving = pct(fs["energy_kwh_per_100km"], base["energy_kwh_per_100km"]).lstrip("-")
    assert f"the string's energy by {saving}" in readme
    assert (f"(`pi-saturation`: {pi['speed_std_humans_mps']:.2f} m/s, none, "
            f"{pct(pi['energy_kwh_per_100km'], base['energy_kwh_per_100km'])})") in readme
    for family in ("mpc", "mpc-qp"):  # neither damps nor collides
        c = _cell(t, "ring-v1", family, "one vehicle")
        assert c["collisions"] == 0 and c["speed_std_humans_mps"] > base["speed_std_humans_mps"]
    for family in ("acc", "cacc"):  # collide in every episode of a mixed ring
        mixed = t[(t["scenario"] == "ring-v1") & (t["controller"] == family)
                  & (t["share"].astype(str) != "1")]
        assert (mixed["collisions"] == mixed["runs"]).all()
    pi_rows = t[(t["controller"] == "pi-saturation")]
    for scenario, n in (("slowdown-v1", 8), ("brake-v1", 8), ("openacc-s-v1", 4)):
        rows = pi_rows[pi_rows["scenario"] == scenario]
        more = rows[rows["cav_share"] * n > 1.5]  # more than one seat
        assert len(more) >= 3 and (more["collisions"] > 0).all(), scenario
    for scenario in ("catchup-v1", "ring-v1"):
        assert (pi_rows[pi_rows["scenario"] == scenario]["collisions"] == 0).all()


def test_the_readme_mixed_traffic_command_runs_in_small(tmp_path: Path) -> None:
    assert cli(["run", "--controllers", "cacc,mpc-qp,followerstopper,pi-saturation",
                "--scenarios", "ring-v1,catchup-v1:cav_fraction=0.5", "--episodes", "1",
                "--out", str(tmp_path / "r")]) == 0
    runs = pd.read_csv(tmp_path / "r" / "runs.csv")
    assert set(runs["scenario"]) == {"ring-v1", "catchup-v1[cav_fraction=0.5]"}
    assert sorted(runs["cav_share"].unique()) == pytest.approx([1 / 22, 0.5])


@pytest.mark.parametrize("scenario", ["ring-v1:cavs=0", "catchup-v1:humans=2",
                                      "catchup-v1:placement=front"])
def test_the_study_sets_the_arrangement_itself(scenario: str, tmp_path: Path) -> None:
    out = tmp_path / "pen"
    assert cli(["penetration", "--scenarios", scenario, "--out", str(out)]) == 2
    assert not out.exists()


def test_a_scenario_keeps_its_own_options_in_the_study(tmp_path: Path) -> None:
    out = tmp_path / "pen"
    assert cli(["penetration", "--scenarios", "sine-v1:amplitude_mps=2", "--controllers", "acc",
                "--episodes", "1", "--placements", "1", "--executor", "serial",
                "--out", str(out)]) == 0
    runs = pd.read_csv(out / "runs" / "runs.csv")
    assert all(s.startswith("sine-v1[amplitude_mps=2.0") for s in runs["scenario"])


def test_behind_a_leader_followerstopper_leaves_the_humans_the_smallest_spread() -> None:
    """The README: behind a leader, ``followerstopper`` gives the humans the smallest speed
    spread among the families without a collision at almost every mixed share (all but one
    of the 16 cells of the four leader scenarios)."""
    t = pd.read_csv(COMMITTED / "cells.csv")
    mixed = [s.name for s in SHARES if s.mixed]
    best = []
    for scenario in ("catchup-v1", "slowdown-v1", "brake-v1", "openacc-s-v1"):
        for share in mixed:
            ok = t[(t["scenario"] == scenario) & (t["share"].astype(str) == share)
                   & (t["collisions"] == 0) & (t["controller"] != BASELINE)]
            best.append(ok.loc[ok["speed_std_humans_mps"].idxmin(), "controller"])
    assert len(best) == 16 and best.count("followerstopper") >= 15, best


LEARNED_FAMILY = "ippo[scenario=mixed-v2,variant=mixed-traffic]"


def test_the_readme_quotes_the_learned_family() -> None:
    """The README's reading of the mixed-traffic policy (three training seeds pooled): no
    collision behind a leader, and on the ring its humans' speed spread at each share."""
    from studies.penetration import LEARNED, family

    assert {family(lb) for lb in LEARNED} == {LEARNED_FAMILY}
    readme = (ROOT / "README.md").read_text()
    t = pd.read_csv(COMMITTED / "cells.csv")
    learned = t[t["controller"] == LEARNED_FAMILY]
    leader = learned[learned["scenario"] != "ring-v1"]
    assert len(leader) == 20 and (leader["collisions"] == 0).all()
    assert "leaves the humans there a larger speed spread than `followerstopper`" in readme
    for _, c in leader[leader["share"].astype(str) != "1"].iterrows():
        fs = _cell(t, c["scenario"], "followerstopper", str(c["share"]))
        assert c["speed_std_humans_mps"] > fs["speed_std_humans_mps"], (c["scenario"], c["share"])
    base = _cell(t, "ring-v1", BASELINE, "0")["speed_std_humans_mps"]
    one, quarter, half = (_cell(t, "ring-v1", LEARNED_FAMILY, s)["speed_std_humans_mps"]
                          for s in ("one vehicle", "0.25", "0.5"))
    cut = [round(100 * (1 - v / base)) for v in (one, quarter, half)]
    assert (f"by {cut[0]} % only\n({base:.2f} to {one:.2f} m/s), at a quarter of the seats by "
            f"{cut[1]} % ({quarter:.2f} m/s), at half by {cut[2]} % ({half:.3f} m/s)") in readme
    three, every = (_cell(t, "ring-v1", LEARNED_FAMILY, s) for s in ("0.75", "1"))
    assert (f"collides at three quarters ({three['collisions']} of {three['runs']} runs) and on "
            f"the all-automated ring ({every['collisions']} of {every['runs']})") in readme


def test_a_learned_cell_is_what_the_command_computes(tmp_path: Path) -> None:
    """The learned family's cell on catchup-v1 at share 1 (its three seeds), recomputed."""
    from studies.penetration import LEARNED

    committed = pd.read_csv(COMMITTED / "cells.csv")
    out = tmp_path / "pen"
    assert cli(["penetration", "--scenarios", "catchup-v1", "--controllers", ",".join(LEARNED),
                "--placements", "1", "--executor", "serial", "--out", str(out)]) == 0
    fresh = pd.read_csv(out / "cells.csv")
    a, b = (_cell(t, "catchup-v1", LEARNED_FAMILY, "1") for t in (committed, fresh))
    for col in ("runs", "collisions", "speed_std_last_mps", "braking_events_per_veh_h",
                "energy_kwh_per_100km"):
        assert a[col] == pytest.approx(b[col], rel=1e-9, nan_ok=True), col


SMALL = ["penetration", "--scenarios", "catchup-v1", "--controllers", "acc", "--episodes", "1",
         "--placements", "1", "--executor", "serial"]


@pytest.mark.parametrize(("made", "resume", "needle"), [
    ("report.md", False, "already holds a penetration study (report.md); add --resume"),
    ("runs/store.sqlite", False, "already holds a penetration study (runs/store.sqlite)"),
    ("figures", True, "figures is a file, where the study writes the other"),
    ("report.md/", True, "report.md is a folder"),
    ("figures/penetration-catchup-v1.png/", True, "penetration-catchup-v1.png is a folder"),
])
def test_a_folder_holding_a_study_or_blocking_its_files_is_refused_before_any_run(
        made: str, resume: bool, needle: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 53: without --resume a study's finished report, table and figures were made again
    (once its runs were gone), and a file where the figures folder goes (or a folder where the
    report goes) gave a traceback after every run."""
    out = tmp_path / "pen"
    path = out / made
    path.parent.mkdir(parents=True)
    path.mkdir() if made.endswith("/") else path.write_text("finished")
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert cli([*SMALL, "--out", str(out), *(["--resume"] if resume else [])]) == 2
    err = capsys.readouterr().err
    assert needle in err and len(err.strip().splitlines()) == 1, err
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert not (out / "runs" / "runs.csv").exists()



def test_the_baseline_is_not_a_family(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 53: ``--controllers idm`` ran the baseline as a family the report then left out,
    reading "none without a collision" at every share."""
    out = tmp_path / "pen"
    assert cli([*SMALL, "--controllers", "acc,idm", "--out", str(out)]) == 2
    assert "all-human baseline" in capsys.readouterr().err and not out.exists()


def test_a_damaged_store_under_resume_is_one_line(tmp_path: Path, capsys) -> None:
    """The study's banner comes after the store and its CSV are checked: a damaged runs.csv is
    refused in one line."""
    out = tmp_path / "pen"
    small = ["penetration", "--episodes", "1", "--placements", "1", "--scenarios", "ring-v1",
             "--controllers", "followerstopper", "--executor", "serial", "--out", str(out)]
    assert cli(small) == 0
    (out / "runs" / "runs.csv").write_bytes(b"\xff\xfe garbage\x00")
    capsys.readouterr()
    assert cli([*small, "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "runs.csv" in err[0], err
