"""Class features of the shared policies (issue 55, point 4): off by default (the observation
and its width unchanged), each follower's own class parameters when on, the class
distribution drawn per batch from the run's generator, and the shipped policy acting on a
string of classes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from envs.params import PlatoonParams
from envs.scenarios import make_scenario
from envs.vehicle_classes import CLASS_FEATURE_NAMES, VEHICLE_CLASSES, class_features
from infra.errors import ConfigError
from marl.ppo import PPOTrainer
from marl.ppo_nets import PPOConfig

SMALL = {"n_envs": 4, "rollout_steps": 8}


def test_features_absent_by_default() -> None:
    cfg = PPOConfig()
    assert not cfg.class_features and cfg.obs_dim == 12
    assert PPOConfig(action_mode="ovm-gain").obs_dim == 18
    assert PPOConfig(class_features=True).obs_dim == 12 + len(CLASS_FEATURE_NAMES)
    tr = PPOTrainer(make_scenario("catchup-v1:classes=bus+van+car*6"), 8, 0, 64,
                    PPOConfig(**SMALL))
    assert tr.world.features is None and tr.obs.shape[-1] == 12


def test_features_per_seat_on_a_class_string() -> None:
    """Seat by seat: the class's lag (s), its acceleration bound over the run's (the tighter
    of the two), log10 of its mass over 1000 kg."""
    params = PlatoonParams()
    sc = make_scenario("catchup-v1:classes=bus+van+car*5+truck")
    tr = PPOTrainer(sc, 8, 0, 64, PPOConfig(class_features=True, **SMALL))
    names = ["bus", "van", *["car"] * 5, "truck"]
    want = [[VEHICLE_CLASSES[c].lag_s,
             min(VEHICLE_CLASSES[c].accel_max_mps2, params.accel_max_mps2)
             / params.accel_max_mps2,
             math.log10(VEHICLE_CLASSES[c].mass_kg / 1000.0)] for c in names]
    np.testing.assert_allclose(tr.world.features, want, rtol=1e-6)
    assert tr.obs.shape == (4, 8, 15)
    for b in range(4):  # appended after the observation, the same in every episode
        np.testing.assert_array_equal(tr.obs[b, :, 12:].numpy(), tr.world.features)
    assert tr.world.features[0, 1] == pytest.approx(1.2 / 2.5)  # the bus's 1.2 m/s^2


def test_homogeneous_string_gets_the_published_platoons_features() -> None:
    params = PlatoonParams()
    got = class_features(None, 5, params)
    np.testing.assert_allclose(
        got, [[params.lag_s, 1.0, math.log10(VEHICLE_CLASSES["i3"].mass_kg / 1000)]] * 5,
        rtol=1e-6)


def test_class_draw_reproducible_from_the_seed() -> None:
    cfg = PPOConfig(class_features=True, class_mixes="bus+van+car*6;truck+car*7", **SMALL)

    def labels(seed: int) -> list[str]:
        tr = PPOTrainer(make_scenario("catchup-v1"), 8, seed, 10**4, cfg)
        out = []
        for _ in range(6):
            tr.new_episodes()
            out.append(tr.world.env.scenario.label)
        return out

    first = labels(3)
    assert first == labels(3)
    assert first != labels(4)
    assert all("class_mix=" in lb and "class_seed=" in lb for lb in first)
    assert {lb.split("class_mix=")[1].split(",")[0] for lb in first} <= {"bus+van+car*6",
                                                                          "truck+car*7"}


@pytest.mark.parametrize("options, match", [
    ({"class_mixes": "bus+plane"}, "unknown vehicle class"),
    ({"class_mixes": "bus+van;;car*8"}, "empty item"),
    ({"class_mixes": "car", "algo": "ippo"}, "N >= 2"),
    ({"class_mixes": "car*8", "scenarios": "catchup-v1:classes=car*8"}, "sets its vehicle"),
])
def test_bad_class_mixes_refused(options: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        PPOConfig(**options)


def test_class_mix_of_another_n_refused() -> None:
    with pytest.raises(ConfigError, match="every arrangement names the run's 8 followers"):
        PPOTrainer(make_scenario("catchup-v1"), 8, 0, 64,
                   PPOConfig(class_mixes="car*6", **SMALL))


def test_the_shipped_class_features_policy_acts_on_a_class_string() -> None:
    """``ippo:variant=class-features`` records ``class_features`` in its checkpoint, reads each
    seat's features in the closed loop (the published platoon's on the homogeneous string) and
    drives ``bus+van+car*6`` on validation seeds without a collision."""
    from benchmark.rollout import rollout_batch
    from controllers.policy import PolicyController

    params = PlatoonParams()
    sc = make_scenario("catchup-v1:classes=bus+van+car*6")
    ctrl = PolicyController("ippo", variant="class-features")
    trajs = rollout_batch(ctrl, sc, 8, [1, 2, 3, 4])
    assert ctrl.loaded["config"]["class_features"] is True
    assert ctrl.net.class_features and ctrl.net.obs_mean.shape == (12 + 3,)
    np.testing.assert_array_equal(
        ctrl.policy.features, class_features(sc.vehicle_arrays(8, params), 8, params))
    assert not any(t.collided for t in trajs)
    rollout_batch(ctrl, make_scenario("catchup-v1"), 8, [1])
    np.testing.assert_array_equal(ctrl.policy.features, class_features(None, 8, params))


def test_a_featureless_shared_policy_runs_on_a_class_string_without_features() -> None:
    from benchmark.rollout import rollout_batch
    from controllers.policy import PolicyController

    ctrl = PolicyController("ippo")
    rollout_batch(ctrl, make_scenario("catchup-v1:classes=bus+van+car*6"), 8, [1])
    assert not ctrl.net.class_features and ctrl.policy.features is None
    assert "class_features" not in ctrl.loaded["config"]  # shipped before the option
    assert torch.equal(ctrl.net.obs_mean, ctrl.net.obs_mean[:12])


@pytest.mark.parametrize("options, reward", [
    ({"variant": "class-features"}, -992.8),
    ({"variant": "mixed-traffic", "scenario": "mixed-v2"}, -1031.8),
    ({}, -798.2),
])
def test_the_documented_comparison_on_a_class_string(options: dict, reward: float) -> None:
    """The table of ``docs/learned-control.md`` (vehicle classes): mean validation reward and
    no collision on ``bus+van+car*6`` over the 32 validation seeds."""
    from benchmark.rollout import rollout_batch
    from controllers.policy import PolicyController
    from envs.params import VALIDATION_SEEDS

    trajs = rollout_batch(PolicyController("ippo", **options),
                          make_scenario("catchup-v1:classes=bus+van+car*6"), 8,
                          list(VALIDATION_SEEDS))
    assert round(float(np.mean([t.reward.mean() for t in trajs])), 1) == reward
    assert not any(t.collided for t in trajs)
