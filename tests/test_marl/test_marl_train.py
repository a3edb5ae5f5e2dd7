"""The learners: tiny runs of every algorithm, on-policy consistency, bit accounting."""

from __future__ import annotations

import math

import pytest
import torch
from run_marks import FULL

from marl.a2c import Trainer
from marl.config import algorithm
from marl.learners import PAPER_ALGORITHMS
from marl.quantize import qsgd_bits, ternary_bits
from marl.selection import run_training


@pytest.mark.parametrize("algo", PAPER_ALGORITHMS)
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

    def spy(group, record):
        if len(seen) == 5:
            raise _Stop
        out = orig(group, record)
        want = torch.stack([act["logits"] for _, act in record], 1)  # agent-major (N, T, B, 4)
        seen.append(float((out[0].detach() - want).abs().max()))
        return out

    monkeypatch.setattr(tr, "_recompute", spy)
    monkeypatch.setattr(tr, "_rmsprop", lambda group: None)  # weights fixed: exact
    if algo == "bdc":
        monkeypatch.setattr(tr.algo, "after_step", lambda run, net: None)
    with pytest.raises(_Stop):
        tr.run_batch()
    assert len(seen) == 5 and max(seen) < 1e-5


def _run_updates(tr: Trainer, k: int, monkeypatch) -> None:
    """Run a batch but stop after ``k`` updates."""
    orig = tr._recompute

    def limited(group, record):
        if tr.runs[0].updates == k:
            raise _Stop
        return orig(group, record)

    monkeypatch.setattr(tr, "_recompute", limited)
    with pytest.raises(_Stop):
        tr.run_batch()


def test_bdc_counts_bits(monkeypatch) -> None:
    a = algorithm("bdc")
    tr = Trainer(a, a.config_cls(episodes_parallel=2, n_step=10), "catchup-v1", 3, 0)
    _run_updates(tr, 3, monkeypatch)
    run = tr.runs[0]
    assert run.updates == 3
    lstm = tr.net.critic_lstm  # type: ignore[union-attr]
    n_shared = sum(p[0].numel() for p in lstm.parameters())
    assert run.bits["consensus"] == pytest.approx(run.updates * ternary_bits(n_shared))
    bucket = run.config.qsgd_bucket  # type: ignore[attr-defined]
    per_update = sum(qsgd_bits(p[0].numel(), 1, bucket=bucket) for p in tr.net.critic_parameters())
    assert run.bits["qsgd_local"] == pytest.approx(run.updates * per_update)


def test_consensus_pulls_critics_together(monkeypatch) -> None:
    a = algorithm("wac")
    tr = Trainer(a, a.config_cls(episodes_parallel=2, n_step=10), "catchup-v1", 4, 0)
    w = tr.net.critic_lstm.weight_hh  # type: ignore[union-attr]
    spread0 = float(w.detach().std(0).mean())
    _run_updates(tr, 3, monkeypatch)
    assert float(w.detach().std(0).mean()) < 0.5 * spread0


