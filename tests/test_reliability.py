"""Reliability: one writer per results folder, corrupt stores refused, CSVs never shrunk."""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from benchmark.cli import main as cli
from benchmark.store import ResultStore

ROOT = Path(__file__).resolve().parent.parent
SMALL = ["--controllers", "ovm", "--scenarios", "catchup-v1", "--vehicles", "2", "--episodes",
         "2", "--quiet"]


def _sweep(out: Path, *extra: str) -> None:
    assert cli(["run", *SMALL, "--out", str(out), *extra]) == 0


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "benchmark.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("finished")
    _sweep(out)
    return out


def _copy(finished: Path, tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(finished, out)
    return out


def test_a_second_writer_is_refused_naming_the_first(tmp_path: Path) -> None:
    out = tmp_path / "r"
    with ResultStore(out, writer=True):
        res = _cli("run", *SMALL, "--out", str(out), "--resume")
        assert res.returncode == 2
        assert f"is being written by pid {os.getpid()}" in res.stderr
        assert "Traceback" not in res.stderr
        res = _cli("leaderboard", str(out))
        assert res.returncode == 2 and "being written" in res.stderr
    # the lock goes with the writer: the same command now works
    assert _cli("run", *SMALL, "--out", str(out), "--resume").returncode == 0


def test_two_writers_racing_leave_one_consistent_store(tmp_path: Path) -> None:
    out = tmp_path / "race"
    cmd = [sys.executable, "-m", "benchmark.cli", "run", "--controllers", "ovm,acc",
           "--scenarios", "catchup-v1,slowdown-v1", "--vehicles", "3", "--episodes", "4",
           "--out", str(out), "--resume", "--quiet"]
    procs = [subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for _ in range(2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]  # type: ignore[union-attr]
    assert 0 in [rc for rc, _ in results]
    for rc, err in results:
        assert rc in (0, 2) and "Traceback" not in err
        if rc == 2:
            assert "is being written by pid" in err
    with sqlite3.connect(out / "store.sqlite") as conn:
        ids = [r[0] for r in conn.execute("SELECT id FROM runs")]
    assert len(ids) == len(set(ids)) == 16
    assert len(pd.read_csv(out / "runs.csv")) == 16


def test_an_empty_store_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                        ) -> None:
    out = tmp_path / "empty"
    out.mkdir()
    (out / "store.sqlite").write_bytes(b"")
    (out / "runs.csv").write_text("keep me\n")
    for argv in (["leaderboard", str(out)], ["run", *SMALL, "--out", str(out), "--resume"]):
        assert cli(argv) == 2
        assert "is empty (0 bytes)" in capsys.readouterr().err
    assert (out / "runs.csv").read_text() == "keep me\n"


@pytest.mark.parametrize("damage", ["page", "truncate", "header"])
def test_a_damaged_store_is_refused_and_its_csvs_kept(
        finished: Path, tmp_path: Path, damage: str, capsys: pytest.CaptureFixture[str]) -> None:
    out = _copy(finished, tmp_path)
    path = out / "store.sqlite"
    data = bytearray(path.read_bytes())
    assert len(data) >= 3 * 4096, "the store should span several pages"
    if damage == "page":  # garbage over the second page (a b-tree page of the runs)
        data[4096:8192] = bytes((i * 37 + 11) % 256 for i in range(4096))
    elif damage == "truncate":
        data = data[: len(data) // 2 + 100]
    else:
        data[:16] = b"not a database!!"
    path.write_bytes(bytes(data))
    csv_before = (out / "runs.csv").read_bytes()
    assert cli(["leaderboard", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "not a readable results store" in err
    assert (out / "runs.csv").read_bytes() == csv_before


def test_an_unreadable_record_is_named(finished: Path, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    out = _copy(finished, tmp_path)
    with sqlite3.connect(out / "store.sqlite") as conn:
        run_id = conn.execute("SELECT id FROM runs LIMIT 1").fetchone()[0]
        conn.execute("UPDATE runs SET record = '{broken' WHERE id = ?", (run_id,))
    csv_before = (out / "runs.csv").read_bytes()
    assert cli(["leaderboard", str(out)]) == 2
    assert f"run {run_id!r} is unreadable" in capsys.readouterr().err
    assert (out / "runs.csv").read_bytes() == csv_before


def test_csvs_are_never_replaced_by_fewer_rows(finished: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = _copy(finished, tmp_path)
    with sqlite3.connect(out / "store.sqlite") as conn:
        conn.execute("DELETE FROM runs WHERE rowid = (SELECT MIN(rowid) FROM runs)")
    csv_before = (out / "runs.csv").read_bytes()
    assert cli(["leaderboard", str(out)]) == 2
    assert "lists 2 runs but the store beside it holds 1" in capsys.readouterr().err
    assert (out / "runs.csv").read_bytes() == csv_before
