"""A run stores the content hash of the learned weights it acted with, and a resumed sweep
refuses stored runs of a policy whose checkpoint changed since (retrained or replaced): they
would otherwise stand for weights they never ran."""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import pytest
import torch

from commands.cli import main

STEM = "ia2c__catchup-v1__n3__s0"


def _train(out: Path, steps: int) -> Path:
    assert main(["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--vehicles", "3",
                 "--steps", str(steps), "--episodes-parallel", "2", "--out", str(out)]) == 0
    return out / f"{STEM}.pt"


@pytest.fixture(scope="module")
def policies(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two checkpoints of one name with other weights (300 and 600 training steps)."""
    root = tmp_path_factory.mktemp("policies")
    return _train(root / "a", 300), _train(root / "b", 600)


def _sweep(folder: Path, out: Path, *extra: str) -> int:
    return main(["run", "--controllers", f"ia2c:checkpoint_dir={folder},cacc,safe:ia2c:"
                 f"checkpoint_dir={folder}", "--scenarios", "catchup-v1", "--vehicles", "3",
                 "--episodes", "2", "--quiet", "--out", str(out), *extra])


def _stored(out: Path) -> dict[str, str]:
    with sqlite3.connect(out / "store.sqlite") as conn:
        rows = conn.execute("SELECT id, record FROM runs ORDER BY id").fetchall()
    return {i: json.loads(r)["policy_sha256"] for i, r in rows}


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_each_run_stores_the_hash_of_the_weights_it_acted_with(policies, tmp_path) -> None:
    """The hash is the checkpoint's own ``sha256`` field (read here with torch), for the policy
    and behind the safety filter; a controller without learned weights stores none."""
    a, b = policies
    want_a, want_b = (torch.load(p, weights_only=True)["sha256"] for p in (a, b))
    assert want_a != want_b and len(want_a) == 64
    assert _sweep(a.parent, tmp_path / "r") == 0
    got = _stored(tmp_path / "r")
    assert len(got) == 6
    assert {h for i, h in got.items() if i.startswith("cacc|")} == {""}
    assert {h for i, h in got.items() if not i.startswith("cacc|")} == {want_a}


def test_resume_refuses_the_runs_of_a_changed_policy(policies, tmp_path, capsys) -> None:
    """Replacing the checkpoint is refused on --resume (exit 2, the store and CSVs untouched);
    the folder moved aside, the command evaluates the new weights; the checkpoint put back, the
    moved folder resumes."""
    a, b = policies
    folder = tmp_path / "ckpt"
    shutil.copytree(a.parent, folder)
    out = tmp_path / "r"
    assert _sweep(folder, out) == 0
    files = {p.name: _digest(p) for p in out.iterdir() if p.suffix in (".sqlite", ".csv")}
    shutil.copy(b, folder / a.name)  # retrained elsewhere, copied over
    capsys.readouterr()
    assert _sweep(folder, out, "--resume") == 2
    err = capsys.readouterr().err
    old, new = (torch.load(p, weights_only=True)["sha256"][:12] for p in (a, b))
    assert "holds 4 runs of learned policies whose checkpoints changed since they ran" in err
    assert f"on catchup-v1, N = 3: weights {old} then, {new} now, and 1 more setting" in err
    assert f"{out.resolve()} holds" in err and "Traceback" not in err
    assert "move that folder aside and run the command again with --resume" in err
    assert {p.name: _digest(p) for p in out.iterdir() if p.suffix in (".sqlite", ".csv")} == files
    out.rename(tmp_path / "aside")  # the remedy the message names
    assert _sweep(folder, out, "--resume") == 0
    fresh = set(_stored(out).values())
    assert fresh == {"", torch.load(b, weights_only=True)["sha256"]}
    shutil.copy(a, folder / a.name)  # the other remedy: the checkpoint put back
    assert _sweep(folder, tmp_path / "aside", "--resume") == 0


def test_runs_stored_before_the_hash_cannot_be_checked(policies, tmp_path) -> None:
    """A record without ``policy_sha256`` (stored by an earlier version) is resumed as it is."""
    a, b = policies
    folder = tmp_path / "ckpt"
    shutil.copytree(a.parent, folder)
    out = tmp_path / "r"
    assert _sweep(folder, out) == 0
    with sqlite3.connect(out / "store.sqlite") as conn:
        for run_id, text in conn.execute("SELECT id, record FROM runs").fetchall():
            rec = json.loads(text)
            del rec["policy_sha256"]
            conn.execute("UPDATE runs SET record = ? WHERE id = ?", (json.dumps(rec), run_id))
    shutil.copy(b, folder / a.name)
    assert _sweep(folder, out, "--resume") == 0