@pytest.mark.slow
def test_ia2c_learns_catchup(tmp_path) -> None:
    """70k steps of IA2C on catchup-v1 (default config), seeds 0, 1 and 2 as one population: in
    the median run the training reward rises by more than 250 (mean of the last five batches
    against the first three) and the kept snapshot, chosen on sampled validation, collides in
    at most a third of the 32 validation episodes, where the untrained policy collides in
    nearly all, and scores better by more than 200 (measured: kept snapshots with 13, 0 and 6
    collisions, -706, -565 and -755, against 32 of 32 at -1,315 untrained). The median of three
    seeds, because one seed's run changes with the last bit of the gradients (12 seeds of this
    test: 0 to 13 collisions, median 0). 70k steps is early: the shipped 6e5-step IA2C is
    collision-free on catchup-v1."""
    from benchmark.policy_eval import evaluate_policy, validation_evaluator
    from envs.params import VALIDATION_SEEDS
    from marl.checkpoint import load_checkpoint
    from marl.selection import run_population

    a = algorithm("ia2c")
    results = run_population(a, [a.config_cls()] * 3, "catchup-v1", 8, 70_000, [0, 1, 2],
                             tmp_path, evaluate=validation_evaluator("ia2c", "catchup-v1", 8))
    untrained = a.build_net(a.config_cls(), 8, False, torch.Generator().manual_seed(0))
    base = evaluate_policy("ia2c", untrained, "catchup-v1", 8, VALIDATION_SEEDS)
    assert base["collisions"] >= 30
    rises, collisions, rewards = [], [], []
    for res in results:
        train = [r["train_reward"] for r in res.curve]
        rises.append(sum(train[-5:]) / 5 - sum(train[:3]) / 3)
        assert res.checkpoint is not None
        best = load_checkpoint(res.checkpoint)
        net = a.build_net(a.config_cls(), 8, False)
        net.load_state_dict(best["weights"])
        ev = evaluate_policy("ia2c", net, "catchup-v1", 8, VALIDATION_SEEDS)
        assert best["curve_summary"]["selected_eval_reward_sampled"] == pytest.approx(ev["reward"])
        collisions.append(ev["collisions"])
        rewards.append(ev["reward"])
    assert sorted(rises)[1] > 250
    assert sorted(collisions)[1] <= base["collisions"] / 3
    assert sorted(rewards)[1] > base["reward"] + 200


# ---------------------------------------------------------------- learner departures
def test_published_reward_alpha_per_scenario() -> None:
    """reward_alpha None resolves to the published configs' coop_gamma: IA2C and FPrint 1 on
    catchup and 0 on slowdown, DIAL/CommNet 1 on both, the consensus family WAC/DCEA/BDC 0 on
    both; an explicit value is kept."""
    for name in ("wac", "dcea", "bdc"):
        cfg = algorithm(name).config_cls()
        for sc in ("catchup-v1", "slowdown-v1", "sine-v1"):
            assert cfg.resolved(sc).reward_alpha == 0.0, (name, sc)
    for name in ("ia2c", "fprint"):
        cfg = algorithm(name).config_cls()
        assert cfg.reward_alpha is None
        assert cfg.resolved("catchup-v1").reward_alpha == 1.0
        assert cfg.resolved("slowdown-v1").reward_alpha == 0.0
        assert cfg.resolved("slowdown-v2").reward_alpha == 0.0
        assert cfg.resolved("sine-v1").reward_alpha == 1.0
    for name in ("dial", "commnet"):
        cfg = algorithm(name).config_cls()
        assert cfg.resolved("slowdown-v1").reward_alpha == 1.0
    cfg = algorithm("ia2c").config_cls(reward_alpha=0.5)
    assert cfg.resolved("slowdown-v1").reward_alpha == 0.5
    tr = Trainer(algorithm("ia2c"), algorithm("ia2c").config_cls(), "slowdown-v1", 3, 0)
    assert tr.runs[0].config.reward_alpha == 0.0  # what the checkpoint records


def test_entropy_schedule() -> None:
    cfg = algorithm("ia2c").config_cls(entropy_coef=0.05, entropy_coef_final=0.01)
    assert cfg.entropy_at(0.0) == pytest.approx(0.05)
    assert cfg.entropy_at(0.5) == pytest.approx(0.03)
    assert cfg.entropy_at(2.0) == pytest.approx(0.01)
    assert algorithm("ia2c").config_cls(entropy_coef_final=None).entropy_at(0.7) == 0.05


def test_bad_learner_options() -> None:
    from infra.errors import ConfigError

    cls = algorithm("ia2c").config_cls
    for bad in (
        {"collision_value": "free"},
        {"entropy_coef_final": -1.0},
        {"reward_alpha": 2.0},
        {"actor_lr": 0.0},
        {"lr_scale": -1.0},
        {"selection_mode": "best"},
        {"reward_w_power": 10.0},
        {"power_baseline_kw": float("inf")},
    ):
        with pytest.raises(ConfigError):
            cls(**bad)


