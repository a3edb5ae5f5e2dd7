"""PettingZoo and Gymnasium adapters pass those libraries' own checkers."""

from __future__ import annotations

import warnings

import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test

from envs.adapters import PlatoonGymEnv, PlatoonParallelEnv


def test_pettingzoo_parallel_api() -> None:
    parallel_api_test(PlatoonParallelEnv("catchup-v1", 4), num_cycles=700)


def test_pettingzoo_seed() -> None:
    parallel_seed_test(lambda: PlatoonParallelEnv("slowdown-v1", 4))


def test_gymnasium_checker() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(PlatoonGymEnv("catchup-v1", 4), skip_render_check=True)


def test_adapter_reproduces_published_step() -> None:
    env = PlatoonParallelEnv("catchup-v1", 8)
    env.env.include_power = False
    obs, _ = env.reset(seed=0)
    assert set(obs) == {f"follower_{i}" for i in range(1, 9)}
    _, rewards, *_ = env.step({a: 3 for a in env.agents})
    assert rewards["follower_1"] == pytest.approx(-440.167156, abs=1e-6)
