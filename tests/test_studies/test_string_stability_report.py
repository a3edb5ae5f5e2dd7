"""``cacc-bench string-stability`` (:mod:`studies.string_stability`): the command in small form,
the committed report against its tables, and (``full``) its numbers recomputed from the shipped
checkpoints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from run_marks import FULL

from studies import string_stability as st

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = ROOT / "docs" / "string-stability"


def _command_line(report: str) -> str:
    """The command the report says made it (its first backticked command)."""
    line = next(x for x in report.splitlines() if x.startswith("Made by `"))
    return line.split("`")[1].removesuffix(" --out FOLDER")


def test_the_command_in_small_form(tmp_path) -> None:
    """One test episode, one validation episode, the small design grid, N = 4 sweeps, ``cacc``
    and ``ippo-gains`` on ``catchup-v1``: every table is written, the report is its tables, the
    goal has a row per learned entry, and the shipped segments are certified."""
    from commands.cli import main

    out = tmp_path / "ss"
    argv = ["string-stability", "--scenarios", "catchup-v1", "--episodes", "1",
            "--validation-episodes", "1", "--design", "small", "--sizes", "4",
            "--controllers", "cacc,ippo-gains", "--executor", "serial", "--out", str(out)]
    assert main(argv) == 0
    tables = st.read_tables(out)
    report = (out / "report.md").read_text()
    assert report == st.render_report(tables, _command_line(report))
    assert _command_line(report) == ("cacc-bench string-stability --scenarios catchup-v1 "
                                     "--episodes 1 --validation-episodes 1 --design small "
                                     "--sizes 4 --controllers cacc,ippo-gains --executor serial")
    assert set(tables["goal"]["entry"]) == {"ippo-gains"}
    sweeps = tables["sweeps"]
    assert set(zip(sweeps["n_vehicles"], sweeps["channel"])) == {(4, "ideal"), (4, "degraded"),
                                                                 (4, "none")}
    assert len(sweeps[sweeps["entry"] == "ippo-gains"]) == 3 * 3  # three seeds, three settings
    assert tables["segments"]["certified"].all() and len(tables["segments"]) == 3
    assert len(tables["design"]) == 8 and set(tables["rewards"]["channel"]) == set(st.CHANNELS)
    # resumed: nothing runs again, the same tables
    assert main([*argv, "--resume"]) == 0
    again = st.read_tables(out)
    for name in ("rewards", "sweeps", "design"):
        pd.testing.assert_frame_equal(again[name], tables[name])


def test_the_committed_report_is_made_of_its_tables() -> None:
    """The committed report is rendered from its CSVs; its reward table is the episodes'
    (means and intervals), its goal the episodes' and sweeps' (every verdict recomputed)."""
    tables = st.read_tables(COMMITTED)
    report = (COMMITTED / "report.md").read_text()
    assert report == st.render_report(tables, _command_line(report))
    from infra.files import read_csv

    episodes = read_csv(COMMITTED / "episodes.csv", "the episodes table")
    entries = [e for e in st.default_entries() if e.name in set(episodes["entry"])]
    rewards = st.reward_table(episodes, entries)
    pd.testing.assert_frame_equal(rewards.reset_index(drop=True),
                                  tables["rewards"].reset_index(drop=True), check_dtype=False)
    goal = st.goal_frame(episodes, tables["sweeps"], entries)
    pd.testing.assert_frame_equal(goal.reset_index(drop=True),
                                  tables["goal"].reset_index(drop=True), check_dtype=False)
    # the pooled peak of a learned entry is its training seeds' largest
    sw = tables["sweeps"]
    one = sw[(sw["entry"] == "ippo-gains") & (sw["channel"] == "ideal")]
    assert (one.groupby(["scenario", "n_vehicles"]).size() == len(st.TRAIN_SEEDS)).all()
    assert set(st.TRAIN_SEEDS) == set(one["train_seed"])


@FULL
def test_the_committed_numbers_recompute_from_the_shipped_checkpoints(tmp_path) -> None:
    """``cacc`` and ``ippo-gains``: their test rewards (every V2V setting, both scenarios, all
    100 test seeds), collisions and sweep peaks (every size and setting) recomputed from the
    shipped checkpoints match the committed tables (rewards within 0.05 %, the tolerance across
    processors, collisions equal; peaks within 0.05 %)."""
    from commands.cli import main

    out = tmp_path / "ss"
    assert main(["string-stability", "--controllers", "cacc,ippo-gains", "--design", "small",
                 "--validation-episodes", "1", "--out", str(out)]) == 0
    got, want = st.read_tables(out), st.read_tables(COMMITTED)
    keys = ["entry", "scenario", "channel"]
    r = got["rewards"].merge(want["rewards"], on=keys, suffixes=("", "_c"))
    assert len(r) == len(got["rewards"]) > 0
    assert (r["collisions"] == r["collisions_c"]).all()
    np.testing.assert_allclose(r["reward"], r["reward_c"], rtol=5e-4)
    keys = ["entry", "scenario", "train_seed", "n_vehicles", "channel"]
    s = got["sweeps"].merge(want["sweeps"], on=keys, suffixes=("", "_c"))
    assert len(s) == len(got["sweeps"]) > 0
    np.testing.assert_allclose(s["peak_gain"], s["peak_gain_c"], rtol=5e-4)
    g = got["goal"].merge(want["goal"], on=["entry", "scenario"], suffixes=("", "_c"))
    assert (g["goal_met"] == g["goal_met_c"]).all() and len(g) == 2


@pytest.mark.parametrize(("argv", "message"), [
    (["--sizes", "4,x"], "--sizes takes a comma list"),
    (["--controllers", "nobody"], "nobody is no entry of the report"),
    (["--validation-episodes", "33"], "--validation-episodes"),
])
def test_bad_options_are_refused_in_one_line(argv: list[str], message: str, tmp_path,
                                              capsys) -> None:
    from commands.cli import main

    assert main(["string-stability", *argv, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_the_pages_kept_snapshots_are_the_shipped_checkpoints() -> None:
    """``docs/string-stability/README.md``'s table of kept snapshots: each number is the
    validation reward its shipped ``ippo-gains`` checkpoint records, and each checkpoint's
    segment is the default one the page describes."""
    from controllers.policy import checkpoint_path
    from marl.checkpoint import load_checkpoint
    from marl.ippo_gains import GainScheduleConfig, load_gain_actor

    page = (COMMITTED / "README.md").read_text()
    for sc in ("catchup-v1", "slowdown-v1"):
        row = next(x for x in page.splitlines() if x.startswith(f"| {sc} |"))
        quoted = [float(c) for c in row.strip(" |").split(" | ")[1:]]
        got = []
        for seed in st.TRAIN_SEEDS:
            data = load_checkpoint(checkpoint_path("ippo-gains", sc, 8, seed), algo="ippo-gains")
            got.append(round(data["curve_summary"]["best_reward"], 2))
            assert load_gain_actor(data).segment == GainScheduleConfig().segment
        assert quoted == got, sc


def test_the_readme_quotes_the_committed_goal() -> None:
    """The README's string-stability reading: every number is the committed goal table's
    (``ippo-gains`` against ``cacc``), and the goal holds on both scenarios."""
    import re

    text = " ".join((ROOT / "README.md").read_text().split())
    start = text.index("**String stability.**")
    part = text[start:text.index("How they were trained", start)]
    goal = st.read_tables(COMMITTED)["goal"].set_index(["entry", "scenario"])
    c, s = goal.loc[("ippo-gains", "catchup-v1")], goal.loc[("ippo-gains", "slowdown-v1")]
    peaks = [c[f"peak_ideal_n{n}"] for n in (4, 8, 12)] + [
        s[f"peak_ideal_n{n}"] for n in (4, 8, 12)]
    deg = [c[f"peak_degraded_n{n}"] for n in (4, 8, 12)] + [
        s[f"peak_degraded_n{n}"] for n in (4, 8, 12)]
    want = [f"{max(peaks):.3f}", f"{c['cacc_peak_ideal_n8']:.3f}", f"{max(deg):.3f}",
            f"{c['cacc_peak_degraded_n8']:.3f}"]
    for row in (c, s):
        want += [f"{row['difference']:.2f} [{row['ci_low']:.2f}, {row['ci_high']:.2f}]"]
    want += [f"{c['loss_degraded']:.2f} and {s['loss_degraded']:.2f}",
             f"{c['reference_loss_degraded']:.2f} and {s['reference_loss_degraded']:.2f}"]
    for needle in want:
        assert needle in part, needle
    assert bool(c["goal_met"]) and bool(s["goal_met"]) and "the learned controller that keeps it" in part
    # every number of the reading is checked (besides the 0.2 s delay of the setting)
    assert len([x for x in re.findall(r"\d+\.\d+", part) if x != "0.2"]) == 14
