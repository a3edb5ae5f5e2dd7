"""``ippo-gains``: a shared policy that schedules Ploeg's CACC along a segment certified string
stable (:mod:`marl.ippo_gains`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from infra.errors import ConfigError
from marl.ippo_gains import GainActor, GainScheduleConfig, gains_at


def _constant_actor(s: float, config: GainScheduleConfig = GainScheduleConfig()) -> GainActor:
    """An actor whose output is ``z = atanh(2 s - 1)`` whatever it observes (the last layer's
    weights zero, its bias z), so it picks the point ``s`` of the segment."""
    actor = GainActor(config)
    last = actor.body[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(float(np.arctanh(2 * s - 1)))
    actor.eval()
    return actor


def test_the_default_segment_is_certified_string_stable() -> None:
    """Every point of the default segment: ``||Gamma||_inf <= 1`` for delays 0, 0.1, 0.2 s and
    lags 0, 0.1 s, continuous and discrete, and internally stable (the certificate the study
    reports; analysis.stability computes it, the learner's layer may not)."""
    from studies.string_stability import certificate, certified

    cert = certificate(GainScheduleConfig().segment, points=21)
    assert len(cert) == 21 * 3 * 2
    assert certified(cert)
    # not a check that cannot fail: cacc's own gains at h = 0.5 s are not, with a 0.2 s delay
    bad = certificate(((0.2, 0.7, 0.5), (0.2, 0.7, 0.5)), points=2)
    assert not certified(bad)


def test_gains_are_linear_along_the_segment() -> None:
    kp, kd, h = gains_at(np.array([0.0, 0.5, 1.0]), ((0.2, 2.0, 0.5), (0.6, 3.0, 0.8)))
    np.testing.assert_allclose(kp, [0.2, 0.4, 0.6])
    np.testing.assert_allclose(kd, [2.0, 2.5, 3.0])
    np.testing.assert_allclose(h, [0.5, 0.65, 0.8])


@pytest.mark.parametrize(("options", "message"), [
    ({"algo": "ippo"}, "algo must be ippo-gains"),
    ({"prior": "cacc"}, "prior empty"),
    ({"kp_start": 0.0}, "kp_start must lie in (0, 100]"),
    ({"time_gap_end_s": float("nan")}, "time_gap_end_s must lie in (0, 100]"),
])
def test_bad_configs_are_refused(options: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace("]", r"\]")):
        GainScheduleConfig(**options)


@pytest.mark.parametrize("channel", [(0.0, 0.0), (0.2, 0.0)])
def test_a_constant_schedule_is_the_cacc_controller_with_those_gains(channel: tuple) -> None:
    """A policy that always picks ``s`` drives the platoon as the registered ``cacc`` with the
    gains and time gap at ``s``, in the benchmark's closed loop, to 1e-6 m (ideal V2V and a 0.2 s
    delay; the law reads the float32 observation, measured within 5e-8 m; with loss the two
    controllers' channels, named apart, lose other packets): the acting law is Ploeg's."""
    from benchmark.rollout import rollout_batch
    from controllers.policy import PolicyController
    from controllers.registry import make_controller
    from envs.channel import ChannelConfig
    from envs.scenarios import make_scenario

    actor = _constant_actor(0.3)
    with torch.no_grad():  # the coordinate it picks, in float32 as it acts
        s = float(actor.command(actor(torch.zeros(1, 12))))
    kp, kd, h = (float(x) for x in gains_at(np.array(s), GainScheduleConfig().segment))
    sc, seeds, ch = make_scenario("slowdown-v1"), [2000, 2010], ChannelConfig(*channel)
    ours = rollout_batch(PolicyController.from_net("ippo-gains", actor, sc.id, 4,
                                                   mode="greedy"), sc, 4, seeds, channel=ch)
    ref = rollout_batch(make_controller("cacc", kp=kp, kd=kd, time_gap_s=h), sc, 4, seeds,
                        channel=ch)
    for a, b in zip(ours, ref, strict=True):
        np.testing.assert_allclose(a.gap_m, b.gap_m, atol=1e-6, rtol=0)
        assert a.reward.mean() == pytest.approx(b.reward.mean(), abs=1e-6)


def test_the_training_env_applies_the_same_law() -> None:
    """:class:`marl.ippo_gains.ScheduledEnv` stepped with a constant coordinate moves the
    platoon as the registered ``cacc`` with those gains, to 1e-6 m (the float32 observation;
    the trainer's world and the controller act through one law)."""
    from benchmark.rollout import rollout_batch
    from controllers.registry import make_controller
    from envs.scenarios import make_scenario
    from marl.ippo_gains import ScheduledEnv

    s = 0.8
    cfg = GainScheduleConfig()
    kp, kd, h = (float(x) for x in gains_at(np.array(s), cfg.segment))
    sc = make_scenario("catchup-v1")
    env = ScheduledEnv(sc, 4, action_mode="accel")
    env.segment = cfg.segment
    env.reset([2000])
    gaps = []
    while not env.state.done.all():
        env.step(np.full((1, 4), s))
        gaps.append(env.state.gap_m[0].copy())
    ref = rollout_batch(make_controller("cacc", kp=kp, kd=kd, time_gap_s=h), sc, 4, [2000])[0]
    np.testing.assert_allclose(np.array(gaps), ref.gap_m[1:], atol=1e-6, rtol=0)


def test_a_short_training_writes_a_checkpoint_the_controller_scores_alike(tmp_path) -> None:
    """Train a few updates, keep the best snapshot, load it as ``ippo-gains:checkpoint=...``:
    the harness scores the shipped file exactly as validation scored it, and the file records
    the segment."""
    from benchmark.policy_eval import evaluate_policy, validation_evaluator
    from marl.checkpoint import load_checkpoint
    from marl.ippo_gains import load_gain_actor
    from marl.ppo import train

    cfg = GainScheduleConfig(n_envs=8, rollout_steps=32, eval_every_steps=256,
                             minibatch_rows=512, kp_end=0.5)
    seeds = [1, 2, 3]
    res = train("catchup-v1", 4, 0, 512, cfg, evaluate=validation_evaluator(
        "ippo-gains", "catchup-v1", 4, seeds=seeds))
    from marl.checkpoint import checkpoint_payload, write_run

    write_run(tmp_path, "ippo-gains__catchup-v1__n4__s0", [], {".pt": checkpoint_payload(
        algo="ippo-gains", config=dataclasses.asdict(cfg), scenario="catchup-v1", n_vehicles=4,
        seed=0, steps=res.steps, curve_summary={}, weights=dict(res.actor.state_dict()))})
    data = load_checkpoint(tmp_path / "ippo-gains__catchup-v1__n4__s0.pt", algo="ippo-gains")
    actor = load_gain_actor(data)
    assert actor.segment == cfg.segment
    again = evaluate_policy("ippo-gains", actor, "catchup-v1", 4, seeds)
    assert again["reward"] == res.best["reward"]
