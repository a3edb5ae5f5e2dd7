"""Human drivers in the string (``envs.humans``): the models against closed forms, the
arrangement options of every scenario, and the seed as the only source of the humans' draws."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.humans import (
    OVM_ALPHA_RANGE,
    OVM_GAP_GO_RANGE_M,
    HumanDrivers,
    HumanNoise,
    IDMParams,
    count_automated,
    idm_accel_mps2,
    idm_equilibrium_speed_mps,
    ovm_hetero_accel_mps2,
    place_automated,
)
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import SCENARIOS, make_scenario
from infra.errors import ConfigError


def test_idm_against_its_closed_form() -> None:
    # at rest behind a stopped car: a (1 - (s0/s)^2); s = 2 s0 gives 3/4 of a
    assert idm_accel_mps2(np.array(4.0), np.array(0.0), np.array(0.0)) == pytest.approx(0.75)
    # free road (huge gap) at v0/2: a (1 - 2^-4)
    assert idm_accel_mps2(np.array(1e9), np.array(15.0), np.array(15.0)) == pytest.approx(
        1 - 0.5 ** 4)
    # closing at 2 m/s, v = 10, s = 30: s* = 2 + 10 + 10*2/(2 sqrt(1.5))
    s_star = 2 + 10 + 20 / (2 * math.sqrt(1.5))
    want = 1 - (10 / 30) ** 4 - (s_star / 30) ** 2
    assert idm_accel_mps2(np.array(30.0), np.array(10.0), np.array(8.0)) == pytest.approx(want)


def test_idm_equilibrium_speed_solves_its_equation() -> None:
    p = IDMParams()
    for gap in (3.0, 6.818, 20.0, 60.0):
        v = idm_equilibrium_speed_mps(gap)
        assert idm_accel_mps2(np.array(gap), np.array(v), np.array(v)) == pytest.approx(
            0.0, abs=1e-9)
        assert 0 < v < p.desired_speed_mps
    assert idm_equilibrium_speed_mps(1.5) == 0.0


def test_heterogeneous_ovm_is_the_benchmark_ovm_at_the_nominal_parameters() -> None:
    from envs.dynamics import ovm_command_mps2

    g, v, vp = np.array([12.0, 25.0]), np.array([10.0, 14.0]), np.array([11.0, 13.0])
    got = ovm_hetero_accel_mps2(g, v, vp, np.array(0.6), np.array(0.9), np.array(35.0))
    np.testing.assert_allclose(got, ovm_command_mps2(g, v, vp, 0.6, 0.9))


def gaussian_noise_mps2(seeds: np.ndarray, n_seats: int, steps: int, std: float) -> np.ndarray:
    """Every seat's noise over ``steps`` steps, ``(steps, B, n_seats)``."""
    noise, seats = HumanNoise(seeds, n_seats, steps, std), np.arange(n_seats)
    return np.stack([noise.at(t, seats) for t in range(steps)])


def test_noise_is_gaussian_with_its_std_and_a_function_of_the_seed_alone() -> None:
    x = gaussian_noise_mps2(np.arange(200), 8, 100, 0.2)
    assert x.shape == (100, 200, 8)
    assert abs(x.mean()) < 0.005 and x.std() == pytest.approx(0.2, rel=0.02)
    one = gaussian_noise_mps2(np.array([57]), 8, 100, 0.2)
    np.testing.assert_array_equal(one[:, 0], x[:, 57])
    fewer_seats = gaussian_noise_mps2(np.array([57]), 3, 100, 0.2)
    np.testing.assert_array_equal(fewer_seats[:, 0], x[:, 57, :3])  # a seat's noise is its own
    assert np.unique(x).size > 0.9 * min(x.size, 1 << 16)  # the 2^16 levels are all in use


@pytest.mark.parametrize(("share", "n", "k"), [(0.0, 8, 0), (0.05, 8, 1), (0.25, 8, 2),
                                               (0.5, 8, 4), (0.75, 22, 17), (1.0, 8, 8),
                                               (0.5, 5, 3)])
def test_a_share_counts_half_up_and_a_positive_share_keeps_one_vehicle(share: float, n: int,
                                                                       k: int) -> None:
    assert count_automated(share, n) == k


