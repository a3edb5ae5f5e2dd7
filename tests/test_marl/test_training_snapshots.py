"""Resumable training: a run interrupted after a snapshot and resumed ends with the weights,
kept snapshot and learning curve of the same run uninterrupted (bit for bit), in every family
(the paper's learners, the shared PPO learners, the distiller); a snapshot is removed when its
run finishes, and a damaged one, or one of another run, is refused with one line."""

from __future__ import annotations

import hashlib
import signal
from pathlib import Path

import pytest
import torch
from run_marks import FULL

import marl.checkpoint
from commands.cli import main
from marl.checkpoint import Snapshots
from marl.learners import PPO_LEARNERS

#: Tiny trainings of both command families: several validations, snapshots mid-episode (PPO)
#: and between batches (the paper's learners).
RUNS = {
    "ippo": ["--algo", "ippo", "--steps", "1600", "--set", "n_envs=4", "--set",
             "rollout_steps=50", "--set", "minibatch_rows=128", "--set", "eval_every_steps=400"],
    "bdc": ["--algo", "bdc", "--steps", "4800", "--episodes-parallel", "2", "--set",
            "eval_every_steps=1200"],
}


def _train(out: Path, algo: str, *extra: str) -> int:
    return main(["train", *RUNS[algo], "--scenario", "catchup-v1", "--vehicles", "3",
                 "--out", str(out), *extra])


def _digests(folder: Path) -> dict[str, str]:
    """Each checkpoint's weights and each curve file, hashed (timings left out)."""
    out = {}
    for p in sorted(folder.iterdir()):
        if p.suffix == ".pt":
            w = torch.load(p, weights_only=True)["weights"]
            out[p.name] = hashlib.sha256(b"".join(
                k.encode() + w[k].numpy().tobytes() for k in sorted(w))).hexdigest()
        elif p.name.endswith(".curve.csv"):
            out[p.name] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


class _Stop(Exception):
    pass


def _interrupt_after(monkeypatch: pytest.MonkeyPatch, writes: int, how: str = "signal") -> None:
    """A snapshot at every boundary; the ``writes``-th write is followed by a SIGINT (the
    command's handler raises it as an interrupt) or by ``_Stop`` (a direct call)."""
    monkeypatch.setattr(marl.checkpoint, "SNAPSHOT_EVERY_S", 0.0)
    original = Snapshots.write
    count = {"n": 0}

    def write(self: Snapshots, steps: int, state: dict) -> None:
        original(self, steps, state)
        count["n"] += 1
        if count["n"] == writes:
            if how == "signal":
                signal.raise_signal(signal.SIGINT)
            raise _Stop

    monkeypatch.setattr(Snapshots, "write", write)


@pytest.mark.parametrize("algo", ["ippo", "bdc"])
def test_train_interrupted_and_resumed_gives_the_weights_of_an_uninterrupted_run(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys, algo: str) -> None:
    assert _train(tmp_path / "whole", algo) == 0
    assert "training 1 run into" in capsys.readouterr().err  # where it writes, said at start
    with monkeypatch.context() as m:
        _interrupt_after(m, 2)
        assert _train(tmp_path / "cut", algo) == 128 + signal.SIGINT
    err = capsys.readouterr().err
    assert "--resume" in err and "Traceback" not in err
    stem = f"{algo}__catchup-v1__n3__s0"
    snapshot = tmp_path / "cut" / f"{stem}.snapshot.pt"
    assert snapshot.exists() and not (tmp_path / "cut" / f"{stem}.pt").exists()
    # without --resume the interrupted run is neither lost nor continued: refused, one line
    assert _train(tmp_path / "cut", algo) == 2
    err = capsys.readouterr().err
    assert "snapshot of an interrupted run" in err and len(err.strip().splitlines()) == 1
    assert _train(tmp_path / "cut", algo, "--resume") == 0
    err = capsys.readouterr().err
    assert "continues from its snapshot at" in err and "resumed from" in (
        tmp_path / "cut" / f"{stem}.log").read_text()
    assert not snapshot.exists()  # the finished run's files are the product
    whole, cut = _digests(tmp_path / "whole"), _digests(tmp_path / "cut")
    assert whole == cut and len(whole) == (3 if algo == "bdc" else 2)


