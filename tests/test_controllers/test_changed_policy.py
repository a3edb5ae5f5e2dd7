"""A run stores a hash of the learned policy it acted with (its weights, algorithm, N and
config), and a resumed sweep refuses stored runs of a policy that changed since (retrained to
other weights, or replaced): they would otherwise stand for weights they never ran."""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import pytest
import torch

from commands.cli import main
from marl.checkpoint import content_hash, load_checkpoint, policy_id, write_payload

STEM = "ia2c__catchup-v1__n3__s0"


@pytest.fixture(scope="module")
def policies(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A policy and other weights for it (another training seed)."""
    root = tmp_path_factory.mktemp("policies")
    for seed in (0, 1):
        assert main(["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--vehicles", "3",
                     "--steps", "300", "--episodes-parallel", "2", "--seed", str(seed),
                     "--out", str(root / f"s{seed}")]) == 0
    return root / "s0" / f"{STEM}.pt", root / "s1" / "ia2c__catchup-v1__n3__s1.pt"


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


def _id(path: Path) -> str:
    return policy_id(load_checkpoint(path))


def test_each_run_stores_the_hash_of_the_policy_it_acted_with(policies, tmp_path) -> None:
    """The policy's hash, alone and behind the safety filter; none for a controller without
    learned weights; other weights, another hash."""
    a, b = policies
    assert _id(a) != _id(b) and len(_id(a)) == 64
    assert _sweep(a.parent, tmp_path / "r") == 0
    got = _stored(tmp_path / "r")
    assert len(got) == 6
    assert {h for i, h in got.items() if i.startswith("cacc|")} == {""}
    assert {h for i, h in got.items() if not i.startswith("cacc|")} == {_id(a)}


def test_a_policy_retrained_to_the_same_weights_resumes(policies, tmp_path) -> None:
    """Timings and commit are not the policy: a checkpoint that differs only in them (its own
    content hash differs) resumes its stored runs."""
    a, _ = policies
    folder = tmp_path / "ckpt"
    shutil.copytree(a.parent, folder)
    out = tmp_path / "r"
    assert _sweep(folder, out) == 0
    data = torch.load(a, weights_only=True)
    data["curve_summary"] = {**data["curve_summary"], "wall_s": 1.0 + data["curve_summary"]["wall_s"]}
    data["sha256"] = content_hash(data)
    torch.save(data, folder / a.name)
    assert data["sha256"] != torch.load(a, weights_only=True)["sha256"]
    assert _sweep(folder, out, "--resume") == 0


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
    _replace(b, folder / a.name)  # retrained to other weights, under the same seed
    capsys.readouterr()
    assert _sweep(folder, out, "--resume") == 2
    err = capsys.readouterr().err
    old, new = (_id(p)[:12] for p in (a, b))
    assert "holds 4 runs of learned policies that have changed since they ran" in err
    assert f"on catchup-v1, N = 3: policy {old} then, {new} now, and 1 more setting" in err
    assert f"{out.resolve()} holds" in err and "Traceback" not in err
    assert "move that folder aside and run the command again with --resume" in err
    assert {p.name: _digest(p) for p in out.iterdir() if p.suffix in (".sqlite", ".csv")} == files
    out.rename(tmp_path / "aside")  # the remedy the message names
    assert _sweep(folder, out, "--resume") == 0
    fresh = set(_stored(out).values())
    assert fresh == {"", _id(b)}
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
    _replace(b, folder / a.name)
    assert _sweep(folder, out, "--resume") == 0


def _replace(src: Path, dst: Path) -> None:
    """``dst`` retrained to other weights: ``src``'s policy recorded under ``dst``'s seed (a
    copied file keeps its own seed, which loading refuses)."""
    seed = torch.load(dst, weights_only=True)["seed"]
    write_payload(dst, {**torch.load(src, weights_only=True), "seed": seed})