def test_placements() -> None:
    np.testing.assert_array_equal(place_automated(2, 8, "front", 0), [0, 1])
    np.testing.assert_array_equal(place_automated(2, 8, "rear", 0), [6, 7])
    np.testing.assert_array_equal(place_automated(4, 8, "spread", 0), [0, 2, 4, 6])
    a = place_automated(3, 8, "random", 5)
    np.testing.assert_array_equal(a, place_automated(3, 8, "random", 5))
    assert len(set(a.tolist())) == 3 and all(0 <= s < 8 for s in a)
    draws = {tuple(place_automated(3, 8, "random", s).tolist()) for s in range(20)}
    assert len(draws) > 10  # seeds give other placements


def test_arrangement_options_on_every_scenario() -> None:
    for sid, spec in SCENARIOS.items():
        sc = make_scenario(sid, humans="1")
        n = sc.default_vehicles
        assert sc.arrangement(n).automated[0] is False
        assert sc.label == f"{sid}[humans=1]"
        if not spec.ring:  # the published default: every follower automated
            assert make_scenario(sid).arrangement(n).homogeneous


def test_labels_carry_the_arrangement_and_defaults_add_nothing() -> None:
    assert make_scenario("catchup-v1", cav_fraction="0.5").label == \
        "catchup-v1[cav_fraction=0.5]"
    assert make_scenario("catchup-v1", cav_fraction="1").label == "catchup-v1"
    assert make_scenario("catchup-v1:humans=2+5").arrangement(8).automated == (
        True, False, True, True, False, True, True, True)
    # ring-v1's default is one automated vehicle: asking for all of them is a label of its own
    ring = make_scenario("ring-v1")
    assert ring.arrangement(22).n_automated == 1
    assert make_scenario("ring-v1:cav_fraction=1.0").label == "ring-v1[cav_fraction=1.0]"
    assert make_scenario("ring-v1:cav_fraction=1.0").arrangement(22).homogeneous
    assert make_scenario("ring-v1:cavs=0").arrangement(22).n_automated == 0


@pytest.mark.parametrize("options", [
    {"humans": "9"}, {"humans": "0"}, {"humans": "2+2"}, {"humans": "x"},
    {"cav_fraction": "1.5"}, {"cav_fraction": "-0.1"}, {"cav_fraction": "nan"},
    {"cavs": "9"}, {"cavs": "-2"}, {"cav_fraction": "0.5", "humans": "2"},
    {"placement": "middle"}, {"human_model": "krauss"}, {"reaction_delay_s": "5"},
    {"human_noise_mps2": "-1"}, {"placement_seed": "-1"},
    {"placement_seed": "99999999999999999999"},
    # issue 53: given options that would silently mean something else, or nothing
    {"humans": ""}, {"cavs": "-1"}, {"humans": "2", "placement": "front"},
    {"humans": "2", "placement_seed": "1"},
    {"cav_fraction": "0.5", "placement": "front", "placement_seed": "3"},
    {"reaction_delay_s": "0.05"},
])
def test_arrangements_that_make_no_sense_are_refused(options: dict[str, str]) -> None:
    with pytest.raises(ConfigError):
        make_scenario("catchup-v1", **options).arrangement(8)


