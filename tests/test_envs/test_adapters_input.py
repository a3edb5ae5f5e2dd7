"""The Gymnasium and PettingZoo adapters keep the command line's rules (issue 53, point 4): bad
actions, seeds, delays, perturbations and options are refused with a ConfigError saying what is
expected, before the episode moves."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
import pytest

from envs.adapters import PlatoonGymEnv, PlatoonParallelEnv
from envs.platoon import PlatoonEnv
from infra.errors import ConfigError

ACCEL = r"finite accelerations in m/s\^2 \(outside \[-2.5, 2.5\] clipped\)"
GAINS = r"OVM-gain indices \(whole numbers 0..3\)"


def _gym(mode: str = "ovm-gain") -> PlatoonGymEnv:
    env = PlatoonGymEnv("catchup-v1", 4, action_mode=mode)
    env.reset(seed=0)
    return env


def _pz(mode: str = "ovm-gain") -> PlatoonParallelEnv:
    env = PlatoonParallelEnv("catchup-v1", 4, action_mode=mode)
    env.reset(seed=0)
    return env


def _each(value: Any) -> dict[str, Any]:
    return {f"follower_{i}": value for i in range(1, 5)}


@pytest.mark.parametrize(("mode", "action", "message"), [
    ("accel", [np.nan, 0, 0, 0], rf"action must be {ACCEL} of shape \(4,\), got nan"),
    ("accel", [0, np.inf, 0, 0], rf"action must be {ACCEL} of shape \(4,\), got inf"),
    ("accel", np.zeros(3), rf"action must be {ACCEL} of shape \(4,\), got shape \(3,\)"),
    ("accel", np.zeros((4, 1)), r"of shape \(4,\), got shape \(4, 1\)"),
    ("ovm-gain", [2.7, 2.9, 2, 2], rf"action must be {GAINS} of shape \(4,\), got 2.7"),
    ("ovm-gain", [0, 0, 4, 0], rf"{GAINS} of shape \(4,\), got 4"),
    ("ovm-gain", [0, -1, 0, 0], rf"{GAINS} of shape \(4,\), got -1"),
    ("ovm-gain", np.zeros(3, dtype=int), rf"{GAINS} of shape \(4,\), got shape \(3,\)"),
    ("ovm-gain", ["a", "b", "c", "d"], rf"{GAINS} of shape \(4,\), got a"),
])
def test_gymnasium_refuses_a_bad_action_before_the_step(mode: str, action: Any, message: str
                                                        ) -> None:
    env = _gym(mode)
    with pytest.raises(ConfigError, match=message):
        env.step(action)
    assert env.env.state is not None and env.env.state.step == 0  # the episode did not move


@pytest.mark.parametrize(("mode", "actions", "message"), [
    ("accel", _each(np.array([np.nan], np.float32)),
     rf"the action of follower_1 must be {ACCEL} of shape \(1,\), got nan"),
    ("accel", _each(np.array([0.5, 9.0, 9.0])), r"of shape \(1,\), got shape \(3,\)"),
    ("ovm-gain", _each(2.7), rf"the action of follower_1 must be {GAINS} \(one number\), got 2.7"),
    ("ovm-gain", _each(np.array([1, 2])), r"\(one number\), got shape \(2,\)"),
    ("ovm-gain", {"follower_1": 0},
     r"actions must map each agent \(follower_1 .. follower_4\) to its action; missing follower_2"),
    ("ovm-gain", {**_each(0), "follower_9": 0}, r"; unknown 'follower_9'"),
    ("ovm-gain", [0, 0, 0, 0], r"missing follower_1"),
])
def test_pettingzoo_refuses_a_bad_action_before_the_step(mode: str, actions: Any, message: str
                                                         ) -> None:
    env = _pz(mode)
    with pytest.raises(ConfigError, match=message):
        env.step(actions)
    assert env.env.state is not None and env.env.state.step == 0


def test_good_actions_in_every_accepted_form_act_alike() -> None:
    """Whole floats are gain indices, a bare number is the one-number Box: same steps as the
    space's own form."""
    rewards = [_gym().step(a)[1] for a in (np.array([3, 1, 2, 0]), [3.0, 1.0, 2.0, 0.0])]
    assert rewards[0] == rewards[1]
    pz = [_pz("accel").step(_each(a))[1] for a in (np.array([0.5], np.float32), 0.5)]
    assert pz[0] == pz[1]


