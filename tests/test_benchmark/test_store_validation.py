"""Store records are validated when read: an altered record, or another program's SQLite file,
is refused with exit 2 naming the row, and nothing beside it is rewritten."""

from __future__ import annotations

import contextlib
import hashlib
import json
import re
import shutil
import sqlite3
from pathlib import Path

import pytest

from benchmark.export import RUN_COLUMNS
from benchmark.record_schema import RunRecord, record_problem
from commands.cli import main as cli

SWEEP = ["--controllers", "ovm,cacc", "--scenarios", "catchup-v1", "--vehicles", "2",
         "--episodes", "2", "--quiet"]
RUN_ID = "cacc|catchup-v1|n2|d0.0|l0.0|tau0.0|s2000"


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("finished")
    assert cli(["run", *SWEEP, "--out", str(out)]) == 0
    return out


def _files(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.iterdir()) if p.is_file() and p.name != "store.lock"}


def _tamper(finished: Path, tmp_path: Path, field: str, raw: str) -> Path:
    """A copy of ``finished`` whose record ``RUN_ID`` has ``field`` set to the JSON text ``raw``
    (written as text, so ``NaN``, ``Infinity`` and ``1e999`` reach the store as they are)."""
    out = tmp_path / "tampered"
    shutil.copytree(finished, out)
    with sqlite3.connect(out / "store.sqlite") as conn:
        if field == "row status":
            conn.execute("UPDATE runs SET status = ? WHERE id = ?", (raw, RUN_ID))
        else:
            text = conn.execute("SELECT record FROM runs WHERE id = ?", (RUN_ID,)).fetchone()[0]
            new, n = re.subn(rf'"{field}": ("(?:[^"\\]|\\.)*"|[^,}}]*)', f'"{field}": {raw}', text)
            assert n == 1
            conn.execute("UPDATE runs SET record = ? WHERE id = ?", (new, RUN_ID))
    return out


CASES = [
    ("reward", "NaN", "reward: Input should be a finite number"),
    ("reward", '"abc"', "reward: Input should be a valid number"),
    ("reward", "1e999", "reward: Input should be a finite number"),
    # a finite number no mean or interval survives (issue 53: an empty interval)
    ("reward", "1e308", "reward: Input should be less than or equal to 1000000000000"),
    ("gap_rmse_m", "1e13", "gap_rmse_m: Input should be less than or equal to 1000000000000"),
    ("energy_kwh", "Infinity", "energy_kwh: Input should be a finite number"),
    ("energy_kwh", "-Infinity", "energy_kwh: Input should be a finite number"),
    ("reward", "null", "needs reward"),
    ("collision", '"no"', "collision: Input should be a valid boolean"),
    ("collision", "0", "collision: Input should be a valid boolean"),
    ("steps", "600.5", "steps: Input should be a valid integer"),
    ("status", '"weird"', "status: Input should be 'ok' or 'failed'"),
    ("row status", "failed", "its status 'ok' is not its row's 'failed'"),
    ("controller", '"ovm"', "its key (controller, scenario, N, settings, seed) reads 'ovm|"),
    ("seed", "2010", "reads 'cacc|catchup-v1|n2|d0.0|l0.0|tau0.0|s2010'"),
    ("scenario", '"slowdown-v1"', "reads 'cacc|slowdown-v1|"),
    ("n_vehicles", "3", "reads 'cacc|catchup-v1|n3|"),
    ("comm_delay_s", "0.1", "reads 'cacc|catchup-v1|n2|d0.1|"),
    ("packet_loss", "1.5", "packet_loss: Input should be less than or equal to 1"),
    ("gap_std_m", "-1.0", "gap_std_m: Input should be greater than or equal to 0"),
    ("options", '"[1]"', "options must be a JSON object"),
    ("policy_sha256", '"abc"', "policy_sha256: String should match pattern"),
]


@pytest.mark.parametrize("field, raw, says", CASES, ids=[f"{c[0]}={c[1]}" for c in CASES])
@pytest.mark.parametrize("command", ["leaderboard", "plot", "resume"])
def test_an_altered_record_is_refused_and_nothing_rewritten(
        finished: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], field: str,
        raw: str, says: str, command: str) -> None:
    out = _tamper(finished, tmp_path, field, raw)
    before = _files(out)
    argv = {"leaderboard": ["leaderboard", str(out)],
            "plot": ["plot", str(out), "--no-energy-map"],
            "resume": ["run", *SWEEP, "--out", str(out), "--resume"]}[command]
    assert cli(argv) == 2
    err = capsys.readouterr().err
    assert f"the stored record of run {RUN_ID!r} is invalid" in err and says in err, err
    assert "DELETE FROM runs WHERE id" in err and "--resume" in err
    assert "Traceback" not in err
    assert _files(out) == before  # runs.csv, leaderboard.csv and the store byte-identical
    assert not (out / "figures").exists()


