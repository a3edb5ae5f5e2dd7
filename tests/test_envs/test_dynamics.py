"""Physics, OVM, reward, observation, collision and scenarios, against hand-derived numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.dynamics import (
    agent_observations,
    neighbour_mask,
    ovm_speed_mps,
    physics_step,
    reward_terms,
    vehicle_blocks,
)
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import brake_profile_mps, make_scenario
from infra.errors import ConfigError, UnknownNameError


def test_ovm_speed_reference_points() -> None:
    gaps = np.array([0.0, 5.0, 20.0, 35.0, 50.0, 12.5])
    v = ovm_speed_mps(gaps)
    expected = [0.0, 0.0, 15.0, 30.0, 30.0, 15 * (1 - math.cos(math.pi * 7.5 / 30))]
    np.testing.assert_allclose(v, expected, atol=1e-12)


def test_distance_is_speed_times_time() -> None:
    """Constant speeds: the gap changes by (v_pred - v) * t exactly."""
    env = PlatoonEnv("catchup-v1", 3, include_power=False, observe=False)
    env.reset([1])
    s = env.state
    assert s is not None
    g0 = s.gap_m.copy()
    for _ in range(100):  # zero command: followers keep 15 m/s, leader 15 m/s
        env.step(np.zeros((1, 3)))
    np.testing.assert_allclose(s.gap_m, g0, atol=1e-12)
    # a follower 1 m/s slower than its predecessor loses 1 m/s * 10 s = 10 m more gap
    gap = np.array([[20.0, 20.0]])
    v = np.array([[15.0, 14.0]])
    a = np.zeros((1, 2))
    for _ in range(100):
        gap, v, a, _ = physics_step(gap, v, a, np.zeros((1, 2)), np.array([15.0]),
                                    np.array([15.0]))
    np.testing.assert_allclose(gap, [[20.0, 30.0]], atol=1e-9)


def test_actuator_lag_reaches_63_percent_after_tau() -> None:
    tau = 0.5
    params = PlatoonParams(lag_s=tau)
    gap = np.array([[100.0]])
    v = np.array([[15.0]])
    a = np.zeros((1, 1))
    for _ in range(int(round(tau / params.dt_s))):
        gap, v, a, _ = physics_step(gap, v, a, np.ones((1, 1)), np.array([15.0]),
                                    np.array([15.0]), params)
    assert a[0, 0] == pytest.approx(1 - math.exp(-1), abs=1e-12)


def test_command_clipping_and_speed_bounds() -> None:
    gap = np.array([[20.0, 20.0]])
    v = np.array([[29.9, 0.05]])
    gap2, v2, _, applied = physics_step(gap, v, np.zeros((1, 2)), np.array([[9.0, -9.0]]),
                                        np.array([15.0]), np.array([15.0]))
    assert v2[0, 0] == 30.0 and v2[0, 1] == 0.0
    np.testing.assert_allclose(applied, [[(30 - 29.9) / 0.1, -0.05 / 0.1]])
    # trapezoidal gap update
    assert gap2[0, 0] == pytest.approx(20 + 0.05 * (15 + 15 - 29.9 - 30.0))


def test_reward_terms_by_hand() -> None:
    t = reward_terms(np.array([[8.0]]), np.array([[16.0]]), np.array([[2.0]]),
                     np.array([[3.0]]), 20.0, 15.0)
    assert t["gap"][0, 0] == -144.0
    assert t["speed"][0, 0] == -1.0
    assert t["accel"][0, 0] == pytest.approx(-0.4)
    assert t["safety"][0, 0] == -5.0 * 4.0
    assert t["power"][0, 0] == -30.0


def test_observation_blocks_and_neighbours() -> None:
    params = PlatoonParams()
    gap = np.array([[20.0, 25.0, 10.0]])
    v = np.array([[15.0, 16.0, 14.0]])
    vp = np.array([[15.5, 15.0, 16.0]])
    u = np.array([[1.0, -2.5, 0.0]])
    blk = vehicle_blocks(gap, v, vp, u, 20.0, 15.0, params)
    assert blk.shape == (1, 3, 5)
    np.testing.assert_allclose(blk[0, 1], [1 / 15, -0.2, (ovm_speed_mps(np.array(25.0)) - 16) / 5,
                                           (25 - 0.1 - 20) / 20, -1.0], rtol=1e-6)
    obs = agent_observations(blk)
    assert obs.shape == (1, 3, 15)
    np.testing.assert_array_equal(obs[0, 0, 5:10], 0)  # no front agent for follower 1
    np.testing.assert_array_equal(obs[0, 2, 10:15], 0)  # no rear agent for the last
    np.testing.assert_array_equal(obs[0, 1, 5:10], blk[0, 0])
    np.testing.assert_array_equal(obs[0, 1, 10:15], blk[0, 2])
    assert neighbour_mask(3).tolist() == [[False, True], [True, True], [True, False]]


def test_env_observation_equals_pure_functions() -> None:
    env = PlatoonEnv("catchup-v1", 4)
    obs = env.reset([3])
    s = env.state
    assert s is not None and obs is not None
    ref = agent_observations(vehicle_blocks(s.gap_m, s.speed_mps, s.pred_speed_mps,
                                            s.applied_accel_mps2, 20.0, 15.0))
    np.testing.assert_allclose(obs, ref, rtol=1e-6, atol=1e-6)  # float32 V(gap)


@pytest.mark.parametrize("mode", ["terminate", "published"])
def test_collision_rules(mode: str) -> None:
    env = PlatoonEnv("catchup-v1", 2, include_power=False, observe=False, collision_mode=mode)
    env.reset([0])
    s = env.state
    assert s is not None
    res = None
    for _ in range(1, 200):
        res = env.step(np.array([[0.0, 2.5]]))  # follower 2 drives into follower 1
        if res.collided[0]:
            break
    assert res is not None and res.collided[0]
    hit = s.step
    assert np.all(res.reward[0] == -1000.0)
    frozen = s.gap_m.copy()
    if mode == "terminate":
        assert res.done[0]
    else:
        assert res.done[0] == (hit % 60 == 0)
        while not res.done[0]:
            res = env.step(np.array([[0.0, 2.5]]))
            assert np.all(res.reward[0] == -1000.0)
            np.testing.assert_array_equal(s.gap_m, frozen)
        assert s.step % 60 == 0


def test_step_tracking_reward_is_the_reward_without_its_power_term() -> None:
    """The env returns the tracking reward itself (the terms of ``reward_terms`` without power),
    with the reward's collision and end rules; nothing downstream subtracts the power term."""
    env = PlatoonEnv("catchup-v1", 2, observe=False)
    env.reset([0, 1])
    s = env.state
    assert s is not None
    w5 = env.weights.power
    while True:
        res = env.step(np.array([[0.0, 2.5], [0.0, 0.0]]))  # episode 0 collides, 1 does not
        live = ~res.collided
        np.testing.assert_allclose(res.tracking_reward[live],
                                   res.reward[live] - w5 * res.power_kw[live], rtol=1e-12)
        assert np.all(res.tracking_reward[live] <= 0)
        if res.collided[0]:
            break
    assert np.all(res.tracking_reward[0] == -1000.0) and np.all(res.reward[0] == -1000.0)
    res = env.step(np.zeros((2, 2)))
    assert np.all(res.tracking_reward[0] == 0.0) and np.all(res.reward[0] == 0.0)
    assert res.tracking_reward[1].sum() < 0