def test_absorbing_collision_value() -> None:
    """The collided state's value is the penalty at every remaining scheduled step, discounted
    (checked against a plain sum); 0 under the published rule."""
    a = algorithm("ia2c")
    tr = Trainer(a, a.config_cls(), "slowdown-v1", 3, 0)
    want = sum(-1000.0 * 0.99**k for k in range(540))
    assert tr.runs[0].absorbing_value(540) == pytest.approx(want, rel=1e-9)
    assert tr.runs[0].absorbing_value(0) == 0.0
    pub = Trainer(a, a.config_cls(collision_value="published"), "slowdown-v1", 3, 0)
    assert pub.runs[0].absorbing_value(540) == 0.0


def test_absorbing_value_enters_only_collision_ends(monkeypatch) -> None:
    """In a real batch (random policy on slowdown-v1 collides), the absorbing value is added at
    exactly the steps where an episode ended by collision before its scheduled end."""
    import numpy as np

    a = algorithm("ia2c")
    tr = Trainer(a, a.config_cls(episodes_parallel=4), "slowdown-v1", 8, 0)
    seen = []
    orig = tr._update

    def spy(group, record, segs, nxt):
        seen.append((np.stack(segs[0].terms), np.stack(segs[0].absorbed)))
        return orig(group, record, segs, nxt)

    monkeypatch.setattr(tr, "_update", spy)
    tr.run_batch()
    terms = np.concatenate([t for t, _ in seen])
    absorbed = np.concatenate([x for _, x in seen])
    assert (absorbed != 0).any(), "seed 0's random policy collides on slowdown-v1"
    assert ((absorbed != 0) <= terms).all()
    ends = np.argwhere(absorbed != 0)
    for t_idx, _ in ends:
        remaining = 600 - (t_idx + 1)
        assert remaining % 60 == 0  # published rule: a collision ends at a 60-step boundary
    assert np.allclose(absorbed[absorbed != 0], [tr.runs[0].absorbing_value(600 - t - 1) for t, _ in ends])


def test_return_scale_matches_a_loop() -> None:
    """The running return std merged over segments equals the std of all returns computed by a
    plain loop (episodes reset at terminals, masked steps left out)."""
    import numpy as np

    a = algorithm("ia2c")
    tr = Trainer(a, a.config_cls(), "catchup-v1", 3, 0)
    gen = torch.Generator().manual_seed(1)
    tr.runs[0].return_acc = torch.zeros(2, 3)
    all_rets = []
    acc = np.zeros((2, 3))
    for _ in range(3):
        r = torch.randn(5, 2, 3, generator=gen)
        term = torch.zeros(5, 2, dtype=torch.bool)
        term[2, 0] = True
        mask = torch.ones(5, 2, 1)
        scale = tr.runs[0].return_scale(r, term, mask)
        for t in range(5):
            acc = acc * 0.99 + r[t].numpy()
            all_rets.append(acc.copy())
            acc[0] *= 0.0 if t == 2 else 1.0
    assert float(scale) == pytest.approx(np.std(np.stack(all_rets)), rel=1e-5)


def test_normalise_advantages_per_agent_over_running_entries() -> None:
    """Each agent's advantages get mean 0 and standard deviation 1 over the masked entries,
    computed here by a plain loop; masked-out entries do not enter the statistics."""
    import numpy as np

    from marl.a2c import normalise_advantages

    gen = torch.Generator().manual_seed(0)
    adv = torch.randn(5, 3, 4, generator=gen, dtype=torch.float64) * 7 + 2
    mask = torch.ones(5, 3, 1, dtype=torch.float64)
    mask[3:, 1] = 0.0  # episode 1 ended after 3 steps
    out = normalise_advantages(adv, mask)
    for agent in range(4):
        vals = np.array([adv[t, b, agent].item() for t in range(5) for b in range(3) if mask[t, b, 0]])
        got = np.array([out[t, b, agent].item() for t in range(5) for b in range(3) if mask[t, b, 0]])
        np.testing.assert_allclose(got, (vals - vals.mean()) / (vals.std() + 1e-8), rtol=1e-9)


