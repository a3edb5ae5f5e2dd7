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


def test_every_scenario_is_a_registered_gymnasium_id_that_passes_the_checker() -> None:
    import gymnasium

    from envs.adapters import register_gymnasium
    from envs.scenarios import list_scenarios

    ids = register_gymnasium()
    assert ids == [f"{ns}/{s.id}" for s in list_scenarios()
                   for ns in ("cacc_bench", "cacc_bench_accel")]
    for env_id in ids:
        env = gymnasium.make(env_id)
        spec = next(s for s in list_scenarios() if env_id.endswith(f"/{s.id}"))
        assert env.unwrapped.n_vehicles == spec.default_vehicles  # type: ignore[attr-defined]
        mode = "accel" if env_id.startswith("cacc_bench_accel/") else "ovm-gain"
        assert env.unwrapped.action_mode == mode  # type: ignore[attr-defined]
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            # accel mode: a Box in m/s^2 (the MPC's bounds), not the [-1, 1] it recommends
            warnings.filterwarnings("ignore", message=".*symmetric and normalized")
            check_env(env.unwrapped, skip_render_check=True)


def test_the_module_prefix_registers_in_a_fresh_interpreter() -> None:
    import subprocess
    import sys

    code = ("import gymnasium; env = gymnasium.make('envs.adapters:cacc_bench/slowdown-v1', "
            "n_vehicles=3); obs, info = env.reset(seed=0); print(obs.shape, info['episode_seed'])")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.split() == ["(3,", "15)", "0"]


def test_gymnasium_reads_v2_as_newer_and_warns_on_the_published_slowdown() -> None:
    import gymnasium

    import envs.adapters  # noqa: F401  (registers)

    with pytest.warns(DeprecationWarning, match="upgrading to version `v2`"):
        gymnasium.make("cacc_bench/slowdown-v1")
