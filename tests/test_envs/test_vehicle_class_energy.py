"""Energy per vehicle class (issue 55): the physics model against published consumption on the
NEDC, built from its published definition; the i3 seats keep the benchmark's polynomial."""

from __future__ import annotations

import numpy as np
import pytest

from envs.energy import battery_power_kw
from envs.energy.classes import (
    DragSaving,
    class_power_kw,
    cycle_kwh_per_100km,
    drag_reduction,
    ece15_speed_mps,
    nedc_speed_mps,
)
from envs.platoon import PlatoonEnv
from envs.scenarios import make_scenario
from envs.vehicle_classes import VEHICLE_CLASSES

#: Published NEDC consumption (kWh/100 km, at the mains: charging losses included) and the
#: model's stated agreement: the battery-side model lies below by at most this share
#: (docs/vehicle-classes.md, "Energy").
PUBLISHED_NEDC = {
    # BMW i3 (2016, 125 kW): "13.6-13.1" kWh/100 km NEDC combined, BMW technical data
    "i3": 13.1,
    # small car: VW e-up! (1,139 kg), 11.7 kWh/100 km, Volkswagen at its 2013 launch
    "car": 11.7,
}
TOLERANCE = 0.15


def test_nedc_trace_has_the_published_length_and_distance() -> None:
    v = nedc_speed_mps(0.1)
    assert len(v) == 11801  # 1180 s
    distance_km = float(np.sum(0.5 * (v[1:] + v[:-1])) * 0.1) / 1000
    assert distance_km == pytest.approx(11.007, rel=0.005)  # UNECE R83: 11.007 km
    assert v.max() == pytest.approx(120 / 3.6)


@pytest.mark.parametrize("name", sorted(PUBLISHED_NEDC))
def test_class_consumption_matches_its_published_figure(name: str) -> None:
    cls = VEHICLE_CLASSES[name]
    v = nedc_speed_mps(0.1)
    if cls.powertrain == "i3-map":
        model = cycle_kwh_per_100km(lambda s, u: battery_power_kw(s, u, "map"), v, 0.1)
    else:
        model = cycle_kwh_per_100km(lambda s, u: class_power_kw(cls, s, u), v, 0.1)
    published = PUBLISHED_NEDC[name]
    assert (1 - TOLERANCE) * published <= model <= published, (name, model)


def test_physics_model_against_hand_numbers() -> None:
    bus = VEHICLE_CLASSES["bus"]
    # 15 m/s, steady: (m g c_rr + rho/2 Cd A v^2) v / eta + aux
    road_n = 12156 * 9.81 * 0.00938 + 0.5 * 1.204 * 0.79 * 7.9 * 225
    assert class_power_kw(bus, 15.0, 0.0) == pytest.approx(road_n * 15 / 0.85 / 1000 + 5.0)
    # hard braking is capped by the regeneration limit
    assert class_power_kw(bus, 15.0, -3.0) == pytest.approx(-150.0 + 5.0)


def test_i3_seats_keep_the_polynomial_and_others_their_class() -> None:
    env = PlatoonEnv(make_scenario("catchup-v1:classes=i3+bus"), 2, observe=False)
    env.reset([2000])
    v = np.array([[15.0, 15.0]])
    u = np.array([[0.5, 0.5]])
    p = env.battery_power_kw(v, u)
    assert p[0, 0] == pytest.approx(float(battery_power_kw(15.0, 0.5)))
    assert p[0, 1] == pytest.approx(float(class_power_kw(VEHICLE_CLASSES["bus"], 15.0, 0.5)))


#: The heavier classes against published figures (docs/vehicle-classes.md, "Energy"): each a
#: (cycle, published kWh/100 km, lowest ratio model/published, highest ratio).
HEAVY_PUBLISHED = {
    # VW e-Crafter (2,540 kg, top speed 90 km/h): NEDC 20 kWh/100 km (eurotransport.de, first
    # drive, 2017-09); the NEDC driven up to the van's 90 km/h; at the mains, one-sided 15 %
    "van": ("nedc-90", 20.0, 0.85, 1.0),
    # Proterra 35 ft battery-electric buses, Foothill Transit line 291 (NREL evaluation, Eudy et
    # al. 2016): 2.15 kWh/mile = 133.6 kWh/100 km over 399,663 miles in service, more than half
    # of the time standing with lights and HVAC on; the urban ECE-15 part (31 % standing, moving
    # mean 27.3 km/h against the buses' logged 17.8 mph = 28.6 km/h): the model lies below by at
    # most 40 % (the standing HVAC load of the field average is not in a 5 kW auxiliary load)
    "bus": ("ece15", 2.15 / 1.609344 * 100, 0.60, 1.0),
    # battery-electric tractor-trailers above 30 t in European regional fleets (ICCT 2025,
    # 91 trucks): 92 to 150 kWh/100 km; a bracket, not the same vehicle (the preset is 18.5 t)
    "truck": ("nedc", 121.0, 92.0 / 121.0, 150.0 / 121.0),
}