def test_a_record_deleted_as_the_message_says_is_rerun(finished: Path, tmp_path: Path) -> None:
    """The remedy the message names works: delete the row, resume, the CSVs are whole again."""
    out = _tamper(finished, tmp_path, "collision", '"no"')
    with sqlite3.connect(out / "store.sqlite") as conn:
        conn.execute("DELETE FROM runs WHERE id = ?", (RUN_ID,))
    assert cli(["run", *SWEEP, "--out", str(out), "--resume"]) == 0
    import pandas as pd

    from benchmark.metrics import TIMING_COLUMNS

    def table(folder: Path) -> pd.DataFrame:
        return pd.read_csv(folder / "runs.csv").drop(columns=list(TIMING_COLUMNS))

    pd.testing.assert_frame_equal(table(out), table(finished))


@pytest.mark.parametrize("command", ["leaderboard", "plot", "resume", "run"])
def test_another_programs_sqlite_file_is_refused_and_never_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    out = tmp_path / "theirs"
    out.mkdir()
    with sqlite3.connect(out / "store.sqlite") as conn:
        conn.execute("CREATE TABLE users (name TEXT)")
        conn.execute("INSERT INTO users VALUES ('alice')")
    conn.close()
    before = (out / "store.sqlite").read_bytes()
    argv = {"leaderboard": ["leaderboard", str(out)], "plot": ["plot", str(out)],
            "resume": ["run", *SWEEP, "--out", str(out), "--resume"],
            "run": ["run", *SWEEP, "--out", str(out)]}[command]
    assert cli(argv) == 2
    err = capsys.readouterr().err
    assert "not a cacc-bench results store" in err and "(users)" in err
    assert (out / "store.sqlite").read_bytes() == before
    assert not (out / "runs.csv").exists()


def test_a_store_with_an_extra_table_is_refused(finished: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "extra"
    shutil.copytree(finished, out)
    with sqlite3.connect(out / "store.sqlite") as conn:
        conn.execute("CREATE TABLE notes (x)")
    conn.close()
    assert cli(["leaderboard", str(out)]) == 2
    assert "(meta, notes, runs, trajectories)" in capsys.readouterr().err


def test_a_damaged_trajectory_is_refused_by_plot(finished: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "traj"
    shutil.copytree(finished, out)
    with sqlite3.connect(out / "store.sqlite") as conn:
        conn.execute("UPDATE trajectories SET data = x'504b0304deadbeef' WHERE id = ?",
                     (RUN_ID,))
    conn.close()
    assert cli(["plot", str(out), "--no-energy-map"]) == 2
    err = capsys.readouterr().err
    assert f"the stored trajectory of run {RUN_ID!r} is unreadable" in err


def test_a_corrupt_store_is_refused_in_one_line(finished: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 53: SQLite's integrity check reports a damaged page in several lines (9 in the
    probe); the refusal is one line naming the first problem."""
    out = tmp_path / "corrupt"
    shutil.copytree(finished, out)
    store = out / "store.sqlite"
    whole = store.read_bytes()

    def lines_of_the_check(page: int) -> int:
        """Zero one page's header; the lines SQLite's own check then prints (0: unreadable)."""
        store.write_bytes(whole[:page * 4096] + bytes(12) + whole[page * 4096 + 12:])
        try:
            with contextlib.closing(sqlite3.connect(store)) as conn:
                return len("\n".join(r[0] for r in conn.execute("PRAGMA quick_check"))
                           .splitlines())
        except sqlite3.DatabaseError:
            return 0

    assert any(lines_of_the_check(page) > 2 for page in range(2, len(whole) // 4096))
    before = _files(out)
    assert cli(["leaderboard", str(out)]) == 2
    err = capsys.readouterr().err
    assert "is not a readable results store (integrity check: " in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert _files(out) == before


def test_every_column_of_runs_csv_is_declared() -> None:
    """runs.csv reads only declared fields (``controller_name`` is the record's ``name``)."""
    declared = set(RunRecord.model_fields) | {"controller_name"}
    assert set(RUN_COLUMNS) <= declared


def test_records_of_finished_and_failed_runs_are_valid(finished: Path) -> None:
    with sqlite3.connect(finished / "store.sqlite") as conn:
        rows = conn.execute("SELECT id, status, record FROM runs").fetchall()
    conn.close()
    assert len(rows) == 4
    for run_id, status, text in rows:
        assert record_problem(run_id, status, json.loads(text)) is None
    rec = json.loads(rows[0][2])
    metrics = {"steps", "collision", "reward", "energy_kwh", "string_gain", "string_stable"}
    failed = {k: v for k, v in rec.items() if k not in metrics}
    failed.update(status="failed", error="ValueError: boom", traceback="...")
    assert record_problem(rows[0][0], "failed", failed) is None
    # an ok run without its metrics is not a finished run
    assert "needs steps" in str(record_problem(rows[0][0], "ok", {**failed, "status": "ok"}))
