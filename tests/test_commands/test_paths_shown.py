"""Paths as the user can open them: relative to the folder they ran the command from, also
while a command works inside its output folder (``reproduce``, ``sensitivity``); ``plot`` names
every file it writes."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmark.work_folder import shown_path, working_in
from commands.plot import say_written


def test_a_path_is_shown_from_where_the_user_stands(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    assert shown_path("out/runs/runs.csv") == "out/runs/runs.csv"
    with working_in("out"):
        assert shown_path("runs/runs.csv") == "out/runs/runs.csv"  # not relative to --out
    assert shown_path("/elsewhere/x.csv") == "/elsewhere/x.csv"


def test_plot_names_the_files_it_wrote(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    out = Path("r/figures")
    say_written([out / "leaderboard.png", out / "leaderboard.pdf", out / "energy_map.png"], out)
    assert capsys.readouterr().out == ("wrote 3 files into r/figures:\n"
                                       "  leaderboard.{png,pdf}\n  energy_map.png\n")
