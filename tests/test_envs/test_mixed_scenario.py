"""``mixed-v1`` and ``mixed-v2``: the training distributions (per episode a kind of disturbance
and its draws)."""

from __future__ import annotations

import numpy as np
import pytest

from envs.scenarios import (
    MIXED_KINDS,
    MIXED_V1_KINDS,
    dynamic_platform_profile_mps,
    episode_stream,
    make_scenario,
)
from infra.errors import ConfigError


def test_an_episode_is_its_seed_alone_or_in_a_batch() -> None:
    sc = make_scenario("mixed-v1")
    batch = sc.episodes(np.arange(40), 5)
    for k in (0, 17, 39):
        one = sc.episodes([k], 5)
        np.testing.assert_array_equal(one.leader_speed_mps[0], batch.leader_speed_mps[k])
        np.testing.assert_array_equal(one.gap_m[0], batch.gap_m[k])
        np.testing.assert_array_equal(one.speed_mps[0], batch.speed_mps[k])


def test_every_kind_is_drawn_about_equally() -> None:
    """Each of the four kinds is told apart by its leader: catchup and brake start at v*, a
    slowdown starts above it, a catchup leader never moves, a sine never stays put."""
    sc = make_scenario("mixed-v1", gap_spread=0.0, speed_spread_mps=0.0)
    ep = sc.episodes(np.arange(400), 4)
    lead = ep.leader_speed_mps
    slowdown = lead[:, 0] > 15.0 + 1e-9
    flat = np.all(lead == 15.0, axis=1)
    catchup = flat & (ep.gap_m[:, 0] > 20.0 * 1.5 - 1e-9)
    brake = ~slowdown & ~flat & (lead.min(axis=1) >= 3.0 - 1e-9) & np.all(
        np.diff(lead, axis=1) >= -2.5 * 0.1 - 1e-9, axis=1) & (lead.max(axis=1) <= 15.0 + 1e-9)
    sine = ~slowdown & ~flat & ~brake
    for mask in (slowdown, catchup, brake, sine):
        assert 0.15 < mask.mean() < 0.35
    assert np.all(np.abs(lead[sine] - 15.0) <= 3.0 + 1e-9)


def test_a_kind_alone_and_its_draws_stay_in_their_ranges() -> None:
    sc = make_scenario("mixed-v1", kinds="brake", brake_rate_max_mps2=2.0, gap_spread=0.1)
    ep = sc.episodes(np.arange(100), 6)
    rates = -np.diff(ep.leader_speed_mps, axis=1) / 0.1
    assert rates.max() <= 2.0 + 1e-9 and ep.leader_speed_mps.min() >= 3.0 - 1e-9
    assert np.all((ep.gap_m >= 18.0 - 1e-9) & (ep.gap_m <= 22.0 + 1e-9))
    assert np.all(np.abs(ep.speed_mps - 15.0) <= 0.5 + 1e-9)


@pytest.mark.parametrize(("options", "needle"), [
    ({"kinds": "catchup+nope"}, "kinds must join"),
    ({"kinds": "brake+brake"}, "kinds must join"),
    ({"brake_rate_max_mps2": 3.0}, "brake_rate_max_mps2"),
    ({"gap_spread": 0.6}, "gap_spread"),
])
def test_impossible_options_are_refused(options: dict, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        make_scenario("mixed-v1", **options)


def test_the_kinds_are_named_in_the_listing() -> None:
    sc = make_scenario("mixed-v1")
    assert sc.options["kinds"] == "+".join(MIXED_V1_KINDS) and sc.target_gap_m == 20.0
    assert make_scenario("mixed-v2").options["kinds"] == "+".join(MIXED_KINDS)


def test_mixed_v1_keeps_its_four_kinds() -> None:
    """The OpenACC-like leader is ``mixed-v2``'s; ``mixed-v1`` refuses it, so a v1 label keeps
    meaning the distribution its policies were trained on."""
    with pytest.raises(ConfigError, match="mixed-v1 kinds must join"):
        make_scenario("mixed-v1", kinds="openacc")


def test_mixed_v2_draws_the_openacc_like_leader() -> None:
    """About one episode in five is the Dynamic-Platform-like leader of ``openacc-train``: a
    cruise in [7.5, 12] m/s (every other kind starts at 15 m/s or above), braking at no more than
    3.5 m/s^2, with the followers starting at d* and the leader's speed; the other kinds are
    ``mixed-v1``'s builders."""
    sc = make_scenario("mixed-v2", gap_spread=0.0, speed_spread_mps=0.0)
    ep = sc.episodes(np.arange(500), 4)
    lead = ep.leader_speed_mps
    oa = lead[:, 0] < 15.0 - 1e-9
    assert 0.15 < oa.mean() < 0.25
    assert lead[oa, 0].min() >= 7.5 and lead[oa, 0].max() <= 12.0
    assert np.all(-np.diff(lead[oa], axis=1) <= 3.5 * 0.1 + 1e-9) and lead[oa].min() >= 3.0 - 1e-9
    np.testing.assert_array_equal(ep.speed_mps[oa], np.repeat(lead[oa, :1], 4, axis=1))
    np.testing.assert_array_equal(ep.gap_m[oa], 20.0)
    for k in np.flatnonzero(oa)[:5]:  # the openacc-train generator, on the episode's stream
        rng = episode_stream(int(k), "mixed")
        assert MIXED_KINDS[int(rng.integers(len(MIXED_KINDS)))] == "openacc"
        np.testing.assert_array_equal(lead[k], dynamic_platform_profile_mps(rng.random(6),
                                                                            sc.n_steps))

