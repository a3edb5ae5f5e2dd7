"""The training device (``--device``): everything a trainer computes with lives on it, the
environments, random streams and checkpoints stay on the CPU, and the CPU path is unchanged."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch
from run_marks import representative

from commands.cli import main as cli
from envs.dynamics import OBS_DIM
from infra.errors import ConfigError
from marl.a2c import Trainer
from marl.config import algorithm, training_device
from marl.learners import PAPER_ALGORITHMS
from marl.selection import acting_net

N, SCENARIO = 3, "catchup-v1"
NO_GPU = not torch.cuda.is_available()


def _tiny(name: str):
    a = algorithm(name)
    return a, a.config_cls(episodes_parallel=4, n_step=7)


def _trained(name: str, seeds: list[int], device: str = "cpu") -> Trainer:
    a, cfg = _tiny(name)
    tr = Trainer(a, cfg, SCENARIO, N, seeds, device=device)
    for r in tr.runs:
        r.total_steps = 5000
    tr.run_batch()
    return tr


@pytest.fixture
def default_device_meta() -> Iterator[None]:
    """Tensors made without a device land on ``meta``, where mixing them with the CPU tensors
    of training fails: a stand-in for a second device on a machine without one."""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


@pytest.mark.parametrize("name", representative(PAPER_ALGORITHMS, {"bdc"}))
def test_training_places_every_tensor_explicitly(name: str, default_device_meta: None) -> None:
    """A population of two trains a batch with the default device elsewhere: every tensor the
    trainer, the networks, the losses, consensus and QSGD make names its device (a GPU run
    would otherwise mix devices), and the numbers are those of the plain CPU run."""
    tr = _trained(name, [0, 1])
    assert all(p.device.type == "cpu" for p in tr.net.parameters())
    torch.set_default_device(None)
    plain = _trained(name, [0, 1])
    for (key, p), q in zip(tr.net.named_parameters(), plain.net.parameters(), strict=True):
        assert torch.equal(p, q), key


def test_device_names() -> None:
    assert training_device("cpu") == torch.device("cpu")
    for bad in ("tpu", "cuda:x", "mps", "meta", ""):
        with pytest.raises(ConfigError, match="--device"):
            training_device(bad)


@pytest.mark.skipif(not NO_GPU, reason="this machine has a CUDA GPU")
def test_a_missing_gpu_is_refused_before_any_work(tmp_path, capsys) -> None:
    with pytest.raises(ConfigError, match="sees no CUDA GPU"):
        training_device("cuda")
    out = tmp_path / "out"
    code = cli(["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--steps", "10",
                "--device", "cuda", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "sees no CUDA GPU" in err and "Traceback" not in err
    assert not list(tmp_path.rglob("*.pt"))


@pytest.mark.skipif(NO_GPU, reason="needs a CUDA GPU")
@pytest.mark.parametrize("name", ["ia2c", "bdc", "dial"])
def test_a_gpu_population_starts_as_on_the_cpu_and_trains(name: str) -> None:
    """On a GPU the initial weights are the CPU's (built there from the same streams), one
    acting step's logits match the CPU's to float32 rounding, and a batch trains to finite
    weights whose acting network (what a checkpoint stores) is on the CPU. (Later weights are
    not compared: the kernels round differently and one flipped sampled action changes the
    episode.)"""
    a, cfg = _tiny(name)
    gpu = Trainer(a, cfg, SCENARIO, N, [0, 1], device="cuda")
    cpu = Trainer(a, cfg, SCENARIO, N, [0, 1])
    assert all(p.device.type == "cuda" for p in gpu.net.parameters())
    for (key, p), q in zip(gpu.net.named_parameters(), cpu.net.parameters(), strict=True):
        assert torch.equal(p.cpu(), q), key
    obs = torch.randn(2 * N, cfg.episodes_parallel, OBS_DIM,
                      generator=torch.Generator().manual_seed(1))
    state = cpu.net.initial_state(cfg.episodes_parallel)
    on_gpu = gpu._act(obs.cuda(), {k: v.cuda() for k, v in state.items()}, gpu.runs)
    on_cpu = cpu._act(obs, state, cpu.runs)
    torch.testing.assert_close(on_gpu["logits"].cpu(), on_cpu["logits"], rtol=1e-5, atol=1e-6)
    for r in gpu.runs:
        r.total_steps = 5000
    gpu.run_batch()
    assert all(bool(torch.isfinite(p).all()) for p in gpu.net.parameters())
    assert all(p.device.type == "cpu" for p in acting_net(gpu, gpu.runs[0]).parameters())


@pytest.mark.skipif(NO_GPU, reason="needs a CUDA GPU")
def test_a_gpu_run_is_deterministic() -> None:
    one, two = _trained("bdc", [3], "cuda"), _trained("bdc", [3], "cuda")
    for (key, p), q in zip(one.net.named_parameters(), two.net.parameters(), strict=True):
        assert torch.equal(p, q), key


def test_the_populations_note_quotes_the_committed_gpu_check() -> None:
    """The GPU table and protocol times of docs/populations.md are those of the committed
    output of docs/scripts/gpu_check.sh (docs/gpu-check/), run on a lent GPU machine."""
    import json
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    note = (root / "docs" / "populations.md").read_text()
    section = note[note.index("## On a GPU"):note.index("## The measurements in brief")]
    rows = json.loads((root / "docs" / "gpu-check" / "throughput.json").read_text())
    rate = {(r["algo"], r["population"], r["device"]): r["env_steps_per_s"] for r in rows}
    for algo in ("ia2c", "bdc"):
        for k in (6, 1):
            line = f"| `{algo}` | {k} | {rate[algo, k, 'cuda']:,} | {rate[algo, k, 'cpu']:,} |"
            assert line in section, line
        gain = rate[algo, 6, "cuda"] / rate[algo, 6, "cpu"]
        assert f"{gain:.1f}x (`{algo}`)" in section
    assert "12 passed, 1 skipped" in (root / "docs" / "gpu-check" / "gpu-tests.log").read_text()
    times = dict(re.findall(r"protocol on (\w+): exit 0, ([\d.]+) s wall",
                            (root / "docs" / "gpu-check" / "protocol.txt").read_text()))
    assert f"{times['cuda']} s with `--device cuda`, {times['cpu']} s on the 16 CPU cores" in section