def test_batched_env_equals_separate_runs() -> None:
    seeds = [2000, 2010, 2020, 7]
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 4, size=(120, len(seeds), 6))
    for sc in ("catchup-v1", "slowdown-v1", "brake-v1"):
        env = PlatoonEnv(sc, 6, params=PlatoonParams(lag_s=0.2))
        env.reset(seeds)
        batch_rewards = []
        for t in range(120):
            batch_rewards.append(env.step_actions(actions[t]).reward.copy())
        for k, seed in enumerate(seeds):
            one = PlatoonEnv(sc, 6, params=PlatoonParams(lag_s=0.2))
            one.reset([seed])
            for t in range(120):
                r = one.step_actions(actions[t, k : k + 1]).reward
                np.testing.assert_array_equal(r[0], batch_rewards[t][k])


def test_scenario_profiles() -> None:
    sc = make_scenario("slowdown-v1")
    ep = sc.episodes([0], 3)
    v0 = 15 * (1.5 + 0.5488135039273248)
    assert ep.leader_speed_mps[0, 0] == pytest.approx(v0)
    assert ep.leader_speed_mps[0, 299] == pytest.approx(15.0)
    assert ep.leader_speed_mps[0, 150] == pytest.approx(v0 + (15 - v0) * 150 / 299)
    v = brake_profile_mps(600)
    assert v[100] == 15.0 and v[140] == pytest.approx(5.0) and v[240] == pytest.approx(5.0)
    assert v[120] == pytest.approx(10.0)
    assert v[240 + 33] == pytest.approx(5 + 1.5 * 3.3)
    assert v[300] == pytest.approx(5 + 1.5 * 6.0) and v[400] == 15.0
    sine = make_scenario("sine-v1", frequency_hz=0.1, amplitude_mps=0.5).episodes([1], 2)
    assert sine.leader_speed_mps[0, 25] == pytest.approx(15.5)  # t = 2.5 s, quarter period
    assert np.all(sine.gap_m == 20.0) and np.all(sine.speed_mps == 15.0)


