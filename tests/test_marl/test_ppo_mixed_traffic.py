"""The shared learner on mixed traffic (marl.ppo with ``scenarios`` and ``cav_share_min``):
each batch draws its road and its automated seats from the run's generator; human seats'
agent-steps enter neither the loss nor the statistics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from infra.errors import CaccBenchError
from marl.ppo import PPOTrainer, train
from marl.ppo_nets import PPOConfig

MIXED = PPOConfig(n_envs=4, rollout_steps=16, epochs=2, minibatch_rows=64,
                  eval_every_steps=10**6, scenarios="catchup-v1,ring-v1", cav_share_min=0.05,
                  vehicles_min=3, vehicles_max=6)


@pytest.mark.parametrize(("fields", "needle"), [
    ({"cav_share_min": 0.0}, "0 < cav_share_min <= cav_share_max <= 1"),
    ({"cav_share_min": 0.6, "cav_share_max": 0.5}, "0 < cav_share_min <= cav_share_max"),
    ({"cav_share_max": 1.5}, "cav_share_max <= 1"),
    ({"scenarios": "catchup-v1,nowhere-v1"}, "nowhere-v1"),
    ({"scenarios": "catchup-v1:cavs=2", "cav_share_min": 0.5}, "sets its automated seats"),
    ({"scenarios": "ring-v1:placement=spread", "cav_share_min": 0.5}, "or their placement"),
    ({"scenarios": "ring-v1,catchup-v1,ring-v1:vehicles=22"}, "names ring-v1 more than once"),
    ({"algo": "ippo-bdc", "scenarios": "catchup-v1"}, "trains at one N"),
    ({"algo": "ippo-bdc", "cav_share_min": 0.5}, "trains at one N"),
])
def test_a_bad_mixed_traffic_config_is_refused(fields: dict, needle: str) -> None:
    with pytest.raises(CaccBenchError, match=needle):
        PPOConfig(**fields)


def test_batches_draw_roads_and_seats() -> None:
    """Over a run the batches meet both roads (the ring at its own 22 vehicles, a string at
    3 to 6 followers) and shares from one vehicle to all, from the run's generator."""
    trainer = PPOTrainer(*_args(MIXED, 40_000))
    seen = []
    for _ in range(40):
        w = trainer.draw_world()
        sc = w.env.scenario
        assert (w.n == 22) if sc.ring else (3 <= w.n <= 6)
        seen.append((sc.ring, w.n, int(w.automated.sum())))
    assert {ring for ring, _, _ in seen} == {False, True}
    assert any(k == 1 for _, _, k in seen) and any(k == n for _, n, k in seen)
    again = PPOTrainer(*_args(MIXED, 40_000))
    assert [(w.env.scenario.ring, w.n, int(w.automated.sum()))
            for w in (again.draw_world() for _ in range(40))] == seen


def test_the_update_learns_only_from_live_automated_agent_steps() -> None:
    cfg = dataclasses.replace(MIXED, scenarios="", vehicles_min=0, vehicles_max=0,
                              cav_share_min=0.5, cav_share_max=0.5)
    trainer = PPOTrainer(*_args(cfg, 10_000))
    auto = trainer.world.automated.numpy()
    assert 0 < auto.sum() < len(auto)
    before = float(trainer.actor.obs_count)
    ro = trainer.collect()
    assert not ro.live[..., ~auto].any() and ro.live[..., auto].all()
    # the observation statistics count the same agent-steps
    assert float(trainer.actor.obs_count) - before == pytest.approx(float(ro.live.sum()), abs=0.5)
    adv, ret = trainer.advantages(ro)
    rows, _ = trainer.rows(ro, adv, ret)
    assert rows[0].shape[0] == int(ro.live.sum())
    trainer.update(ro)
    assert np.isfinite(float(trainer.actor.obs_mean.sum()))


def test_the_same_seed_gives_the_same_mixed_traffic_weights() -> None:
    one, two = (train("catchup-v1", 4, 7, 2048, MIXED).actor for _ in range(2))
    other = train("catchup-v1", 4, 8, 2048, MIXED).actor
    same = [torch.equal(a, b) for a, b in zip(one.state_dict().values(),
                                             two.state_dict().values(), strict=True)]
    assert all(same)
    assert not all(torch.equal(a, b) for a, b in zip(one.state_dict().values(),
                                                     other.state_dict().values(), strict=True))