def test_every_controller_meets_the_same_humans_on_the_same_seed() -> None:
    """The humans' parameters and noise come from the episode seed alone: two envs stepped by
    different commands, and one episode alone or in a batch, give the humans the same draws."""
    sc = make_scenario("catchup-v1:humans=2+5+7,human_model=ovm")
    a, b = PlatoonEnv(sc, 8, observe=False), PlatoonEnv(sc, 8, observe=False)
    a.reset([3, 4, 5])
    b.reset([4])
    ha, hb = a._humans, b._humans
    assert isinstance(ha, HumanDrivers) and isinstance(hb, HumanDrivers)
    np.testing.assert_array_equal(ha.alpha[1], hb.alpha[0])
    np.testing.assert_array_equal(ha.gap_go_m[1], hb.gap_go_m[0])
    seats = np.arange(8)
    for t in (0, 1, 299, 599):
        np.testing.assert_array_equal(ha.noise.at(t, seats)[1], hb.noise.at(t, seats)[0])
    assert OVM_ALPHA_RANGE[0] <= ha.alpha.min() and ha.alpha.max() <= OVM_ALPHA_RANGE[1]
    assert OVM_GAP_GO_RANGE_M[0] <= ha.gap_go_m.min() <= ha.gap_go_m.max() <= 39.0
    # whatever the controllers command, a human seat gets its model's command: drive two envs
    # with opposite commands and check seat 2's command against its model at each step
    for env in (a, b):
        env.reset([4])
    for t in range(50):
        for env, u in ((a, -2.0), (b, 2.0)):
            s = env.state
            assert s is not None and env._humans is not None
            want = env._humans.commands(t, np.full((1, 8), u), s.gap_m, s.speed_mps,
                                        s.leader_speed_now_mps)
            env._humans._history.clear()
            assert want[0, 0] == u and want[0, 2] == u  # automated seats keep the command
            ovm = ovm_hetero_accel_mps2(s.gap_m[0, 1], s.speed_mps[0, 1], s.speed_mps[0, 0],
                                        env._humans.alpha[0, 1], env._humans.beta[0, 1],
                                        env._humans.gap_go_m[0, 1])
            assert want[0, 1] == pytest.approx(ovm + env._humans.noise.at(t, seats)[0, 1])
            env.step(np.full((1, 8), u))


def test_a_human_seat_drives_by_its_model_and_takes_no_command() -> None:
    sc = make_scenario("catchup-v1:humans=1,human_noise_mps2=0")
    env = PlatoonEnv(sc, 2, observe=False)
    env.reset([0])
    s = env.state
    assert s is not None
    want = idm_accel_mps2(s.gap_m[0, 0], s.speed_mps[0, 0], s.pred_speed_mps[0, 0])
    v0 = s.speed_mps[0, 0]
    env.step(np.array([[2.5, 0.0]]))  # the command of seat 1 is ignored
    assert (s.speed_mps[0, 0] - v0) / 0.1 == pytest.approx(
        float(np.clip(want, PlatoonParams().accel_min_mps2, PlatoonParams().accel_max_mps2)))


def test_reaction_delay_acts_on_what_was_seen_that_long_ago() -> None:
    sc0 = make_scenario("brake-v1:humans=1,human_noise_mps2=0")
    sc5 = make_scenario("brake-v1:humans=1,human_noise_mps2=0,reaction_delay_s=0.5")
    runs = []
    for sc in (sc0, sc5):
        env = PlatoonEnv(sc, 2, observe=False)
        env.reset([0])
        v = []
        for _ in range(200):
            env.step(np.zeros((1, 2)))
            assert env.state is not None
            v.append(env.state.speed_mps[0, 0])
        runs.append(np.array(v))
    # the leader brakes at 10 s (step 100): the delayed human starts braking 5 steps later
    first = [int(np.flatnonzero(np.diff(r) < -0.05)[0]) for r in runs]
    assert first[1] - first[0] == 5


def test_homogeneous_scenarios_have_no_humans() -> None:
    env = PlatoonEnv("catchup-v1", 8, observe=False)
    env.reset([0])
    assert env._humans is None and env.state is not None and env.state.automated is None


def test_one_arrangement_of_human_positions_is_one_label() -> None:
    """Issue 53: ``humans=5+2``, ``02+5`` and ``2 + 5`` were three labels (three leaderboard
    rows) of the arrangement ``humans=2+5``."""
    labels = {make_scenario(f"catchup-v1:humans={text}").label
              for text in ("2+5", "5+2", "02+5", "2 + 5")}
    assert labels == {"catchup-v1[humans=2+5]"}


@pytest.mark.parametrize("options", [{"cav_fraction": 0.0}, {"humans": "1+2"}])
def test_the_adapters_refuse_a_string_with_no_automated_follower(options: dict) -> None:
    """Issue 53: the Gymnasium and PettingZoo views ran an all-human string, ignoring every
    action, where ``run`` refuses an automated controller."""
    from envs.adapters import PlatoonGymEnv, PlatoonParallelEnv

    for cls in (PlatoonGymEnv, PlatoonParallelEnv):
        with pytest.raises(ConfigError, match="no automated follower"):
            cls("catchup-v1", n_vehicles=2, **options)