@pytest.mark.parametrize("make", [lambda: PlatoonGymEnv("catchup-v1", 4),
                                  lambda: PlatoonParallelEnv("catchup-v1", 4)])
@pytest.mark.parametrize(("seed", "message"), [
    (2**64, r"seed must lie in 0..2147483647, got 18446744073709551616"),
    (2**31, r"seed must lie in 0..2147483647, got 2147483648"),
    (-1, r"seed must lie in 0..2147483647, got -1"),
    (1.5, r"seed must be a whole number in 0..2147483647, got 1.5"),
])
def test_reset_seeds_keep_the_command_lines_range(make: Callable[[], Any], seed: Any,
                                                  message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        make().reset(seed=seed)


@pytest.mark.parametrize(("options", "message"), [
    ({"perturbation": [0.1, 0.2]}, r"perturbation must be one number in \[0, 1\] or one per "
                                   r"episode \(B = 1\), got \[0.1, 0.2\]"),
    ({"perturbation": "abc"}, r"perturbation must be one number .* got 'abc'"),
    ([0.5], r"options must be a dict \(perturbation: U in \[0, 1\]\), got \[0.5\]"),
])
def test_reset_options_are_checked(options: Any, message: str) -> None:
    for env in (PlatoonGymEnv("catchup-v1", 4), PlatoonParallelEnv("catchup-v1", 4)):
        with pytest.raises(ConfigError, match=message):
            env.reset(seed=0, options=options)
    # one number, or one per episode, still sets U
    obs = [PlatoonGymEnv("catchup-v1", 4).reset(seed=0, options={"perturbation": u})[0]
           for u in (0.3, [0.3])]
    np.testing.assert_array_equal(obs[0], obs[1])


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"action_mode": "accel", "comm_delay_s": 0.05},
     r"comm_delay_s 0.05 s: V2V messages arrive after whole simulation steps of 0.1 s"),
    ({"comm_delay_s": 0.2}, r"comm_delay_s and packet_loss act on the V2V messages of the accel "
                            r"mode; .* give action_mode='accel' or leave them at 0"),
    ({"amplitude_mps": 2.0}, r"scenario catchup-v1 has no option 'amplitude_mps'"),
])
def test_construction_keeps_the_command_lines_rules(kwargs: dict[str, Any], message: str
                                                    ) -> None:
    for cls in (PlatoonGymEnv, PlatoonParallelEnv):
        with pytest.raises(ConfigError, match=message):
            cls("catchup-v1", 4, **kwargs)
    PlatoonGymEnv("catchup-v1", 4, action_mode="accel", comm_delay_s=0.3)  # whole steps: fine


def test_gymnasium_make_options_go_through_the_scenario_rules() -> None:
    import envs.adapters  # noqa: F401  (registers)

    env = gymnasium.make("cacc_bench/sine-v1", amplitude_mps=2, disable_env_checker=True)
    assert env.unwrapped.env.scenario.label == "sine-v1[amplitude_mps=2.0]"  # type: ignore[attr-defined]
    ring = gymnasium.make("cacc_bench/ring-v1", vehicles=10, disable_env_checker=True)
    assert ring.unwrapped.n_vehicles == 10  # type: ignore[attr-defined]
    with pytest.raises(ConfigError, match=r"sine-v1 amplitude_mps must lie in \[0, 10\] m/s"):
        gymnasium.make("cacc_bench/sine-v1", amplitude_mps=-1, disable_env_checker=True)


def test_the_env_itself_refuses_bad_commands_and_gain_indices() -> None:
    env = PlatoonEnv("catchup-v1", 3)
    env.reset([0, 1])
    with pytest.raises(ConfigError, match=r"commands must be finite .* of shape \(2, 3\), got nan"):
        env.step(np.array([[0.0, np.nan, 0.0], [0.0, 0.0, 0.0]]))
    with pytest.raises(ConfigError, match=r"of shape \(2, 3\), got shape \(3,\)"):
        env.step(np.zeros(3))
    with pytest.raises(ConfigError, match=rf"actions must be {GAINS} of shape \(2, 3\), got 2.5"):
        env.step_actions(np.full((2, 3), 2.5))
    assert env.state is not None and env.state.step == 0
    env.step_actions(np.full((2, 3), 2.0))  # whole floats are indices
