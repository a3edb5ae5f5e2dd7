"""``ring-v1``: the ring road without a leader (conservation of its length, the waves the
humans make, the refusals)."""

from __future__ import annotations

import numpy as np
import pytest

from envs.humans import idm_equilibrium_speed_mps
from envs.platoon import PlatoonEnv
from envs.scenarios import RING_VEHICLE_LENGTH_M, make_scenario
from infra.errors import ConfigError


def test_the_ring_starts_near_uniform_spacing_at_the_idm_equilibrium() -> None:
    sc = make_scenario("ring-v1")
    assert sc.default_vehicles == 22 and sc.n_steps == 3000 and sc.ring
    assert sc.target_gap_m == pytest.approx(260 / 22 - 5)
    assert sc.target_speed_mps == pytest.approx(idm_equilibrium_speed_mps(260 / 22 - 5))
    ep = sc.episodes([0, 1], 22)
    np.testing.assert_allclose(ep.gap_m.sum(axis=1), 260 - 22 * RING_VEHICLE_LENGTH_M)
    assert np.abs(ep.gap_m - sc.target_gap_m).max() <= 2.0  # two shifts of at most 1 m
    assert not np.array_equal(ep.gap_m[0], ep.gap_m[1])


def test_the_ring_keeps_its_length_and_waves_form_among_idm_humans() -> None:
    sc = make_scenario("ring-v1:cavs=0")
    env = PlatoonEnv(sc, 22, observe=False)
    env.reset([0, 1, 2])
    free_m = 260 - 22 * RING_VEHICLE_LENGTH_M
    v = []
    for _ in range(sc.n_steps):
        env.step(np.zeros((3, 22)))
        s = env.state
        assert s is not None
        np.testing.assert_allclose(s.gap_m.sum(axis=1), free_m, rtol=0, atol=1e-9)
        v.append(s.speed_mps[:, -1].copy())
    assert s is not None and not s.collided.any()
    last = np.array(v)[600:]  # after the first minute
    assert (last.std(axis=0) >= 1.0).all()  # stop-and-go waves


def test_follower_one_follows_follower_n() -> None:
    env = PlatoonEnv("ring-v1:cav_fraction=1.0", 22, observe=False)
    env.reset([0])
    s = env.state
    assert s is not None
    s.speed_mps[0, -1] = 7.0
    assert s.pred_speed_mps[0, 0] == 7.0
    assert s.leader_speed_now_mps[0] == 7.0


@pytest.mark.parametrize("text", ["ring-v1:length_m=50", "ring-v1:vehicles=1",
                                  "ring-v1:perturbation_m=9"])
def test_impossible_rings_are_refused(text: str) -> None:
    with pytest.raises(ConfigError):
        make_scenario(text)


def test_the_ring_count_is_its_option_not_a_platoon_size() -> None:
    sc = make_scenario("ring-v1")
    with pytest.raises(ConfigError, match="vehicles=10"):
        sc.episodes([0], 10)
    assert make_scenario("ring-v1:vehicles=10").episodes([0], 10).gap_m.shape == (1, 10)


def test_a_ring_longer_than_the_limit_is_refused() -> None:
    from envs.scenarios import MAX_RING_LENGTH_M

    with pytest.raises(ConfigError, match="at most"):
        make_scenario(f"ring-v1:length_m={2 * MAX_RING_LENGTH_M}")


def test_a_placement_seed_where_the_placement_is_not_random_is_refused() -> None:
    """Issue 53: ``ring-v1:placement_seed=3`` (the ring's one automated vehicle sits in front)
    was a second label of ``ring-v1``, with the same numbers."""
    with pytest.raises(ConfigError, match="add placement=random"):
        make_scenario("ring-v1:placement_seed=3")
    assert make_scenario("ring-v1:placement=random,placement_seed=3").label == \
        "ring-v1[placement=random,placement_seed=3]"