def test_diverged_weights_stop_training_with_a_clear_error(monkeypatch) -> None:
    """A NaN weight after an update raises TrainingDivergedError (a CLI error with exit 2),
    naming the tensor, instead of training on with a NaN policy."""
    from infra.errors import TrainingDivergedError

    a = algorithm("bdc")
    orig = a.after_step

    def poison(run, net):
        orig(run, net)
        with torch.no_grad():
            net.critic_lstm.weight_ih[run.rows][0, 0, 0] = float("nan")

    monkeypatch.setattr(a, "after_step", poison)
    with pytest.raises(TrainingDivergedError, match="critic_lstm.weight_ih"):
        run_training(a, a.config_cls(episodes_parallel=2), "catchup-v1", 3, 1000, 0, None)


# ---------------------------------------------------------------- reward as configuration
def test_reward_override_changes_training_reward_not_the_score() -> None:
    """Training-reward weights and the power baseline change what the learner sees, never the
    benchmark's score of the same weights."""
    from benchmark.policy_eval import evaluate_policy
    from envs.params import RewardWeights

    a = algorithm("ia2c")
    paper = Trainer(a, a.config_cls(), "catchup-v1", 3, 0)
    shaped = Trainer(a, a.config_cls(reward_w_power=0.0, reward_w_gap=-2.0), "catchup-v1", 3, 0)
    cruise = Trainer(a, a.config_cls(power_baseline_kw=None), "catchup-v1", 3, 0)
    assert paper.runs[0].env.weights == RewardWeights()
    assert shaped.runs[0].env.weights.power == 0.0 and shaped.runs[0].env.weights.gap == -2.0
    # P(15 m/s, 0) of the fitted model, resolved and recorded in the config: within 3 % of the
    # map model's cruise power there
    from envs.energy import battery_power_kw, map_battery_power_kw

    p0 = cruise.runs[0].config.power_baseline_kw
    assert p0 == round(float(battery_power_kw(15.0, 0.0)), 6)
    assert p0 == pytest.approx(float(map_battery_power_kw(15.0, 0.0)), rel=0.03)
    [(_, r_paper)] = paper.run_batch()
    [(_, r_shaped)] = shaped.run_batch()
    [(_, r_cruise)] = cruise.run_batch()
    # same seed, same weights at the start: the first batches differ only by the reward
    assert r_shaped != pytest.approx(r_paper, rel=1e-3)
    assert r_cruise > r_paper + 3 * 4.0  # at least 4 kW x 10 x 3 agents less cost per step
    net = a.build_net(a.config_cls(), 3, False, torch.Generator().manual_seed(0))
    seeds = [1, 2]
    score = evaluate_policy("ia2c", net, "catchup-v1", 3, seeds, "greedy")
    # the evaluator takes no config: the benchmark scores with the paper's weights whatever
    # the learner was trained on; the env's default weights are the paper's
    assert score == evaluate_policy("ia2c", net, "catchup-v1", 3, seeds, "greedy")
    from envs.platoon import PlatoonEnv

    assert PlatoonEnv("catchup-v1", 3).weights == RewardWeights()


def test_selection_prefers_later_snapshot_on_tie_and_saves_final(tmp_path) -> None:
    """With identical validation scores every evaluation replaces the kept snapshot (a tie goes
    to the later one); the final weights are saved too, and the curve has both modes."""
    import pandas as pd

    from marl.checkpoint import load_checkpoint

    a = algorithm("ia2c")
    calls = []

    def constant(net, mode):
        calls.append(mode)
        return {"reward": -500.0, "collisions": 0.0, "tracking_reward": -50.0}

    cfg = a.config_cls(episodes_parallel=2, n_step=20, eval_every_steps=1000)
    res = run_training(a, cfg, "catchup-v1", 3, 3000, 0, tmp_path, evaluate=constant)
    kept = load_checkpoint(res.checkpoint)
    final = load_checkpoint(res.final_checkpoint)
    assert kept["steps"] == final["steps"] == res.steps
    assert kept["curve_summary"]["selected_at_steps"] == res.steps
    assert set(calls) == {"sampled", "greedy"}
    curve = pd.read_csv(res.curve_csv)
    assert {"eval_reward_sampled", "eval_reward_greedy", "eval_collisions_sampled",
            "eval_collisions_greedy"} <= set(curve.columns)

    scores = iter([-400.0, -450.0, -450.0, -450.0, -450.0, -450.0])

    def falling(net, mode):
        r = next(scores) if mode == "sampled" else -1.0
        return {"reward": r, "collisions": 0.0, "tracking_reward": 0.0}

    res2 = run_training(a, cfg, "catchup-v1", 3, 3000, 0, tmp_path / "b", evaluate=falling)
    kept2 = load_checkpoint(res2.checkpoint)
    first_eval = int(curve["steps"][curve["eval_reward_sampled"].notna()].iloc[0])
    assert kept2["curve_summary"]["selected_at_steps"] == first_eval < res2.steps
    assert kept2["curve_summary"]["selected_eval_reward_sampled"] == -400.0


