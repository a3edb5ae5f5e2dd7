"""Populations: K runs trained as one stacked network, each exactly as it would train alone."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from run_marks import FULL, representative

from infra.errors import ConfigError, TrainingDivergedError
from marl.a2c import Trainer
from marl.config import algorithm
from marl.learners import PAPER_ALGORITHMS
from marl.selection import run_population, run_training

#: N = 3 on catchup-v1 with B = 2 and 7-step segments: the untrained policies collide, so runs
#: end their batches at different steps and mid-segment (updates of part of the stack)
N, SCENARIO = 3, "catchup-v1"


def _tiny(name: str, **changes: object):
    a = algorithm(name)
    return a, dataclasses.replace(a.config_cls(episodes_parallel=4, n_step=7), **changes)


def _train(tr: Trainer, batches: int) -> None:
    for r in tr.runs:
        r.total_steps = 5000
    for _ in range(batches):
        tr.run_batch()


def _rows(tr: Trainer, k: int) -> dict[str, torch.Tensor]:
    return {n: p[tr.runs[k].rows] for n, p in tr.net.named_parameters()}


def _assert_run_equals_solo(pop: Trainer, k: int, solo: Trainer) -> None:
    mine, alone = _rows(pop, k), dict(solo.net.named_parameters())
    assert mine.keys() == alone.keys()
    for name, p in alone.items():
        assert torch.equal(mine[name], p), f"{name} of run {k} differs from the run alone"
    a, b = pop.runs[k], solo.runs[0]
    assert (a.steps, a.episodes, a.updates, a.bits) == (b.steps, b.episodes, b.updates, b.bits)


@pytest.mark.parametrize("name", representative(PAPER_ALGORITHMS, {"bdc"}))
def test_each_run_of_a_population_trains_exactly_as_alone(name: str) -> None:
    """Weights (critics included), step counts, updates and bit tallies of every run equal a
    separate run of the same seed (a population of one) to the last bit, for every algorithm:
    messages, the critics' neighbour actions, consensus and QSGD stay inside a run, and updates
    of part of the stack round as those of the whole."""
    a, cfg = _tiny(name)
    seeds = [0, 1, 2]
    pop = Trainer(a, cfg, SCENARIO, N, seeds)
    _train(pop, 1)
    for k, seed in enumerate(seeds):
        solo = Trainer(a, cfg, SCENARIO, N, seed)
        _train(solo, 1)
        _assert_run_equals_solo(pop, k, solo)


def test_the_unaligned_case_is_exercised() -> None:
    """The equality above covers runs whose batches end at different steps, mid-segment, so
    that updates of part of the stack happen (otherwise it would only test whole-stack
    updates)."""
    a, cfg = _tiny("ia2c")
    pop = Trainer(a, cfg, SCENARIO, N, [0, 1, 2])
    _train(pop, 1)
    assert len({r.steps for r in pop.runs}) == 3
    assert any(r.steps % cfg.n_step for r in pop.runs)


@FULL
def test_a_population_of_configs_trains_each_as_alone() -> None:
    """Runs may differ in every non-structural field (rates, clip, discount, entropy,
    reward shaping): each trains with its own."""
    a, base = _tiny("bdc")
    configs = [
        base,
        dataclasses.replace(base, actor_lr=1e-3, grad_clip=0.5, gamma=0.95),
        dataclasses.replace(base, entropy_coef=0.2, reward_w_power=0.0, return_norm=True,
                            rmsprop_alpha=0.9, consensus_eps=0.01),
    ]
    pop = Trainer(a, configs, SCENARIO, N, [4, 4 + 1, 4 + 2])
    _train(pop, 1)
    for k, cfg in enumerate(configs):
        solo = Trainer(a, cfg, SCENARIO, N, 4 + k)
        _train(solo, 1)
        _assert_run_equals_solo(pop, k, solo)


def test_runs_of_a_population_must_share_the_structure() -> None:
    a, cfg = _tiny("ia2c")
    with pytest.raises(ConfigError, match="n_step"):
        Trainer(a, [cfg, dataclasses.replace(cfg, n_step=8)], SCENARIO, N, [0, 1])
    with pytest.raises(ConfigError, match="one config per seed"):
        Trainer(a, [cfg, cfg], SCENARIO, N, [0])
    with pytest.raises(ConfigError, match="distinct seeds"):
        run_population(a, [cfg, cfg], SCENARIO, N, 100, [3, 3])


@FULL
def test_population_checkpoints_and_curves_equal_separate_runs(tmp_path) -> None:
    """Through the driver: each run's selected and final checkpoints hold the weights, steps and
    selection of the run trained alone, and its learning curve is the same."""
    import pandas as pd

    from benchmark.policy_eval import validation_evaluator
    from marl.checkpoint import load_checkpoint

    a, cfg = _tiny("dcea", eval_every_steps=1000)
    evaluate = validation_evaluator("dcea", SCENARIO, N, [1, 2])
    pop = run_population(a, [cfg, cfg], SCENARIO, N, 2500, [0, 1], tmp_path / "pop",
                         evaluate=evaluate)
    for k, seed in enumerate([0, 1]):
        solo = run_training(a, cfg, SCENARIO, N, 2500, seed, tmp_path / f"s{seed}",
                            evaluate=evaluate)
        for got, want in ((pop[k].checkpoint, solo.checkpoint),
                          (pop[k].final_checkpoint, solo.final_checkpoint)):
            g, w = load_checkpoint(got), load_checkpoint(want)
            assert g["steps"] == w["steps"] and g["seed"] == w["seed"] == seed
            assert g["curve_summary"]["selected_at_steps"] == w["curve_summary"]["selected_at_steps"]
            for key, tensor in w["weights"].items():
                assert torch.equal(g["weights"][key], tensor), key
        pd.testing.assert_frame_equal(pd.read_csv(pop[k].curve_csv), pd.read_csv(solo.curve_csv))


def test_a_diverged_run_stops_alone_and_the_others_finish(monkeypatch, tmp_path) -> None:
    """A run whose weights become non-finite stops; the other runs finish and save their
    checkpoints (equal to theirs alone), and then the error names the diverged run's seed."""
    a, cfg = _tiny("wac", eval_every_steps=1000)
    orig = a.after_step

    def poison(run, net):
        orig(run, net)
        if run.seed == 7:
            with torch.no_grad():
                net.critic_lstm.weight_ih[run.rows][0, 0, 0] = float("nan")

    def constant(net, mode):
        return {"reward": -1.0, "collisions": 0.0, "tracking_reward": -1.0}

    monkeypatch.setattr(a, "after_step", poison)
    with pytest.raises(TrainingDivergedError, match="seed 7: weights critic_lstm.weight_ih"):
        run_population(a, [cfg, cfg], SCENARIO, N, 1500, [7, 8], tmp_path, evaluate=constant)
    monkeypatch.setattr(a, "after_step", orig)
    assert not list(tmp_path.glob("*__s7.final.pt"))
    survivor = torch.load(next(tmp_path.glob("*__s8.final.pt")), weights_only=True)
    alone = run_training(a, cfg, SCENARIO, N, 1500, 8, tmp_path / "alone", evaluate=constant)
    want = torch.load(alone.final_checkpoint, weights_only=True)
    assert survivor["steps"] == want["steps"]
    for key, tensor in want["weights"].items():
        assert torch.equal(survivor["weights"][key], tensor), key


def test_stacked_weights_are_row_major_even_along_size_one_axes() -> None:
    """A (N, 72, 1) critic head made by ``.contiguous()`` of a transpose kept strides (72, 1, 72)
    and its batched product rounded differently from a row-major copy of some of its agents
    (what an update of part of a population computes on): the layers store row-major weights."""
    from marl.layers import BatchedLinear, BatchedLSTMCell

    head = BatchedLinear(6, 72, 1)
    assert head.weight.stride() == (72, 1, 1)
    cell = BatchedLSTMCell(6, 64, 64)
    assert cell.weight_ih.stride() == (64 * 256, 256, 1)
    x = torch.randn(6, 14, 72, generator=torch.Generator().manual_seed(0))
    whole = head(x)
    idx = torch.tensor([3, 4, 5])
    part = torch.baddbmm(head.bias.index_select(0, idx).unsqueeze(1), x[3:],
                         head.weight.index_select(0, idx))
    assert torch.equal(whole[3:], part)