def test_an_all_automated_share_range_draws_nothing_more() -> None:
    """``cav_share_min = cav_share_max = 1`` is the homogeneous learner, bit for bit."""
    plain = dataclasses.replace(MIXED, scenarios="", cav_share_min=1.0)
    assert not plain.mixed_traffic
    a = train("catchup-v1", 4, 3, 1024, plain).actor
    b = train("catchup-v1", 4, 3, 1024, dataclasses.replace(plain, cav_share_max=1.0)).actor
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(),
                                                 b.state_dict().values(), strict=True))


def _args(cfg: PPOConfig, steps: int) -> tuple:
    from envs.scenarios import make_scenario

    return make_scenario("catchup-v1"), 4, 0, steps, cfg


def test_validation_scores_every_road_with_humans() -> None:
    """On mixed traffic a string is validated at half its followers automated; a ring as it is
    (one automated vehicle) and at half; without humans the roads as they are."""
    from envs.scenarios import make_scenario

    labels = [sc.label for sc in MIXED.validation_roads(make_scenario("slowdown-v1"))]
    assert labels == ["catchup-v1[cav_fraction=0.5]", "ring-v1",
                      "ring-v1[cav_fraction=0.5,placement=random]"]  # the ring's is front
    plain = dataclasses.replace(MIXED, cav_share_min=1.0)
    assert [sc.label for sc in plain.validation_roads(make_scenario("slowdown-v1"))] == [
        "catchup-v1", "ring-v1"]
    alone = dataclasses.replace(plain, scenarios="")
    assert [sc.label for sc in alone.validation_roads(make_scenario("slowdown-v1"))] == [
        "slowdown-v1"]


def test_a_validation_over_roads_pools_them() -> None:
    """The evaluator of several roads: mean reward, summed collisions and episodes; a ring at its
    own vehicle count."""
    from benchmark.policy_eval import evaluate_policy, validation_evaluator
    from envs.scenarios import make_scenario
    from marl.ppo_nets import SharedActor

    torch.manual_seed(0)
    actor = SharedActor(MIXED)
    roads = [make_scenario("catchup-v1", cav_fraction=0.5), make_scenario("ring-v1")]
    both = validation_evaluator("ippo", roads, 4, seeds=(1, 2))(actor, "sampled")
    one = [evaluate_policy("ippo", actor, sc, n, (1, 2)) for sc, n in zip(roads, (4, 22))]
    assert both["reward"] == pytest.approx((one[0]["reward"] + one[1]["reward"]) / 2)
    assert both["collisions"] == one[0]["collisions"] + one[1]["collisions"]
    assert both["episodes"] == 4


SHIPPED = ("controllers", "checkpoints", "variants", "mixed-traffic")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_shipped_mixed_traffic_policies_were_trained_on_the_distribution(seed: int) -> None:
    """Three seeds of ``ippo`` on ``mixed-v2`` and the ring, shares 0.05 to 1 at random
    placements, N 4 to 12 on the strings; each kept snapshot collision-free on its validation
    roads."""
    from pathlib import Path

    from marl.checkpoint import load_checkpoint

    root = Path(__file__).resolve().parents[2]
    data = load_checkpoint(root.joinpath(*SHIPPED, f"ippo__mixed-v2__n8__s{seed}.pt"))
    cfg = data["config"]
    assert (cfg["scenarios"], cfg["cav_share_min"], cfg["cav_share_max"]) == (
        "mixed-v2,ring-v1", 0.05, 1.0)
    assert (cfg["vehicles_min"], cfg["vehicles_max"]) == (4, 12)
    assert data["seed"] == seed and data["curve_summary"]["best_collisions"] == 0
    text = " ".join((root / "docs" / "learned-control.md").read_text().split())
    assert f"({data['curve_summary']['best_reward']:.2f})" in text  # the page quotes the file


@pytest.mark.parametrize(("scenario", "n"), [("ring-v1", 22), ("catchup-v1:cav_fraction=0.25", 8),
                                             ("openacc-s-v1:cavs=1", 4)])
def test_the_shipped_mixed_traffic_policy_drives_any_arrangement(scenario: str, n: int) -> None:
    from benchmark.check import check_controller
    from envs.scenarios import make_scenario

    check_controller("ippo", make_scenario(scenario), n, steps=30, variant="mixed-traffic",
                     scenario="mixed-v2")
