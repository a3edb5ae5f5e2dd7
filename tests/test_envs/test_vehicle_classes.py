"""Vehicle classes (issue 55): presets, the arrangement grammar, per-vehicle lags and bounds in
the batched dynamics, with the homogeneous platoon untouched."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.dynamics import physics_step
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import make_scenario
from envs.vehicle_classes import (
    VEHICLE_CLASSES,
    canonical_classes,
    parse_class_sequence,
    zheng_lag_s,
)
from infra.errors import ConfigError


def test_presets_cover_the_issue_classes_and_keep_their_sources() -> None:
    assert {"car", "i3", "van", "bus", "truck"} <= set(VEHICLE_CLASSES)
    i3 = VEHICLE_CLASSES["i3"]
    # the i3 class is the energy model's car (SUMO MMPEVEM data, docs/spec/energy.md)
    assert (i3.mass_kg, i3.drag_coeff, i3.frontal_area_m2, i3.rolling_coeff) == (
        1417.0, 0.29, 2.38, 0.007)
    bus = VEHICLE_CLASSES["bus"]  # ADVISOR VEH_RTS06 and SUMO's bus defaults
    assert (bus.mass_kg, bus.drag_coeff, bus.frontal_area_m2, bus.accel_max_mps2) == (
        12156.0, 0.79, 7.9, 1.2)
    for c in VEHICLE_CLASSES.values():
        assert c.sources.strip()
    # Zheng et al.'s rule at the ends of its range: 1036 kg -> 0.51 s, 1934 kg -> 0.78 s
    assert zheng_lag_s(1036.0) == pytest.approx(0.5108)
    assert zheng_lag_s(1934.0) == pytest.approx(0.7802)
    assert zheng_lag_s(5000.0) == pytest.approx(0.8)


def test_grammar_expands_repeats_and_writes_one_spelling() -> None:
    assert parse_class_sequence("bus+van+car*3") == ("bus", "van", "car", "car", "car")
    assert canonical_classes(("car", "car", "van", "car")) == "car*2+van+car"
    a = make_scenario("catchup-v1:classes=bus+van+car+car*5")
    b = make_scenario("catchup-v1[classes=bus+van+car*6]")
    assert a.label == b.label == "catchup-v1[classes=bus+van+car*6]"
    assert [c.name for c in a.vehicle_classes(8)] == ["bus", "van"] + ["car"] * 6
    assert make_scenario("catchup-v1").vehicle_classes(8) is None


def test_seeded_mix_is_a_fixed_shuffle_of_the_multiset() -> None:
    names = [c.name for c in make_scenario("catchup-v1:class_mix=car*6+van+bus,class_seed=3")
             .vehicle_classes(8)]
    assert sorted(names) == sorted(["car"] * 6 + ["van", "bus"])
    again = [c.name for c in make_scenario("catchup-v1:class_mix=car*6+van+bus,class_seed=3")
             .vehicle_classes(8)]
    assert names == again
    others = {tuple(c.name for c in make_scenario(
        f"catchup-v1:class_mix=car*6+van+bus,class_seed={s}").vehicle_classes(8))
        for s in range(6)}
    assert len(others) > 1  # the seed moves them


@pytest.mark.parametrize("label", [
    "catchup-v1:classes=plane*8", "catchup-v1:classes=car*0", "catchup-v1:classes=car*x",
    "catchup-v1:classes=car++van", "catchup-v1:classes=", "catchup-v1:class_seed=2",
    "catchup-v1:classes=car*8,class_mix=car*8", "catchup-v1:class_mix=car*8,class_seed=-1",
])
def test_bad_classes_are_refused_when_parsed(label: str) -> None:
    with pytest.raises(ConfigError):
        make_scenario(label)


def test_a_sequence_of_the_wrong_length_is_refused_with_the_count() -> None:
    from envs.scenarios import check_size_fits

    sc = make_scenario("catchup-v1:classes=bus+car*6")
    with pytest.raises(ConfigError, match="names 7 vehicles but the run has 8"):
        check_size_fits(sc, 8)
    check_size_fits(sc, 7)


def test_classes_combine_with_humans() -> None:
    sc = make_scenario("catchup-v1:classes=car+van+car*6,humans=2")
    env = PlatoonEnv(sc, 8, observe=False)
    env.reset([2000])
    assert not env.state.automated_mask[1] and env.vehicles.names[1] == "van"
    for _ in range(50):
        env.step(np.zeros((1, 8)))
    assert np.isfinite(env.state.speed_mps).all()


def test_homogeneous_default_path_is_unchanged() -> None:
    """The default (no classes) runs the published code: bit-identical to the formula."""
    rng = np.random.default_rng(1)
    b, n = 5, 4
    gap, v = rng.uniform(10, 30, (b, n)), rng.uniform(0, 30, (b, n))
    u = rng.normal(0, 3, (b, n))
    p = PlatoonParams()
    _, v_next, a, _ = physics_step(gap, v, np.zeros((b, n)), u, np.full(b, 15.0),
                                   np.full(b, 15.0), p)
    assert np.array_equal(a, np.clip(u, -2.5, 2.5))
    assert np.array_equal(v_next, np.clip(v + np.clip(u, -2.5, 2.5) * 0.1, 0, 30))


def test_one_class_string_equals_the_homogeneous_env_with_its_lag() -> None:
    """A string of i3s (lag 0.625 s, bounds within +-2.5) steps bit for bit as the homogeneous
    env with ``lag_s`` 0.625: the per-vehicle path computes what the scalar one does."""
    lag = VEHICLE_CLASSES["i3"].lag_s
    e1 = PlatoonEnv(make_scenario("slowdown-v1:classes=i3*4"), 4, observe=False)
    e2 = PlatoonEnv("slowdown-v1", 4, PlatoonParams(lag_s=lag), observe=False)
    e1.reset([2000, 2010])
    e2.reset([2000, 2010])
    rng = np.random.default_rng(0)
    for _ in range(300):
        u = rng.normal(0, 2, (2, 4))
        r1, r2 = e1.step(u), e2.step(u)
        assert np.array_equal(r1.reward, r2.reward)
        assert np.array_equal(e1.state.speed_mps, e2.state.speed_mps)
        assert np.array_equal(e1.state.command_mps2, e2.state.command_mps2)


def test_each_vehicle_gets_its_own_lag_and_bounds() -> None:
    env = PlatoonEnv(make_scenario("catchup-v1:classes=bus+car"), 2, observe=False)
    env.reset([2000])
    res = env.step(np.array([[3.0, -3.0]]))
    bus, car = VEHICLE_CLASSES["bus"], VEHICLE_CLASSES["car"]
    # one step of the lag from rest: a = g u with g = 1 - exp(-dt/tau), u clipped per vehicle
    expected = [bus.accel_max_mps2 * (1 - math.exp(-0.1 / bus.lag_s)),
                -2.5 * (1 - math.exp(-0.1 / car.lag_s))]
    assert env.state.realised_accel_mps2[0] == pytest.approx(expected, rel=1e-12)
    assert env.state.command_mps2[0].tolist() == [bus.accel_max_mps2, -2.5]
    assert res.power_kw.shape == (1, 2)


def test_a_run_wide_lag_with_classes_is_refused() -> None:
    with pytest.raises(ConfigError, match="leave the lag out"):
        PlatoonEnv(make_scenario("catchup-v1:classes=car*4"), 4,
                   PlatoonParams(lag_s=0.2)).reset([1])