@pytest.mark.parametrize(("sequence", "kept_index"), [
    # (reward, collisions) of the selection mode at each evaluation -> which one is kept
    ([(-400.0, 1.0), (-900.0, 0.0), (-950.0, 0.0)], 1),   # fewer collisions beat a better reward
    ([(-900.0, 0.0), (-400.0, 1.0), (-800.0, 0.0)], 2),   # then the better reward among them
    ([(-500.0, 2.0), (-500.0, 2.0), (-600.0, 3.0)], 1),   # a tie goes to the later snapshot
    ([(-500.0, 0.0), (-499.0, 0.0), (-500.0, 0.0)], 1),   # strictly worse never replaces
])
def test_selection_rule_on_stubbed_scores(tmp_path, sequence, kept_index) -> None:
    """Fewest collisions first, then the best reward, a tie to the later snapshot; the greedy
    scores (the other mode) never decide."""
    from marl.checkpoint import load_checkpoint

    a = algorithm("ia2c")
    scores = iter(sequence)

    def stub(net, mode):
        if mode == "greedy":  # the other mode, made tempting: it must not matter
            return {"reward": 0.0, "collisions": 0.0, "tracking_reward": 0.0}
        r, c = next(scores)
        return {"reward": r, "collisions": c, "tracking_reward": 0.0}

    cfg = a.config_cls(episodes_parallel=2, n_step=20, eval_every_steps=1000)
    res = run_training(a, cfg, "catchup-v1", 3, 3600, 0, tmp_path, evaluate=stub)
    import pandas as pd

    curve = pd.read_csv(res.curve_csv)
    evals = curve[curve["eval_reward_sampled"].notna()]
    assert len(evals) == len(sequence)
    kept = load_checkpoint(res.checkpoint)["curve_summary"]
    assert kept["selected_at_steps"] == int(evals["steps"].iloc[kept_index])
    assert (kept["selected_eval_reward_sampled"], kept["selected_eval_collisions_sampled"]) == \
        sequence[kept_index]


def test_run_training_needs_an_evaluator_to_select(tmp_path) -> None:
    from infra.errors import ConfigError

    a = algorithm("ia2c")
    with pytest.raises(ConfigError, match="validation evaluator"):
        run_training(a, a.config_cls(), "catchup-v1", 3, 100, 0, tmp_path)


def test_qsgd_is_counted_as_local_not_sent(tmp_path) -> None:
    """BDC's QSGD-compressed gradients are applied by the agent that computed them: their
    payload is reported as local, and the bits sent are the consensus messages alone."""
    a = algorithm("bdc")
    res = run_training(a, a.config_cls(episodes_parallel=2, n_step=20), "catchup-v1", 3, 200, 0,
                       None)
    assert res.bits["local_qsgd_payload_bits_per_agent"] > 0
    assert "training_qsgd_bits_per_agent" not in res.bits
    tr = Trainer(a, a.config_cls(episodes_parallel=2, n_step=20), "catchup-v1", 3, 0)
    tr.run_batch()
    shared = tr.net.shared_critic_parameters()
    per_round = ternary_bits(sum(p[0].numel() for p in shared))
    assert tr.runs[0].bits["consensus"] == pytest.approx(per_round * tr.runs[0].updates)


