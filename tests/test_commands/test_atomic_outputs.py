"""Nothing finished is overwritten or misread (issue 32, item 1): outputs are written atomically
and only when their run finishes, checkpoints carry a content hash that loading verifies, and
every command that writes a folder takes the folder's lock."""

from __future__ import annotations

import errno
import hashlib
from pathlib import Path
from typing import Any

import pytest
import torch

from benchmark.folder_lock import folder_lock
from commands.cli import main as cli
from infra import atomic
from infra.errors import ConfigError
from marl.checkpoint import (
    FORMAT_VERSION,
    content_hash,
    load_checkpoint,
    save_checkpoint,
    write_payload,
)

SHIPPED = Path(__file__).resolve().parents[2] / "controllers" / "checkpoints"
STEM = "bdc__catchup-v1__n2__s0"
TRAIN = ["train", "--algo", "bdc", "--scenario", "catchup-v1", "--vehicles", "2",
         "--steps", "1500", "--set", "eval_every_steps=720"]


def _digests(folder: Path) -> dict[str, str]:
    """Every file's digest (the lock file, empty and left by design, aside)."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.iterdir()) if p.is_file() and p.name != "store.lock"}


def _no_temporaries(folder: Path) -> None:
    assert not [p.name for p in folder.rglob("*.tmp")]


# ------------------------------------------------------------------------- atomic writes
def test_a_failed_write_leaves_the_old_file_and_no_temporary(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "a.txt"
    atomic.write_text(target, "old")

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    with pytest.raises(OSError, match="No space"):
        atomic.write_text(target, "new" * 1000)
    with pytest.raises(OSError, match="No space"):
        atomic.write_with(target, lambda tmp: tmp.write_text("new"))
    assert target.read_text() == "old"
    _no_temporaries(tmp_path)


def test_staged_files_are_renamed_together_or_not_at_all(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    atomic.write_text(a, "a0")
    atomic.write_text(b, "b0")
    with pytest.raises(RuntimeError), atomic.StagedFiles() as staged:
        staged.write_text(a, "a1")
        staged.write_text(b, "b1")
        raise RuntimeError("interrupted before the commit")
    assert (a.read_text(), b.read_text()) == ("a0", "b0")
    _no_temporaries(tmp_path)
    with atomic.StagedFiles() as staged:
        staged.write_text(a, "a1")
        staged.write_text(b, "b1")
        staged.commit()
    assert (a.read_text(), b.read_text()) == ("a1", "b1")
    assert oct(a.stat().st_mode & 0o777) != oct(0o600)  # a plain file's mode, not mkstemp's
    _no_temporaries(tmp_path)


# ------------------------------------------------------------------------- checkpoints
@pytest.fixture
def checkpoint(tmp_path: Path) -> Path:
    """A real, finished bdc checkpoint (copied from the shipped N = 2 one, saved as format 2)."""
    data = load_checkpoint(SHIPPED / f"{STEM}.pt")
    return save_checkpoint(tmp_path / f"{STEM}.pt", algo="bdc", config=data["config"],
                           scenario="catchup-v1", n_vehicles=2, seed=0, steps=data["steps"],
                           curve_summary=data["curve_summary"], weights=data["weights"])


def test_a_checkpoint_carries_its_content_hash_and_the_weights_round_trip(
        checkpoint: Path) -> None:
    raw = torch.load(checkpoint, weights_only=True)
    assert raw["format_version"] == FORMAT_VERSION == 2
    assert raw["sha256"] == content_hash(raw)
    shipped = load_checkpoint(SHIPPED / f"{STEM}.pt")
    again = load_checkpoint(checkpoint, algo="bdc", n_vehicles=2)
    for key, value in shipped["weights"].items():
        assert torch.equal(value, again["weights"][key]), key  # bit for bit


def _flip(path: Path, offset: int, n: int = 200) -> None:
    blob = bytearray(path.read_bytes())
    for i in range(offset, min(offset + n, len(blob))):
        blob[i] ^= 0xFF
    path.write_bytes(bytes(blob))


@pytest.mark.parametrize("damage", ["flip-weights", "flip-start", "truncate", "empty",
                                    "directory"])
def test_a_damaged_checkpoint_is_refused_with_what_to_do(checkpoint: Path, damage: str) -> None:
    size = checkpoint.stat().st_size
    if damage == "flip-weights":
        _flip(checkpoint, size // 2)
    elif damage == "flip-start":
        _flip(checkpoint, 0)
    elif damage == "truncate":
        checkpoint.write_bytes(checkpoint.read_bytes()[: size // 3])
    elif damage == "empty":
        checkpoint.write_bytes(b"")
    else:
        checkpoint.unlink()
        checkpoint.mkdir()
    with pytest.raises(ConfigError, match=r"cacc-bench train --algo bdc") as err:
        load_checkpoint(checkpoint, algo="bdc", n_vehicles=2)
    assert "\n" not in str(err.value)


def _altered(checkpoint: Path, rehash: bool, change: str) -> Path:
    data = torch.load(checkpoint, weights_only=True)
    if change == "shape":
        data["weights"]["fc.weight"] = data["weights"]["fc.weight"][:, :, :10].clone()
    elif change == "extra-key":
        data["weights"]["bogus"] = torch.zeros(2, 3, dtype=torch.float16)
    elif change == "dtype":
        data["weights"]["fc.weight"] = data["weights"]["fc.weight"].float()
    elif change == "config-type":
        data["config"]["hidden"] = "64"
    elif change == "config-field":
        data["config"]["nonsense"] = 1.0
    elif change == "missing-key":
        data["weights"].pop("fc.bias", None)  # gone already on a second alteration
    elif change == "steps-type":
        data["steps"] = "many"
    if rehash:
        write_payload(checkpoint, data)
    else:
        torch.save(data, checkpoint)
    return checkpoint


@pytest.mark.parametrize("change", ["shape", "extra-key", "dtype", "config-type",
                                    "config-field", "missing-key", "steps-type"])
def test_an_altered_checkpoint_is_refused(checkpoint: Path, change: str) -> None:
    """Altered and saved again: the hash no longer matches. Altered with a new hash (a file
    written wrongly): shapes, dtypes, config types and the set of weights are checked (a
    missing weight was a RuntimeError traceback from ``load_state_dict``)."""
    with pytest.raises(ConfigError, match="damaged or was altered.*content hash"):
        load_checkpoint(_altered(checkpoint, False, change), algo="bdc", n_vehicles=2)
    with pytest.raises(ConfigError, match="damaged or was altered") as err:
        load_checkpoint(_altered(checkpoint, True, change), algo="bdc", n_vehicles=2)
    assert "content hash" not in str(err.value)
    if change == "missing-key":
        assert "weight 'fc.bias' of the bdc network is missing" in str(err.value)


def test_shipped_format_1_files_load_by_their_digest_anywhere(tmp_path: Path) -> None:
    """Format 1 (no hash) is read only for the shipped files, wherever a copy lies; a damaged
    copy or another format-1 file is refused."""
    copy = tmp_path / f"{STEM}.pt"
    copy.write_bytes((SHIPPED / f"{STEM}.pt").read_bytes())
    assert torch.load(copy, weights_only=True)["format_version"] == 1
    assert load_checkpoint(copy, algo="bdc", n_vehicles=2)["steps"] > 0
    _flip(copy, copy.stat().st_size // 2)
    with pytest.raises(ConfigError, match="format version 1.*differs from the shipped.*git checkout"):
        load_checkpoint(copy, algo="bdc", n_vehicles=2)
    other = tmp_path / "other.pt"
    other.write_bytes(copy.read_bytes())
    with pytest.raises(ConfigError, match="format version 1.*not one of the shipped files"):
        load_checkpoint(other, algo="bdc", n_vehicles=2)


def test_every_shipped_checkpoint_is_verified() -> None:
    from marl.shipped_digests import FORMAT_1_SHA256

    paths = sorted(SHIPPED.rglob("*.pt"))
    assert len(paths) >= len(FORMAT_1_SHA256) > 0
    for path in paths:
        load_checkpoint(path)


# ------------------------------------------------------------------------- train
@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with a finished run (.pt, .final.pt, .curve.csv, .log)."""
    out = tmp_path_factory.mktemp("finished")
    assert cli([*TRAIN, "--out", str(out)]) == 0
    return out