def test_a_snapshot_of_another_config_or_a_damaged_one_is_refused(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    with monkeypatch.context() as m:
        _interrupt_after(m, 1)
        assert _train(tmp_path, "bdc") == 128 + signal.SIGINT
    capsys.readouterr()
    snapshot = tmp_path / "bdc__catchup-v1__n3__s0.snapshot.pt"
    assert _train(tmp_path, "bdc", "--resume", "--set", "gamma=0.9") == 2
    err = capsys.readouterr().err
    assert "another run (config fields gamma differ)" in err and "Traceback" not in err
    assert _train(tmp_path, "bdc", "--resume", "--steps", "6000") == 2
    assert "budget_steps differ" in capsys.readouterr().err
    blob = bytearray(snapshot.read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    snapshot.write_bytes(bytes(blob))
    assert _train(tmp_path, "bdc", "--resume") == 2
    err = capsys.readouterr().err
    assert "is damaged" in err and "remove it" in err and len(err.strip().splitlines()) == 1
    assert snapshot.exists()  # refused, never removed behind the user's back
    assert _train(tmp_path, "bdc", "--overwrite") == 0  # from the start: the snapshot goes
    assert "removed the snapshots of 1 interrupted run" in capsys.readouterr().err
    assert not snapshot.exists() and (tmp_path / "bdc__catchup-v1__n3__s0.final.pt").exists()


@FULL
@pytest.mark.parametrize("options", [
    *({"algo": name} for name in PPO_LEARNERS),  # every one in the registry, with its own state
    {"algo": "mappo", "vehicles_min": 2, "vehicles_max": 5, "packet_loss_max": 0.3},  # drawn
    {"algo": "ippo", "cav_share_min": 0.5, "cav_share_max": 0.9},  # human seats drawn
], ids=lambda o: "-".join(map(str, o.values())))
def test_every_shared_learner_resumes_bit_for_bit(options: dict, tmp_path: Path) -> None:
    """Interrupted after 7 updates (mid-episode: the batch in flight is stepped again)."""
    from envs.scenarios import make_scenario
    from marl.learners import LEARNERS, load
    from marl.training import config_class

    cfg = config_class(options["algo"])(n_envs=4, rollout_steps=50, minibatch_rows=128,
                                        eval_every_steps=400, **options)
    trainer_cls = load(f"{LEARNERS[cfg.algo].module}:TRAINER")

    def score(actor: torch.nn.Module, mode: str) -> dict[str, float]:
        with torch.no_grad():
            x = torch.linspace(-1, 1, 5 * 3 * 12).reshape(5, 3, 12)
            return {"reward": float(actor(x).sum()), "collisions": 0.0}

    def state(trainer: object) -> dict[str, torch.Tensor]:
        return {f"{m}.{k}": v.clone() for m in ("actor", "critic")
                for k, v in [*getattr(trainer, m).named_parameters(),
                             *getattr(trainer, m).named_buffers()]}

    sc = make_scenario("catchup-v1")
    whole = trainer_cls(sc, 3, 0, 3000, cfg)
    res = whole.train(score)
    snapshots = Snapshots(tmp_path / "run.snapshot.pt", {"run": 1}, every_s=0)
    stopping = Snapshots(snapshots.path, {"run": 1}, every_s=0)
    count = {"n": 0}
    write = stopping.write

    def write_then_stop(steps: int, s: dict) -> None:
        write(steps, s)
        count["n"] += 1
        if count["n"] == 7:
            raise _Stop

    stopping.write = write_then_stop  # type: ignore[method-assign]
    with pytest.raises(_Stop):
        trainer_cls(sc, 3, 0, 3000, cfg).train(score, None, stopping)
    assert 0 < (snapshots.steps() or 0) < 3000
    resumed = trainer_cls(sc, 3, 0, 3000, cfg)
    again = resumed.train(score, None, snapshots)
    a, b = state(whole), state(resumed)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert again.curve == res.curve and again.best == res.best and again.steps == res.steps
    assert all(torch.equal(v, again.actor.state_dict()[k])
               for k, v in res.actor.state_dict().items())


@FULL
def test_a_population_resumes_each_run_from_its_own_snapshot(tmp_path: Path) -> None:
    """Three runs in one stack, cut when the first wrote its second snapshot (the others at
    other points of their batches): each continues from its own, and every file is the
    uninterrupted population's."""
    from marl.config import algorithm
    from marl.selection import run_population

    algo = algorithm("bdc")
    cfg = algo.config_cls(episodes_parallel=2, eval_every_steps=1200)

    def score(net: torch.nn.Module, mode: str) -> dict[str, float]:
        s = sum(float(p.double().sum()) for p in net.parameters())
        return {"reward": s, "collisions": 0.0, "tracking_reward": s}

    def snaps(folder: Path, stop: bool) -> list[Snapshots]:
        out = [Snapshots(folder / f"s{s}.snapshot.pt", {"seed": s}, every_s=0)
               for s in (0, 1, 2)]
        if stop:
            write, count = out[0].write, {"n": 0}

            def write_then_stop(steps: int, state: dict) -> None:
                write(steps, state)
                count["n"] += 1
                if count["n"] == 2:
                    raise _Stop

            out[0].write = write_then_stop  # type: ignore[method-assign]
        return out

    run_population(algo, [cfg] * 3, "catchup-v1", 3, 4000, [0, 1, 2], tmp_path / "a",
                   evaluate=score)
    with pytest.raises(_Stop):
        run_population(algo, [cfg] * 3, "catchup-v1", 3, 4000, [0, 1, 2], tmp_path / "b",
                       evaluate=score, snapshots=snaps(tmp_path / "b", True))
    assert len(list((tmp_path / "b").glob("*.snapshot.pt"))) == 3
    run_population(algo, [cfg] * 3, "catchup-v1", 3, 4000, [0, 1, 2], tmp_path / "b",
                   evaluate=score, snapshots=snaps(tmp_path / "b", False))
    assert not list((tmp_path / "b").glob("*.snapshot.pt"))
    assert _digests(tmp_path / "a") == _digests(tmp_path / "b") != {}


@FULL
def test_distill_resumes_after_a_round(tmp_path: Path) -> None:
    from commands.train import model_expert
    from marl.distill import DistillConfig, distill

    cfg = DistillConfig(expert="cacc", rounds=3, episodes_per_round=2, grad_steps=100)

    def score(actor: torch.nn.Module, mode: str) -> dict[str, float]:
        with torch.no_grad():
            return {"reward": float(actor(torch.ones(2, 12)).sum()), "collisions": 0.0}

    whole = distill("catchup-v1", model_expert("cacc"), 3, 0, cfg, evaluate=score)
    path = tmp_path / "d.snapshot.pt"
    stopping = Snapshots(path, {"d": 1}, every_s=0)
    write = stopping.write

    def write_then_stop(steps: int, state: dict) -> None:
        write(steps, state)
        raise _Stop

    stopping.write = write_then_stop  # type: ignore[method-assign]
    with pytest.raises(_Stop):
        distill("catchup-v1", model_expert("cacc"), 3, 0, cfg, evaluate=score,
                snapshots=stopping)
    again = distill("catchup-v1", model_expert("cacc"), 3, 0, cfg, evaluate=score,
                    snapshots=Snapshots(path, {"d": 1}, every_s=0))
    assert again.curve == whole.curve and again.best == whole.best
    assert all(torch.equal(v, again.actor.state_dict()[k])
               for k, v in whole.actor.state_dict().items())


def test_plain_state_keeps_an_objects_tensors_and_its_generator_by_place() -> None:
    """A learner's own state (what ``setup`` made) goes through plain data and back: tensors,
    numbers, tuples, arrays, an object filled in place, the trainer's generator by identity;
    anything else is refused rather than silently lost."""
    import numpy as np

    from marl.checkpoint import plain_state, restore_state
    from marl.quantize import ErrorFeedbackQSGD

    gen = torch.Generator().manual_seed(0)
    q = ErrorFeedbackQSGD(2, gen, 4)
    q.compress([torch.randn(3, 5, generator=gen)])
    state = {"qsgd": q, "bits": {"consensus": 3.5}, "pair": (1, 2.0), "a": np.arange(3)}
    plain = plain_state(state, (gen,))
    other = torch.Generator()
    fresh = {"qsgd": ErrorFeedbackQSGD(2, other, 4), "bits": {}, "pair": (0, 0.0), "a": None}
    back = restore_state(fresh, plain, (other,))
    assert back["qsgd"] is fresh["qsgd"] and back["qsgd"].generator is other
    assert torch.equal(back["qsgd"].residual[0], q.residual[0])
    assert back["bits"] == {"consensus": 3.5} and back["pair"] == (1, 2.0)
    assert (back["a"] == np.arange(3)).all()
    with pytest.raises(TypeError):
        plain_state({"g": torch.Generator()}, (gen,))
    with pytest.raises(TypeError):
        plain_state({"f": print})


@FULL
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_training_process_stopped_by_a_signal_or_killed_resumes(tmp_path: Path, sig: int
                                                                  ) -> None:
    """The command in its own process (snapshots at every boundary), stopped by SIGTERM or
    killed once its snapshot exists: ``--resume`` ends with the uninterrupted run's files."""
    import subprocess
    import sys
    import time

    root = Path(__file__).resolve().parents[2]
    start = ("import sys, marl.checkpoint as c; c.SNAPSHOT_EVERY_S = 0.0; "
             "from commands.cli import main; sys.exit(main())")
    argv = ["train", *RUNS["bdc"], "--steps", "9600", "--scenario", "catchup-v1",
            "--vehicles", "3", "--out", str(tmp_path / "cut")]
    proc = subprocess.Popen([sys.executable, "-c", start, *argv], cwd=root, text=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    snapshot = tmp_path / "cut" / "bdc__catchup-v1__n3__s0.snapshot.pt"
    deadline = time.monotonic() + 240
    while not snapshot.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before its first snapshot"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == (-sig if sig == signal.SIGKILL else 128 + sig), err
    if sig != signal.SIGKILL:
        assert "keep their last snapshot (continue with --resume)" in err, err
    assert snapshot.exists() and not snapshot.with_name("bdc__catchup-v1__n3__s0.pt").exists()
    resumed = subprocess.run([sys.executable, "-c", start, *argv, "--resume"], cwd=root,
                             text=True, capture_output=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert "continues from its snapshot" in resumed.stderr
    assert main(["train", *RUNS["bdc"], "--steps", "9600", "--scenario", "catchup-v1",
                 "--vehicles", "3", "--out", str(tmp_path / "whole")]) == 0
    assert _digests(tmp_path / "whole") == _digests(tmp_path / "cut") != {}
