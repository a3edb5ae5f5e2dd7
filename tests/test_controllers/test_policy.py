"""MARL policies as controllers: checkpoint loading, sampled and greedy acting, V2V accounting,
errors."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
import torch
from run_marks import FULL, representative

from benchmark.policy_eval import evaluate_policy
from benchmark.rollout import rollout
from controllers.base import EpisodeContext, reset_controller
from controllers.policy import PolicyController
from envs.platoon import PlatoonEnv
from infra.errors import ConfigError, UnknownNameError
from marl.checkpoint import save_checkpoint
from marl.config import algorithm
from marl.learners import LEARNERS, PAPER_ALGORITHMS


def _ckpt(tmp_path, algo="ia2c", n=4, scenario="catchup-v1"):
    a = algorithm(algo)
    cfg = a.config_cls()
    net = a.build_net(cfg, n, True, torch.Generator().manual_seed(1))
    import dataclasses

    path = save_checkpoint(
        tmp_path / f"{algo}.pt",
        algo=algo,
        config=dataclasses.asdict(cfg),
        scenario=scenario,
        n_vehicles=n,
        seed=0,
        steps=0,
        curve_summary={},
        weights=net.acting_state_dict(),
    )
    return path, net


def _rollout(ctrl, n=4, seeds=(2000, 2010), steps=30, scenario="catchup-v1"):
    env = PlatoonEnv(scenario, n)
    ctx = EpisodeContext(env.scenario, n, np.asarray(seeds), env.params)
    reset_controller(ctrl, ctx)
    obs = env.reset(list(seeds))
    out = []
    for _ in range(steps):
        u = ctrl.act(env.state, obs)
        out.append(u)
        res = env.step(u)
        obs = res.observation
    return np.array(out), ctx, env


def _ovm_candidates(gap: np.ndarray, v: np.ndarray, v_pred: np.ndarray) -> np.ndarray:
    """The four commands of the MARL action set, from the spec's formulas (not the code's):
    V(gap) = 15 (1 - cos(pi (gap - 5) / 30)) on [5, 35], u = alpha (V - v) + beta (v_pred - v)
    (the environment bounds the command later); (alpha, beta) = (0, 0), (0.5, 0), (0, 0.5),
    (0.5, 0.5)."""
    g = np.clip(gap, 5.0, 35.0)
    target = 15.0 * (1.0 - np.cos(np.pi * (g - 5.0) / 30.0))
    pairs = [(0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)]
    return np.stack([a * (target - v) + b * (v_pred - v) for a, b in pairs])


def _rollout_states(ctrl, n=4, seeds=(2000, 2010), steps=30):
    env = PlatoonEnv("catchup-v1", n)
    ctx = EpisodeContext(env.scenario, n, np.asarray(seeds), env.params)
    reset_controller(ctrl, ctx)
    obs = env.reset(list(seeds))
    cmds, cands = [], []
    for _ in range(steps):
        s = env.state
        cands.append(_ovm_candidates(s.gap_m, s.speed_mps, s.pred_speed_mps))
        u = ctrl.act(s, obs)
        cmds.append(u)
        obs = env.step(u).observation
    return np.array(cmds), np.array(cands)


@pytest.mark.parametrize("algo", ["ia2c", "dial", "bdc"])
def test_greedy_takes_the_argmax_and_sampled_draws_all_actions(tmp_path, algo) -> None:
    """With the actor head's weights zeroed and its bias slightly favouring action 1, greedy
    acting is action 1's OVM command at every step and vehicle; sampled acting uses all four
    actions (each with probability about a quarter)."""
    a = algorithm(algo)
    cfg = a.config_cls()
    net = a.build_net(cfg, 4, True, torch.Generator().manual_seed(1))
    weights = net.acting_state_dict()
    weights["actor_head.weight"] = torch.zeros_like(weights["actor_head.weight"])
    weights["actor_head.bias"] = torch.tensor([0.0, 0.05, 0.0, 0.0]).expand(4, 4).clone()
    import dataclasses

    path = save_checkpoint(tmp_path / f"{algo}.pt", algo=algo, config=dataclasses.asdict(cfg),
                           scenario="catchup-v1", n_vehicles=4, seed=0, steps=0,
                           curve_summary={}, weights=weights)
    u, cands = _rollout_states(PolicyController(algo, checkpoint=str(path), mode="greedy"))
    np.testing.assert_allclose(u, cands[:, 1], rtol=1e-12, atol=1e-12)
    u, cands = _rollout_states(PolicyController(algo, checkpoint=str(path)), steps=60)
    chosen = np.argmin(np.abs(cands - u[:, None]), axis=1)
    np.testing.assert_allclose(np.take_along_axis(cands, chosen[:, None], 1)[:, 0], u, atol=1e-12)
    freq = np.bincount(chosen.ravel(), minlength=4) / chosen.size
    assert np.all(freq > 0.15), freq


@pytest.mark.parametrize("algo", PAPER_ALGORITHMS)
def test_policy_controller_sends_its_messages_and_counts_bits(tmp_path, algo) -> None:
    path, _ = _ckpt(tmp_path, algo)
    ctrl = PolicyController(algo, checkpoint=str(path))
    assert ctrl.family == "marl" and ctrl.needs_observation
    u, ctx, env = _rollout(ctrl)
    assert u.shape == (30, 2, 4) and np.isfinite(u).all()
    width = 5 + ctrl.net.msg_width
    # every follower broadcasts its block (and message) every step, 32 bits per float
    assert ctx.bits_sent == 30 * 2 * 4 * width * 32
    assert {"ia2c": 0, "fprint": 4, "dial": 64, "commnet": 64}.get(algo, 0) == ctrl.net.msg_width


@pytest.mark.parametrize("algo", representative(PAPER_ALGORITHMS, {"bdc", "dial"}))
@pytest.mark.parametrize("mode", ["sampled", "greedy"])
def test_training_validation_is_the_benchmark_loop(algo, mode) -> None:
    """Training's validation (batched episodes, the live network) gives what the harness's
    one-episode rollouts of the shipped controller give, on trained weights (the shipped seed-0
    checkpoints, slowdown-v1, where policies act and some collide), episode by episode."""
    from envs.scenarios import make_scenario

    ctrl = PolicyController(algo, mode=mode)
    seeds = [2000, 2010, 2020, 2030]
    trajs = [rollout(ctrl, make_scenario("slowdown-v1"), 8, s) for s in seeds]
    got = evaluate_policy(algo, ctrl.net, "slowdown-v1", 8, seeds, mode)
    want = float(np.mean([t.reward.mean() for t in trajs]))
    # To the last bit in both modes. A one-row float32 matrix product (gemv) rounds otherwise
    # than the rows of a batch, which once flipped a greedy near-tie (DIAL, 1e6-step slowdown
    # weights: -1570.28 batched against -1570.36 alone); the controller gives its network at
    # least MIN_LANES rows, which removed the difference.
    assert got["reward"] == want
    assert got["collisions"] == sum(t.collided for t in trajs)
    assert len({round(t.reward.mean(), 6) for t in trajs}) == len(seeds)  # the episodes differ


@pytest.mark.parametrize("algo", LEARNERS)
def test_a_network_row_does_not_depend_on_the_batch(algo, monkeypatch) -> None:
    """The probe behind batching policies, one for every learner: an episode's outputs (and
    next recurrent state) are the same, to the last bit, whether its row is computed among 64 or
    in the ``MIN_LANES`` rows (itself repeated) that a lone episode's controller uses. With one
    row (gemv) the networks with one layer per agent differ, on every machine measured: the
    probe is not vacuous (a shared actor's one row measured equal on AMD EPYC)."""
    import controllers.policy as cp

    cp.rows_are_batch_invariant.cache_clear()
    assert cp.rows_are_batch_invariant(algo)
    monkeypatch.setattr(cp, "MIN_LANES", 1)
    cp.rows_are_batch_invariant.cache_clear()
    if LEARNERS[algo].per_agent:
        assert not cp.rows_are_batch_invariant(algo)
    cp.rows_are_batch_invariant.cache_clear()


def test_policies_run_one_at_a_time_where_the_probe_fails(monkeypatch) -> None:
    """On a machine whose kernels made rows depend on the batch, the harness would not batch
    policy episodes (each its own batch, stored as it finishes), and the records stay exact."""
    import controllers.policy as cp
    from benchmark.suite import batch_keys, build_sweep, execute_batch, execute_run

    keys = build_sweep([("ia2c", {"untrained": "true"})], ["catchup-v1"], [3], [2000, 2010])
    assert [len(b) for b in batch_keys(keys)] == [2]
    monkeypatch.setattr(cp, "rows_are_batch_invariant", lambda algo, n_agents=8: False)
    assert [len(b) for b in batch_keys(keys)] == [1, 1]
    ctrl = cp.PolicyController("ia2c", untrained="true")
    assert not ctrl.batch_invariant
    recs = execute_batch(keys)  # a batch handed over anyway runs seed by seed
    assert [r["reward"] for r in recs] == [execute_run(k)["reward"] for k in keys]


def test_a_lone_episode_gives_the_network_min_lanes_rows(monkeypatch) -> None:
    import marl.acting
    from controllers.policy import MIN_LANES

    rows = []
    real = marl.acting.policy_actions

    def spy(net, obs, *args):
        rows.append(obs.shape[0])
        return real(net, obs, *args)

    monkeypatch.setattr(marl.acting, "policy_actions", spy)
    from envs.scenarios import make_scenario

    rollout(PolicyController("ia2c", untrained="true"), make_scenario("catchup-v1"), 3, 2000)
    assert MIN_LANES == 8 and set(rows) == {8}


def test_sampled_mode_is_reproducible_and_differs_from_greedy(tmp_path) -> None:
    """Sampled actions depend only on the episode seed and agent: a rerun, another batch
    composition and another controller object give the same commands; greedy differs."""
    path, _ = _ckpt(tmp_path, "ia2c")
    u1, _, _ = _rollout(PolicyController("ia2c", checkpoint=str(path)), seeds=(2000, 2010))
    u2, _, _ = _rollout(PolicyController("ia2c", checkpoint=str(path)), seeds=(2010, 2000, 2020))
    np.testing.assert_array_equal(u1[:, 0], u2[:, 1])
    np.testing.assert_array_equal(u1[:, 1], u2[:, 0])
    ug, _, _ = _rollout(PolicyController("ia2c", checkpoint=str(path), mode="greedy"))
    assert not np.array_equal(u1, ug)
    ctrl = PolicyController("ia2c", checkpoint=str(path))
    assert not ctrl.deterministic and ctrl.options == {"checkpoint": str(path)}
    greedy = PolicyController("ia2c", mode="greedy")
    assert greedy.deterministic and greedy.options == {"mode": "greedy"}
    with pytest.raises(ConfigError, match="mode must be one of"):
        PolicyController("ia2c", mode="argmax")


def test_missing_checkpoint_names_train_command(tmp_path) -> None:
    ctrl = PolicyController("bdc", checkpoint=str(tmp_path / "nope.pt"))
    with pytest.raises(ConfigError, match="cacc-bench train --algo bdc --scenario catchup-v1"):
        _rollout(ctrl)
    ctrl = PolicyController("bdc", scenario="sine-v1")  # no shipped bdc policy for sine-v1
    with pytest.raises(ConfigError, match="cacc-bench train --algo bdc --scenario sine-v1"):
        _rollout(ctrl)
    ctrl = PolicyController("bdc", scenario="no-such-scenario-v9")  # named as unknown, not to train
    with pytest.raises(UnknownNameError, match="unknown scenario 'no-such-scenario-v9'"):
        _rollout(ctrl)


def test_wrong_algorithm_or_size_fails(tmp_path) -> None:
    path, _ = _ckpt(tmp_path, "ia2c", n=4)
    with pytest.raises(ConfigError, match="holds algorithm 'ia2c'"):
        _rollout(PolicyController("wac", checkpoint=str(path)))
    with pytest.raises(ConfigError, match="N = 4"):
        _rollout(PolicyController("ia2c", checkpoint=str(path)), n=3)


def test_untrained_and_bad_options() -> None:
    u, _, _ = _rollout(PolicyController("ia2c", untrained=True))
    assert np.isfinite(u).all()
    with pytest.raises(ConfigError, match="no option"):
        PolicyController("ia2c", horizon=3)


def test_variant_loads_its_folder_and_bad_variants_fail(tmp_path, monkeypatch) -> None:
    import controllers.policy as policy

    monkeypatch.setattr(policy, "VARIANT_DIR", tmp_path / "variants")
    folder = tmp_path / "variants" / "w5_m1"
    folder.mkdir(parents=True)
    path, _ = _ckpt(tmp_path, "ia2c", n=4)
    path.rename(folder / "ia2c__catchup-v1__n4__s0.pt")
    assert policy.shipped_variants() == ["w5_m1"]
    ctrl = PolicyController("ia2c", variant="w5_m1")
    same = PolicyController("ia2c", checkpoint=str(folder / "ia2c__catchup-v1__n4__s0.pt"))
    np.testing.assert_array_equal(_rollout(ctrl)[0], _rollout(same)[0])
    assert ctrl.options == {"variant": "w5_m1"}
    with pytest.raises(ConfigError, match="unknown variant 'w5_m2'; shipped with ia2c: w5_m1"):
        PolicyController("ia2c", variant="w5_m2")
    with pytest.raises(ConfigError, match="not both"):
        PolicyController("ia2c", variant="w5_m1", checkpoint_dir=str(tmp_path))
    with pytest.raises(ConfigError, match="no bdc policy for catchup-v1 .* holds: ia2c__"):
        _rollout(PolicyController("bdc", variant="w5_m1"))


def test_registry_builds_policy() -> None:
    from controllers.registry import make_controller

    ctrl = make_controller("bdc", untrained="true")
    assert isinstance(ctrl, PolicyController) and ctrl.algo == "bdc" and ctrl.untrained


def test_train_cmd_errors_and_tiny_run(tmp_path) -> None:
    from commands.train import main

    with pytest.raises(UnknownNameError):
        main(["--algo", "nope", "--scenario", "catchup-v1"])
    with pytest.raises(UnknownNameError):
        main(["--algo", "ia2c", "--scenario", "nope-v1"])
    assert (
        main(
            [
                "--algo",
                "ia2c",
                "--scenario",
                "catchup-v1",
                "--steps",
                "50",
                "--vehicles",
                "3",
                "--episodes-parallel",
                "2",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    stem = tmp_path / "ia2c__catchup-v1__n3__s0"
    assert stem.with_suffix(".pt").exists()
    lines = (tmp_path / "ia2c__catchup-v1__n3__s0.curve.csv").read_text().splitlines()
    assert lines[0] == (
        "episode,steps,train_reward,eval_reward_sampled,eval_collisions_sampled,"
        "eval_reward_greedy,eval_collisions_greedy"
    ) and len(lines) >= 2
    assert stem.with_suffix(".final.pt").exists()
    assert "bit/vehicle/s" in (tmp_path / "ia2c__catchup-v1__n3__s0.log").read_text()


def shipped_seeds(algo: str, scenario: str) -> list[int]:
    """Training seeds of the shipped checkpoints of ``algo`` on ``scenario`` (N = 8)."""
    from controllers.policy import CHECKPOINT_DIR

    found = CHECKPOINT_DIR.glob(f"{algo}__{scenario}__n8__s*.pt")
    return sorted(int(p.stem.rsplit("__s", 1)[1]) for p in found)


def pooled_evaluation(algo: str, scenario: str, mode: str = "sampled") -> dict[str, float]:
    """The shipped seeds of a policy on the 50 evaluation seeds: collisions summed, reward the
    mean over all episodes (what ``cacc-bench run --pool-seeds`` reports)."""
    from controllers.policy import checkpoint_path
    from envs.params import EVAL_SEEDS
    from marl.checkpoint import load_checkpoint
    from marl.config import config_from_dict

    a = algorithm(algo)
    out = []
    for seed in shipped_seeds(algo, scenario):
        data = load_checkpoint(checkpoint_path(algo, scenario, 8, seed), algo=algo, n_vehicles=8)
        net = a.build_net(config_from_dict(a, data["config"]), 8, with_critic=False)
        net.load_state_dict(data["weights"])
        out.append(evaluate_policy(algo, net, scenario, 8, EVAL_SEEDS, mode))
    return {
        "collisions": sum(r["collisions"] for r in out),
        "episodes": sum(r["episodes"] for r in out),
        "reward": float(np.mean([r["reward"] for r in out])),
        "seeds": len(out),
    }


@functools.cache
def _reference(name: str, scenario: str) -> dict[str, float]:
    """``ovm`` or ``duty`` on the 50 evaluation seeds through the harness's closed loop."""
    from benchmark.rollout import rollout_batch
    from controllers.registry import make_controller
    from envs.params import EVAL_SEEDS
    from envs.scenarios import make_scenario

    trajs = rollout_batch(make_controller(name), make_scenario(scenario), 8, EVAL_SEEDS)
    return {"reward": float(np.mean([t.reward.mean() for t in trajs])),
            "collisions": float(sum(t.collided for t in trajs))}


#: Shipped policies that avoid collisions by crawling: fewer collisions than their untrained
#: policy, but no better mean reward. None since the slowdown-v1 policies were trained longer
#: (at 6e5 steps, BDC and DCEA crawled there: -1,845 and -3,369).
CRAWLING: frozenset[tuple[str, str]] = frozenset()

#: What the README's table reads, three training seeds pooled (150 episodes): (collisions, mean
#: reward) per algorithm and scenario (catchup-v1 trained 6e5 steps, slowdown-v1 2e6 steps, the
#: same for all seven; retrained under the limited-regeneration energy fit); ``ovm`` -652 on
#: catchup-v1 and -756 on slowdown-v1.
MEASURED: dict[tuple[str, str], tuple[int, float]] = {
    ("bdc", "catchup-v1"): (0, -451.89), ("dcea", "catchup-v1"): (0, -455.88),
    ("wac", "catchup-v1"): (0, -462.61), ("dial", "catchup-v1"): (0, -511.28),
    ("commnet", "catchup-v1"): (0, -515.18), ("fprint", "catchup-v1"): (0, -609.28),
    ("ia2c", "catchup-v1"): (0, -705.54),
    ("bdc", "slowdown-v1"): (0, -671.44), ("dcea", "slowdown-v1"): (0, -653.80),
    ("wac", "slowdown-v1"): (0, -667.54), ("dial", "slowdown-v1"): (17, -906.49),
    ("commnet", "slowdown-v1"): (0, -790.05), ("fprint", "slowdown-v1"): (0, -573.31),
    ("ia2c", "slowdown-v1"): (0, -651.48),
}

#: Algorithms that, pooled, are collision-free and better than ``ovm`` on slowdown-v1 (the
#: README's reading; BDC among them is the MARL-credibility issue's bar).
SAFE_AND_AHEAD_ON_SLOWDOWN = frozenset({"bdc", "fprint", "dcea", "ia2c", "wac"})

#: Algorithms whose pooled reward does not beat ``ovm`` on catchup-v1 (the README's reading:
#: IA2C's three seeds at -693, -774 and -649 against -652).
BEHIND_OVM_ON_CATCHUP = frozenset({"ia2c"})


@pytest.mark.parametrize("scenario", ["catchup-v1", "slowdown-v1"])
def test_duty_beats_ovm_on_the_evaluation_seeds(scenario) -> None:
    """``duty`` (its default k) beats ``ovm`` by more than 50 per step, both collision-free."""
    ovm = _reference("ovm", scenario)
    duty = _reference("duty", scenario)
    assert ovm["collisions"] == duty["collisions"] == 0
    assert duty["reward"] > ovm["reward"] + 50


@pytest.mark.parametrize("scenario", ["catchup-v1", "slowdown-v1"])
@pytest.mark.parametrize("name", representative(PAPER_ALGORITHMS, {"bdc"}))
def test_shipped_policies_on_the_evaluation_seeds(name, scenario) -> None:
    """What the README says of the shipped policies, on the 50 published evaluation seeds in the
    default (sampled) mode, pooled over the three shipped training seeds:

    - every algorithm ships seeds 0, 1 and 2 and reads the README's numbers (:data:`MEASURED`);
    - every policy collides in a smaller fraction of episodes than its untrained policy (45 to
      48 of 50) and, except those in :data:`CRAWLING`, scores a better reward;
    - catchup-v1: every algorithm but those of :data:`BEHIND_OVM_ON_CATCHUP` beats ``ovm``;
      slowdown-v1: exactly the algorithms of :data:`SAFE_AND_AHEAD_ON_SLOWDOWN`, BDC among
      them, are collision-free and better than ``ovm``.
    """
    from envs.params import EVAL_SEEDS

    ovm = _reference("ovm", scenario)
    a = algorithm(name)
    assert shipped_seeds(name, scenario) == [0, 1, 2]
    pooled = pooled_evaluation(name, scenario)
    collisions, reward = MEASURED[(name, scenario)]
    assert pooled["collisions"] == collisions
    # kernels round differently between CPUs, which can flip a sampled near-tie: DIAL on
    # slowdown-v1 reads -752.28 where measured and -752.19 on an AMD EPYC (AVX-512 kernels)
    assert pooled["reward"] == pytest.approx(reward, abs=0.5)
    net = a.build_net(a.config_cls(), 8, False, torch.Generator().manual_seed(0))
    untrained = evaluate_policy(name, net, scenario, 8, EVAL_SEEDS)
    assert untrained["collisions"] >= 45
    assert pooled["collisions"] / pooled["episodes"] < untrained["collisions"] / 50
    if (name, scenario) not in CRAWLING:
        assert pooled["reward"] > untrained["reward"] + 50
    if scenario == "catchup-v1":
        assert (pooled["reward"] > ovm["reward"] + 30) == (name not in BEHIND_OVM_ON_CATCHUP)
    else:
        safe_and_ahead = pooled["collisions"] == 0 and pooled["reward"] > ovm["reward"]
        assert safe_and_ahead == (name in SAFE_AND_AHEAD_ON_SLOWDOWN)


def test_bdc_greedy_is_worse_than_sampled_on_catchup() -> None:
    """The greedy version of BDC's shipped catchup-v1 weights is worse than the sampled one
    (the README's -674 against -452)."""
    greedy = pooled_evaluation("bdc", "catchup-v1", "greedy")
    assert greedy["reward"] < MEASURED[("bdc", "catchup-v1")][1] - 100


def test_bdc_slowdown_curves_at_2e6_steps() -> None:
    """The README: the three shipped BDC seeds on slowdown-v1 (2e6 steps, retrained under the
    limited-regeneration fit) keep collision-free validation snapshots scoring -705.9, -710.8
    and -693.3 (under the plain polynomial: -667.2, -691.4, -693.3; at 1e6 steps -728.0,
    -914.7, -838.9, ``docs/bdc-slowdown-study.md``)."""
    import pandas as pd

    from controllers.policy import CHECKPOINT_DIR

    best = []
    for seed in (0, 1, 2):
        curve = pd.read_csv(CHECKPOINT_DIR / f"bdc__slowdown-v1__n8__s{seed}.curve.csv")
        ev = curve.dropna(subset=["eval_reward_sampled"])
        assert ev["steps"].max() >= 2_000_000
        best.append(ev.loc[ev["eval_collisions_sampled"] == 0, "eval_reward_sampled"].max())
    assert np.round(best, 1).tolist() == [-705.9, -710.8, -693.3]


@pytest.mark.parametrize(("controller", "scenario", "n"), [
    ("bdc", "catchup-v1", 2), ("bdc", "catchup-v1", 4), ("bdc", "catchup-v1", 6),
    ("bdc:scenario=openacc-train-s-v1", "openacc-s-v1", 4),
    ("bdc:scenario=openacc-train-m-v1", "openacc-m-v1", 4),
    ("bdc:scenario=openacc-train-l-v1", "openacc-l-v1", 4),
])
def test_the_shipped_size_and_openacc_policies_run(controller: str, scenario: str, n: int) -> None:
    """Seed 0 of the reproduction's platoon-size and OpenACC studies ships (README, Reproducing
    the paper): `run --controllers bdc --vehicles 4` works after install."""
    from benchmark.suite import build_sweep, execute_run
    from controllers.registry import parse_controller_list

    key = build_sweep(parse_controller_list(controller), [scenario], [n], [2000])[0]
    rec = execute_run(key)
    assert rec["status"] == "ok", rec.get("error")
    assert not rec["collision"] and rec["steps"] > 100


def test_the_paper_report_judged_the_shipped_catchup_policies() -> None:
    """The committed paper-budget report's catchup-v1 rows (docs/paper-reproduction) are the
    shipped policies on the same episodes: its pooled rewards and collisions read
    :data:`MEASURED` (the README says so of the report)."""
    import pandas as pd

    docs = Path(__file__).resolve().parents[2] / "docs" / "paper-reproduction"
    t2 = pd.read_csv(docs / "table2.csv").set_index(["name", "scenario"])
    for (name, scenario), (collisions, reward) in MEASURED.items():
        if scenario == "catchup-v1":
            assert t2.loc[(name, scenario), "collisions"] == collisions
            assert t2.loc[(name, scenario), "reward_mean"] == pytest.approx(reward, abs=0.5)


@FULL
def test_ia2c_seeds_disagree_on_power_where_bdc_seeds_agree() -> None:
    """The README's reading of the energy claim's wide interval against IA2C on catchup-v1
    (shipped seeds, 50 evaluation seeds, actions sampled): one IA2C seed uses far more platoon
    power than any BDC seed (57.1 kW where measured), the other two less (37.6, 37.8), while
    BDC's three agree (39.7 to 40.4)."""
    from benchmark.rollout import rollout_batch
    from controllers.registry import make_controller
    from envs.params import EVAL_SEEDS
    from envs.scenarios import make_scenario

    def power_kw(algo: str, seed: int) -> float:
        trajs = rollout_batch(make_controller(algo, seed=seed), make_scenario("catchup-v1"), 8,
                              EVAL_SEEDS)
        return float(np.mean([t.power_kw[1:].sum(axis=1).mean() for t in trajs]))

    ia2c = [power_kw("ia2c", s) for s in (0, 1, 2)]
    bdc = [power_kw("bdc", s) for s in (0, 1, 2)]
    assert max(bdc) / min(bdc) < 1.03
    assert max(ia2c) > 1.3 * max(bdc)
    assert sum(p < min(bdc) for p in ia2c) == 2
    assert [round(p, 1) for p in ia2c] == pytest.approx([57.1, 37.6, 37.8], abs=0.2)
