"""The learners: tiny runs of every algorithm, on-policy consistency, bit accounting."""

from __future__ import annotations

import math

import pytest
import torch

from marl.common import ALGORITHM_NAMES, Trainer, algorithm, run_training
from marl.quantize import qsgd_bits, ternary_bits


@pytest.mark.parametrize("algo", ALGORITHM_NAMES)
def test_tiny_training_run(algo) -> None:
    a = algorithm(algo)
    cfg = a.config_cls(episodes_parallel=2, n_step=20)
    res = run_training(a, cfg, "catchup-v1", 3, 100, 0, None)
    assert res.steps >= 100 and res.checkpoint is None and res.bits["updates"] >= 1
    assert all(math.isfinite(r["train_reward"]) for r in res.curve)
    assert res.bits["execution_bits_per_agent_step"] == 32 * (
        5 + {"fprint": 4, "dial": 64, "commnet": 64}.get(algo, 0)
    )


class _Stop(Exception):
    pass


@pytest.mark.parametrize("algo", ["ia2c", "fprint", "dial", "bdc"])
def test_recompute_equals_rollout(algo, monkeypatch) -> None:
    """The training recompute reproduces the acting logits: the LSTM state advanced exactly once
    per observation, including across n-step boundaries."""
    a = algorithm(algo)
    tr = Trainer(a, a.config_cls(episodes_parallel=2, n_step=7), "catchup-v1", 3, 0)
    seen = []
    orig = tr._recompute

    def spy(seg_state, record):
        if len(seen) == 5:
            raise _Stop
        logits, values, actions = orig(seg_state, record)
        want = torch.stack([r["logits"] for r in record])
        seen.append(float((logits.detach() - want).abs().max()))
        return logits, values, actions

    monkeypatch.setattr(tr, "_recompute", spy)
    tr.optimizer.param_groups[0]["lr"] = 0.0  # keep weights fixed: exact comparison
    tr.optimizer.param_groups[1]["lr"] = 0.0
    if algo == "bdc":
        monkeypatch.setattr(tr.algo, "after_step", lambda trainer: None)
    with pytest.raises(_Stop):
        tr.run_batch()
    assert len(seen) == 5 and max(seen) < 1e-5


def _run_updates(tr: Trainer, k: int, monkeypatch) -> None:
    """Run a batch but stop after ``k`` updates."""
    orig = tr._recompute

    def limited(seg_state, record):
        if tr.updates == k:
            raise _Stop
        return orig(seg_state, record)

    monkeypatch.setattr(tr, "_recompute", limited)
    with pytest.raises(_Stop):
        tr.run_batch()


def test_bdc_counts_bits(monkeypatch) -> None:
    a = algorithm("bdc")
    tr = Trainer(a, a.config_cls(episodes_parallel=2, n_step=10), "catchup-v1", 3, 0)
    _run_updates(tr, 3, monkeypatch)
    assert tr.updates == 3
    lstm = tr.net.critic_lstm  # type: ignore[union-attr]
    n_shared = sum(p[0].numel() for p in lstm.parameters())
    assert tr.bits["consensus"] == pytest.approx(tr.updates * ternary_bits(n_shared))
    per_update = sum(qsgd_bits(p[0].numel(), 1) for p in tr.net.critic_parameters())
    assert tr.bits["qsgd"] == pytest.approx(tr.updates * per_update)


def test_consensus_pulls_critics_together(monkeypatch) -> None:
    a = algorithm("wac")
    tr = Trainer(a, a.config_cls(episodes_parallel=2, n_step=10), "catchup-v1", 4, 0)
    w = tr.net.critic_lstm.weight_hh  # type: ignore[union-attr]
    spread0 = float(w.detach().std(0).mean())
    _run_updates(tr, 3, monkeypatch)
    assert float(w.detach().std(0).mean()) < 0.5 * spread0


@pytest.mark.slow
def test_ia2c_learns_catchup(tmp_path) -> None:
    """70k steps of IA2C (seed 0) reach a greedy validation reward well above the untrained
    policy's (-950 with collisions) and above OVM's (about -640)."""
    from marl.common import VALIDATION_SEEDS, evaluate_greedy

    a = algorithm("ia2c")
    res = run_training(a, a.config_cls(), "catchup-v1", 8, 70_000, 0, tmp_path)
    best = max(r["eval_reward"] for r in res.curve if not math.isnan(r["eval_reward"]))
    untrained = a.build_net(a.config_cls(), 8, False, torch.Generator().manual_seed(0))
    base = evaluate_greedy(untrained, "catchup-v1", 8, VALIDATION_SEEDS)
    assert best > base["reward"] + 200 and best > -600