def test_training_messages_per_algorithm() -> None:
    """Per agent and step in training: the execution messages, the 2-bit action for the
    neighbours' critics, and for DIAL/CommNet the message gradients back to both neighbours."""
    from marl.networks import training_step_bits_per_agent

    want = {"ia2c": 160 + 2, "fprint": 288 + 2, "dial": 2208 + 2 + 4096,
            "commnet": 2208 + 2 + 4096, "wac": 162, "dcea": 162, "bdc": 162}
    for name, bits in want.items():
        a = algorithm(name)
        net = a.build_net(a.config_cls(), 3, True)
        assert training_step_bits_per_agent(net) == bits, name
        if name in ("wac", "dcea", "bdc"):  # the README's consensus payloads
            shared = sum(p[0].numel() for p in net.shared_critic_parameters())
            assert shared == 33_024


@FULL
def test_a_short_training_learns() -> None:
    """3e4 steps of IA2C on catchup-v1 (N = 8), seeds 0, 1 and 2 as one population: the untrained
    policies collide in every one of 16 validation episodes (sampled); trained, together they
    collide in at most half of the 48 and score better by more than 300 on average (measured:
    15, 0 and 6 collisions, rewards -1,177, -753 and -625 from about -1,360: a mean gain of 510;
    with the policy-gradient sign flipped 0, 13 and 16 collisions and a mean gain of 99). One
    seed alone is too noisy to judge a learner by at this budget: seed 0 collided 3 times under
    the plain power polynomial, 7 times after a 1-ulp change in gradient clipping, 15 under the
    limited-regeneration fit, and 0 with the sign flipped. A learner whose update does nothing,
    or pushes the wrong way, fails this in about 20 s."""
    from benchmark.policy_eval import evaluate_policy
    from marl.selection import acting_net

    a = algorithm("ia2c")
    seeds = [0, 1, 2]
    trainer = Trainer(a, a.config_cls(), "catchup-v1", 8, seeds)
    for run in trainer.runs:
        run.total_steps = 30_000
    episodes = list(range(1, 17))
    before = [evaluate_policy("ia2c", acting_net(trainer, r), "catchup-v1", 8, episodes, "sampled")
              for r in trainer.runs]
    while any(r.steps < 30_000 for r in trainer.runs):
        trainer.run_batch()
    after = [evaluate_policy("ia2c", acting_net(trainer, r), "catchup-v1", 8, episodes, "sampled")
             for r in trainer.runs]
    assert all(b["collisions"] == 16 for b in before)
    assert sum(x["collisions"] for x in after) <= 24
    gain = sum(x["reward"] - b["reward"] for x, b in zip(after, before, strict=True)) / 3
    assert gain > 300


def test_a_separate_critic_is_skipped_while_acting() -> None:
    """Training acts without a separate critic (WAC, DCEA, BDC): the same logits and actor
    state, the critic's state passed through untouched; the update recomputes the critic (the
    pinned BDC training did not change when this was introduced)."""
    a = algorithm("bdc")
    net = a.build_net(a.config_cls(), 3, True, torch.Generator().manual_seed(0))
    assert net.separate_critic and not algorithm("ia2c").build_net(
        algorithm("ia2c").config_cls(), 3, True).separate_critic
    state = net.initial_state(2)
    state = {k: torch.randn(v.shape, generator=torch.Generator().manual_seed(1)) for k, v in state.items()}
    obs = torch.randn(3, 2, 15, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        full = net.act_step(obs, state, None, None)
        lazy = net.act_step(obs, state, None, None, critic=False)
    assert torch.equal(full[0], lazy[0])
    assert torch.equal(full[2]["h"], lazy[2]["h"]) and torch.equal(full[2]["c"], lazy[2]["c"])
    assert lazy[2]["ch"] is state["ch"] and lazy[2]["cc"] is state["cc"]
    assert "v" not in lazy[1]