def _cycle(name: str) -> np.ndarray:
    if name == "nedc":
        return nedc_speed_mps(0.1)
    if name == "nedc-90":
        return np.minimum(nedc_speed_mps(0.1), 90 / 3.6)
    return ece15_speed_mps(0.1)


@pytest.mark.parametrize("name", sorted(HEAVY_PUBLISHED))
def test_heavy_class_consumption_against_its_published_figure(name: str) -> None:
    cycle, published, lo, hi = HEAVY_PUBLISHED[name]
    cls = VEHICLE_CLASSES[name]
    model = cycle_kwh_per_100km(lambda s, u: class_power_kw(cls, s, u), _cycle(cycle), 0.1)
    assert lo * published <= model <= hi * published, (name, model, published)


def test_ece15_cycle_has_the_published_length() -> None:
    v = ece15_speed_mps(0.1, 1)
    assert len(v) == 1951  # 195 s
    # UNECE R83: 1.013 km (the gear-change pauses held as linear ramps: within 0.6 %)
    assert float(np.sum(0.5 * (v[1:] + v[:-1])) * 0.1) == pytest.approx(1013, rel=0.006)


def test_drag_reduction_passes_through_the_measured_points() -> None:
    r = drag_reduction(np.array([0.2, 0.5, 3.0, 6.0]))
    assert r[0] == pytest.approx(0.43) and r[1] == pytest.approx(0.43)  # held below L/2
    assert r[2] == pytest.approx(0.20)
    assert 0 < r[3] < r[2]  # decays with the gap


def test_drag_saving_scales_only_the_drag_term() -> None:
    van, car = VEHICLE_CLASSES["van"], VEHICLE_CLASSES["car"]
    saving = DragSaving((van, car))
    gap = np.array([[3.25, 13.0]])  # half a van length behind the leader (a van), 2 van lengths
    v = np.array([[20.0, 20.0]])
    u = np.array([[0.0, 0.0]])
    d = saving.delta_kw(gap, v, u)
    drag_w = 0.5 * 1.204 * np.array([van.drag_coeff * van.frontal_area_m2,
                                     car.drag_coeff * car.frontal_area_m2]) * 20.0 ** 3
    r = drag_reduction(np.array([0.5, 2.0]))
    np.testing.assert_allclose(d[0], -r * drag_w / 0.85 / 1000)


def test_drag_saving_is_off_by_default_and_lowers_the_energy_when_on() -> None:
    from benchmark.metrics import run_metrics
    from benchmark.rollout import rollout
    from controllers.registry import make_controller

    out = {}
    for label in ("catchup-v1:classes=bus+van+car*2", "catchup-v1:classes=bus+van+car*2,"
                  "drag_saving=cerutti2021"):
        sc = make_scenario(label)
        traj = rollout(make_controller("cacc"), sc, 4, 2000)
        out[label] = run_metrics(traj, sc.target_gap_m, sc.target_speed_mps)
    off, on = out.values()
    assert off["energy_drag_saving"] == "none" and on["energy_drag_saving"] == "cerutti2021"
    assert off["gap_mean_m"] == on["gap_mean_m"]  # energy only: the motion is the same
    for c in ("bus", "van", "car"):
        assert on[f"energy_kwh_per_100km_{c}"] < off[f"energy_kwh_per_100km_{c}"]
    assert np.isnan(off["energy_kwh_per_100km_truck"])  # a class not in the string


def test_drag_saving_name_is_checked() -> None:
    from infra.errors import ConfigError

    with pytest.raises(ConfigError, match="drag_saving must be one of none, cerutti2021"):
        make_scenario("catchup-v1:drag_saving=zabat")