def _errors(err: str) -> str:
    """Standard error without ``train --overwrite``'s line (:func:`commands.train.check_finished`)
    and the line saying where it trains into."""
    return "\n".join(ln for ln in err.splitlines()
                     if not ln.startswith(("--overwrite: ", "training 1 run into ")))


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir(parents=True)
    for p in src.glob(f"{STEM}*"):
        (dst / p.name).write_bytes(p.read_bytes())
    return dst


def test_an_interrupted_train_leaves_the_finished_files_byte_identical(
        finished: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The issue's case: Ctrl-C after the first evaluation (which used to write a snapshot
    over the finished .pt, .curve.csv and .log) exits 130 and changes nothing."""
    import commands.train as train_cmd
    from infra.interrupt import Interrupted

    out = _copy(finished, tmp_path / "out")
    before = _digests(out)
    assert {f"{STEM}{s}" for s in (".pt", ".final.pt", ".curve.csv", ".log")} <= set(before)
    seen: list[int] = []

    def interrupt(self: object, steps: int, total: int, row: dict) -> None:
        seen.append(steps)
        if steps > 1000:  # after the evaluation at 720 steps
            raise Interrupted(2)

    monkeypatch.setattr(train_cmd._Bar, "__call__", interrupt)
    assert cli([*TRAIN, "--out", str(out), "--overwrite"]) == 130
    assert max(seen) > 1000
    assert "Traceback" not in capsys.readouterr().err
    assert _digests(out) == before
    _no_temporaries(out)


def test_a_full_disk_at_the_end_leaves_no_truncated_file(
        finished: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    import marl.checkpoint as ckpt

    out = _copy(finished, tmp_path / "out")
    before = _digests(out)
    calls: list[str] = []
    real_save = torch.save

    def full_disk(obj: Any, f: Any, *a: Any, **k: Any) -> None:
        calls.append(str(f))
        real_save(obj, f, *a, **k)  # half written, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device", str(f))

    monkeypatch.setattr(ckpt.torch, "save", full_disk)
    assert cli([*TRAIN, "--out", str(out), "--overwrite"]) == 2
    err = _errors(capsys.readouterr().err)
    assert "No space left on device" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert calls
    assert _digests(out) == before
    _no_temporaries(out)


def _limited_to(limit_bytes: int) -> Any:
    """A ``preexec_fn``: files of the child may not grow past ``limit_bytes`` (RLIMIT_FSIZE;
    SIGXFSZ ignored, so a write past it fails with EFBIG as a full disk fails with ENOSPC):
    a real refused write without root or a small filesystem."""
    def limit() -> None:
        import resource
        import signal

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return limit


@pytest.mark.parametrize("command", ["train", "run"])
def test_a_real_refused_write_ends_with_one_line_and_keeps_finished_files(
        finished: Path, tmp_path: Path, command: str) -> None:
    """Rerun of the full-disk case on a 300 KB tmpfs (issue 32): torch's zip writer raised
    ``RuntimeError: unexpected pos`` (train) and SQLite ``database or disk is full`` (run),
    both as tracebacks with exit 1; now exit 2, one line, the finished files unchanged."""
    import subprocess
    import sys

    if command == "train":
        out, argv, limit = _copy(finished, tmp_path / "out"), [*TRAIN, "--overwrite"], 64_000
    else:
        out = tmp_path / "out"
        argv = ["run", "--controllers", "ovm,cacc", "--scenarios", "catchup-v1", "--vehicles",
                "2", "--episodes", "10", "--executor", "serial", "--quiet"]
        limit = 48_000
    before = _digests(out) if out.exists() else {}
    proc = subprocess.run([sys.executable, "-m", "commands", *argv, "--out", str(out)],
                          capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[2],
                          preexec_fn=_limited_to(limit))
    err = _errors(proc.stderr)
    assert proc.returncode == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert ("File too large" if command == "train" else "results store could not grow") in err
    if command == "train":
        assert _digests(out) == before
    else:  # what was stored is whole and valid
        from benchmark.store import ResultStore

        with ResultStore(out) as store:
            assert all(r["status"] == "ok" for r in store.records())
    _no_temporaries(out)


@pytest.mark.parametrize("damage", ["empty", "truncate", "flip"])
def test_train_resume_refuses_a_damaged_final_checkpoint(
        finished: Path, tmp_path: Path, damage: str, capsys: pytest.CaptureFixture[str]) -> None:
    out = _copy(finished, tmp_path / "out")
    final = out / f"{STEM}.final.pt"
    blob = final.read_bytes()
    if damage == "empty":
        final.write_bytes(b"")
    elif damage == "truncate":
        final.write_bytes(blob[: len(blob) // 2])
    else:
        _flip(final, len(blob) // 2)
    before = _digests(out)
    assert cli([*TRAIN, "--out", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert str(final) in err and "remove" in err
    assert _digests(out) == before


def test_train_resume_skips_a_verified_finished_run(
        finished: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _copy(finished, tmp_path / "out")
    before = _digests(out)
    assert cli([*TRAIN, "--out", str(out), "--resume"]) == 0
    assert "1 of 1 runs already finished" in capsys.readouterr().err
    assert _digests(out) == before


# ------------------------------------------------------------------------- locks
LOCKED = {
    "train": TRAIN,
    "tune": ["tune", "--algos", "bdc", "--scenarios", "catchup-v1", "--trials", "1",
             "--steps", "10"],
    "reproduce": ["reproduce", "--budget", "quick", "--algos", "bdc", "--scenarios",
                  "catchup-v1"],
    "sensitivity": ["sensitivity", "--scenarios", "catchup-v1", "--knobs", "v2v",
                    "--steps", "10"],
    "pareto": ["pareto", "--scenarios", "catchup-v1", "--episodes", "1"],
    "stability": ["stability", "--controllers", "cacc"],
}


@pytest.mark.parametrize("command", sorted(LOCKED))
def test_a_second_writer_of_a_folder_is_refused_naming_the_first(
        command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    with folder_lock(out):
        before = _digests(out)
        assert cli([*LOCKED[command], "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1
        assert f"{out} is being written by pid" in err
        assert _digests(out) == before
    assert not (out / "store.owner").exists()


def test_a_lock_that_is_a_folder_is_refused(tmp_path: Path) -> None:
    (tmp_path / "store.lock").mkdir()
    with pytest.raises(ConfigError, match="store.lock is not a file"), folder_lock(tmp_path):
        pass


def test_an_unwritable_folder_is_refused_before_the_lock(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from filelock import FileLock

    def denied(self: object, *a: object, **k: object) -> None:
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(FileLock, "acquire", denied)
    with pytest.raises(ConfigError, match="cannot lock this folder.*Permission denied"), \
            folder_lock(tmp_path / "x"):
        pass


def test_sigint_after_an_evaluation_leaves_the_finished_files_byte_identical(
        finished: Path, tmp_path: Path) -> None:
    """The issue's case as a user meets it: a real SIGINT to `cacc-bench train` once its first
    evaluation is logged (when the old code had written a snapshot over the finished files)."""
    import signal
    import subprocess
    import sys
    import time

    out = _copy(finished, tmp_path / "out")
    before = _digests(out)
    argv = [*TRAIN[:-4], "--steps", "60000", "--set", "eval_every_steps=720", "--overwrite"]
    proc = subprocess.Popen([sys.executable, "-m", "commands", *argv, "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[2])
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            logs = list(out.glob(f".{STEM}.log.*.tmp"))
            if logs and "[kept]" in logs[0].read_text():
                break
            time.sleep(0.2)
        else:
            pytest.fail("no evaluation was logged")
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert _digests(out) == before
    _no_temporaries(out)


def test_a_trusted_format_1_file_can_be_given_its_hash(tmp_path: Path) -> None:
    """A run trained before checkpoints were hashed is refused, naming the upgrade; the
    upgrade keeps every tensor bit for bit and the file then loads."""
    import subprocess
    import sys

    shipped = torch.load(SHIPPED / f"{STEM}.pt", weights_only=True)
    old = tmp_path / "mine.pt"
    torch.save({**shipped, "steps": shipped["steps"] + 1}, old)  # not a shipped file
    with pytest.raises(ConfigError, match=r"python -m marl\.checkpoint"):
        load_checkpoint(old)
    proc = subprocess.run([sys.executable, "-m", "marl.checkpoint", str(old)], text=True,
                          capture_output=True, cwd=Path(__file__).resolve().parents[2])
    assert proc.returncode == 0 and "upgraded to format 2" in proc.stdout, proc.stderr
    new = torch.load(old, weights_only=True)
    assert new["format_version"] == 2 and new["steps"] == shipped["steps"] + 1
    for key, value in shipped["weights"].items():
        assert torch.equal(value, new["weights"][key]) and value.dtype == new["weights"][key].dtype
    load_checkpoint(old, algo="bdc", n_vehicles=2)


def test_a_figure_that_fails_to_save_leaves_the_earlier_one(tmp_path: Path) -> None:
    """Figures go through a temporary file too (:func:`analysis.plots.savefig_atomic`)."""
    from analysis.plots import _plt, savefig_atomic

    plt = _plt()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    path = tmp_path / "f.png"
    savefig_atomic(fig, path, dpi=50)
    before = path.read_bytes()
    assert before.startswith(b"\x89PNG")

    class Broken(Exception):
        pass

    def fail(*args: object, **kwargs: object) -> None:
        raise Broken

    fig.savefig = fail  # type: ignore[method-assign]
    with pytest.raises(Broken):
        savefig_atomic(fig, path)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["f.png"]
    plt.close(fig)
