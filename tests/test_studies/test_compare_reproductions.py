"""studies/compare_reproductions.py: two reproduce folders compared cell by cell."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from studies import compare_reproductions as mod

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = ROOT / "docs" / "paper-reproduction"


def _as_command_wrote_it(tmp_path: Path) -> Path:
    """The committed report laid out as the command's own folder (leaderboard under runs/)."""
    out = tmp_path / "out"
    (out / "runs").mkdir(parents=True)
    for name in mod.TABLES:
        src = COMMITTED / name
        shutil.copyfile(src, out / ("runs" if name == "leaderboard.csv" else "") / name)
    return out


def test_a_folder_equals_its_published_copy(tmp_path: Path, capsys) -> None:
    out = _as_command_wrote_it(tmp_path)
    assert mod.main(str(COMMITTED), str(out)) == 0
    printed = capsys.readouterr().out
    assert "every table equal (timings aside)" in printed
    assert printed.count("equal (timings aside)") == len(mod.TABLES) + 1


def test_timings_are_left_out_and_one_changed_digit_is_found(tmp_path: Path, capsys) -> None:
    import pandas as pd

    out = _as_command_wrote_it(tmp_path)
    board = out / "runs" / "leaderboard.csv"
    text = pd.read_csv(board, dtype=str, keep_default_na=False)
    text["compute_ms_p50_mean"] = "0.123"  # another machine's timing
    text.to_csv(board, index=False)
    assert mod.differing_cells(COMMITTED / "leaderboard.csv", board) == {}
    t2 = pd.read_csv(out / "table2.csv", dtype=str, keep_default_na=False)
    value = t2.loc[3, "power_kw_avg"]
    t2.loc[3, "power_kw_avg"] = value[:-1] + ("1" if value[-1] != "1" else "2")  # last digit
    t2.to_csv(out / "table2.csv", index=False)
    assert mod.differing_cells(COMMITTED / "table2.csv", out / "table2.csv") == {"power_kw_avg": 1}
    assert mod.main(str(COMMITTED), str(out)) == 1
    assert "table2.csv: 1 cells differ (power_kw_avg 1)" in capsys.readouterr().out


def test_other_rows_are_no_cell_comparison(tmp_path: Path) -> None:
    out = _as_command_wrote_it(tmp_path)
    lines = (out / "sizes.csv").read_text().splitlines(keepends=True)
    (out / "sizes.csv").write_text("".join(lines[:-1]))
    assert mod.differing_cells(COMMITTED / "sizes.csv", out / "sizes.csv") is None


def test_reports_of_other_claim_counts_differ_without_a_traceback(tmp_path: Path, capsys) -> None:
    out = _as_command_wrote_it(tmp_path)
    lines = (out / "claims.csv").read_text().splitlines(keepends=True)
    (out / "claims.csv").write_text("".join(lines[:-1]))
    assert mod.main(str(COMMITTED), str(out)) == 1
    assert "not comparable claim by claim" in capsys.readouterr().out


def test_a_folder_without_a_report_is_refused(tmp_path: Path, capsys) -> None:
    assert mod.main(str(COMMITTED), str(tmp_path)) == 2
    assert "no claims.csv" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [[], ["one"]])
def test_usage(argv: list[str]) -> None:
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", mod.__name__, *argv], capture_output=True, text=True)
    assert done.returncode == 2 and "usage:" in done.stderr
