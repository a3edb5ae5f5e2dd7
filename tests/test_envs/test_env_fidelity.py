"""Fidelity to the published CACC benchmark (numbers from spec/environment.md and issue 2)."""

from __future__ import annotations

import numpy as np
import pytest

from envs.params import EVAL_SEEDS
from envs.platoon import PlatoonEnv
from envs.scenarios import published_perturbation


def test_published_seeding() -> None:
    assert published_perturbation(0) == 0.5488135039273248


def test_step_one_catchup_seed0() -> None:
    env = PlatoonEnv("catchup-v1", 8, include_power=False)
    env.reset([0])
    s = env.state
    assert s is not None
    assert s.gap_m[0, 0] == pytest.approx(40.97627, abs=1e-5)
    res = env.step_actions(np.full((1, 8), 3))
    assert s.speed_mps[0, 0] == pytest.approx(15.25, abs=1e-12)
    assert res.applied_accel_mps2[0, 0] == pytest.approx(2.5, abs=1e-9)
    assert s.gap_m[0, 0] == pytest.approx(40.96377, abs=1e-5)
    assert s.gap_m[0, 1] == pytest.approx(20.0125, abs=1e-9)
    # agent 1's evaluation reward without the power term
    assert res.reward[0, 0] == pytest.approx(-440.167156, abs=1e-6)


@pytest.mark.parametrize(
    ("scenario", "expected"), [("catchup-v1", -78.24), ("slowdown-v1", -478.12)]
)
def test_ovm_tracking_reward_over_published_eval_seeds(scenario: str, expected: float) -> None:
    env = PlatoonEnv(scenario, 8, include_power=False, observe=False)
    env.reset(list(EVAL_SEEDS))
    total = np.zeros(len(EVAL_SEEDS))
    for _ in range(env.n_steps):
        res = env.step_actions(np.full((len(EVAL_SEEDS), 8), 3))
        total += res.reward.sum(axis=1)
    assert not res.collided.any()
    assert total.mean() / env.n_steps == pytest.approx(expected, abs=0.01)


def test_slowdown_v1_quirk_first_step_deceleration() -> None:
    """Initial speeds above 30 m/s are clipped at step 1 (a large applied deceleration)."""
    env = PlatoonEnv("slowdown-v1", 4, include_power=False)
    env.reset([0], perturbation=0.9)  # v0 = 15 * 2.4 = 36 m/s
    res = env.step_actions(np.full((1, 4), 3))
    assert env.state is not None
    assert np.all(env.state.speed_mps <= 30.0)
    assert res.applied_accel_mps2[0, 1] < -2.5 * 10


def test_slowdown_v2_caps_initial_speed() -> None:
    env = PlatoonEnv("slowdown-v2", 4, include_power=False)
    env.reset([0], perturbation=0.9)
    assert env.state is not None
    assert env.state.speed_mps.max() == 30.0
    assert env.state.leader_speed_mps[0, 0] == 30.0