def test_explicit_perturbation() -> None:
    ep = make_scenario("catchup-v1").episodes([0, 1], 3, perturbation=0.25)
    np.testing.assert_allclose(ep.gap_m[:, 0], 35.0)
    with pytest.raises(ConfigError):
        make_scenario("catchup-v1").episodes([0], 3, perturbation=1.5)


@pytest.mark.parametrize("n", [2, 16])
def test_platoon_sizes(n: int) -> None:
    """Any N steps like the published law: under OVM (action 3) the followers at equilibrium
    (20 m, 15 m/s) stay there, follower 1 (30.98 m back for seed 0, U = 0.5488) speeds up at
    0.5 (V(30.98) - 15), clipped to 2.5 m/s^2."""
    env = PlatoonEnv("catchup-v1", n)
    obs = env.reset([0])
    assert obs is not None and obs.shape == (1, n, 15)
    gap0 = 20.0 * (1.5 + 0.5488135039273248)
    assert env.state.gap_m[0, 0] == pytest.approx(gap0)
    res = env.step_actions(np.full((1, n), 3))
    assert res.observation.shape == (1, n, 15) and not res.done[0]
    v1 = 15.0 + 0.1 * min(0.5 * (15.0 * (1 - np.cos(np.pi * (gap0 - 5.0) / 30.0)) - 15.0), 2.5)
    assert env.state.speed_mps[0, 0] == pytest.approx(v1, abs=1e-12)
    np.testing.assert_allclose(env.state.speed_mps[0, 1:], 15.0, atol=1e-12)
    np.testing.assert_allclose(env.state.gap_m[0, 2:], 20.0, atol=1e-12)


def test_bad_configuration() -> None:
    with pytest.raises(ConfigError):
        PlatoonEnv("catchup-v1", 1)
    with pytest.raises(UnknownNameError, match="catchup-v1"):
        make_scenario("nope-v1")
    with pytest.raises(ConfigError, match="frequency_hz"):
        make_scenario("catchup-v1", frequency_hz=1.0)
    with pytest.raises(ConfigError):
        PlatoonParams(lag_s=-0.1)


@pytest.mark.parametrize("sc", ["openacc-s-v1", "openacc-m-v1", "openacc-l-v1"])
def test_openacc_scenarios_start_from_real_followers(sc: str) -> None:
    from envs.openacc import load_window

    scenario = make_scenario(sc)
    ep = scenario.episodes([0], 4)
    w = load_window(scenario.options["window"])
    np.testing.assert_allclose(ep.gap_m[0], w.follower_gap_m[0, :4])
    np.testing.assert_allclose(ep.speed_mps[0], w.follower_speed_mps[0, :4])
    np.testing.assert_allclose(ep.leader_speed_mps[0], w.leader_speed_mps[:601])
    if sc == "openacc-m-v1":
        assert "dynamic_part8" in scenario.note and "dynamic_part9" in scenario.note


# --------------------------------------------------------------------------- edges (mutation tests)
@pytest.mark.parametrize("bad", [-1, 4])
def test_actions_outside_the_set_are_refused(bad: int) -> None:
    from envs.dynamics import action_to_command_mps2

    z = np.zeros((1, 2))
    with pytest.raises(ValueError, match=r"actions must be in 0\.\.3"):
        action_to_command_mps2(np.array([[0, bad]]), z + 20.0, z + 15.0, z + 15.0)
    # both ends inside are fine
    action_to_command_mps2(np.array([[0, 3]]), z + 20.0, z + 15.0, z + 15.0)


def test_the_commands_use_the_given_ovm_parameters() -> None:
    """Another OVM (gap_go 25 m): V(15) = 15 (1 - cos(pi/2)) = 15, so action 1 at gap 15 m and
    speed 0 commands 0.5 * 15 = 7.5 m/s^2 (unclipped), not the default's 0.5 * 7.5."""
    from envs.dynamics import action_to_command_mps2, ovm_command_mps2

    p = PlatoonParams(gap_go_m=25.0)
    z = np.zeros((1, 1))
    assert action_to_command_mps2(np.array([[1]]), z + 15.0, z, z, p)[0, 0] == pytest.approx(7.5)
    assert ovm_command_mps2(z + 15.0, z, z, 0.5, 0.0, p)[0, 0] == pytest.approx(7.5)
    assert action_to_command_mps2(np.array([[1]]), z + 15.0, z, z)[0, 0] == pytest.approx(3.75)
    from envs.dynamics import vehicle_blocks

    # observation block 2, (V(gap) - v) / 5: 15 / 5 clipped to 2 with these parameters, 1.5 by default
    assert vehicle_blocks(z + 15.0, z, z, z, 20.0, 15.0, p)[0, 0, 2] == pytest.approx(2.0)
    assert vehicle_blocks(z + 15.0, z, z, z, 20.0, 15.0)[0, 0, 2] == pytest.approx(1.5)


def test_observation_clips_at_plus_minus_two() -> None:
    """Blocks 1 and 2 are clipped to [-2, 2]: a predecessor 20 m/s faster or slower, and an
    optimal speed 30 m/s above or the car 30 m/s above it (published)."""
    from envs.dynamics import vehicle_blocks

    gap = np.array([[40.0, 3.0]])
    v = np.array([[0.0, 30.0]])
    vp = np.array([[20.0, 10.0]])
    b = vehicle_blocks(gap, v, vp, np.zeros((1, 2)), 20.0, 15.0)
    np.testing.assert_allclose(b[0, :, 1], [2.0, -2.0])
    np.testing.assert_allclose(b[0, :, 2], [2.0, -2.0])


def test_reward_terms_without_power_and_the_default_combination() -> None:
    from envs.dynamics import combine_reward, reward_terms

    g = np.array([[22.0]])
    terms = reward_terms(g, g * 0 + 15.0, g * 0, None, 20.0, 15.0)
    np.testing.assert_array_equal(terms["power"], [[0.0]])
    with_power = reward_terms(g, g * 0 + 15.0, g * 0, np.array([[2.0]]), 20.0, 15.0)
    # the default includes the power term: -4 (gap) - 10 * 2 (power)
    assert combine_reward(with_power, training=False)[0, 0] == pytest.approx(-24.0)
    assert combine_reward(with_power, training=False, include_power=False)[0, 0] == -4.0
