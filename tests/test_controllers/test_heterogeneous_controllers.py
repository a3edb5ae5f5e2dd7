"""Controllers on a string of vehicle classes (issue 55): each uses its vehicles' own lag and
bounds where it models them; the paper's policies and the centralised MPC are refused."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.rollout import rollout
from controllers.registry import check_fits, make_controller, parse_controller_list
from envs.params import PlatoonParams
from envs.scenarios import make_scenario
from envs.vehicle_classes import VEHICLE_CLASSES
from infra.errors import ConfigError

HEAVY_FIRST = "brake-v1:classes=bus+van+car*6"


def _ctrl(text: str):  # noqa: ANN202 - a controller
    [(name, opts)] = parse_controller_list(text)
    return make_controller(name, **opts)


def test_xiao_rule_gives_each_vehicle_its_time_gap_and_standstill() -> None:
    sc = make_scenario(HEAVY_FIRST)
    ctrl = _ctrl("cacc:time_gap_rule=xiao")
    rollout(ctrl, sc, 8, 2000, PlatoonParams())
    lags = np.array([c.lag_s for c in sc.vehicle_classes(8)])
    h = np.maximum(0.5, 2 * lags)  # no V2V delay
    assert np.array_equal(ctrl._h, h)
    assert np.allclose(ctrl.standstill_m, 20.0 - h * 15.0)
    # the fixed rule keeps the scalar law
    fixed = _ctrl("cacc")
    rollout(fixed, sc, 8, 2000, PlatoonParams())
    assert np.all(fixed._h == 0.5)


def test_loop_stability_is_checked_for_every_class_lag() -> None:
    # kd = 0.3 < tau kp = 0.8 * 0.5 for the bus: refused before work
    with pytest.raises(ConfigError, match="unstable with this actuator lag"):
        check_fits(_ctrl("cacc:kp=0.5,kd=0.3"), make_scenario(HEAVY_FIRST), 8, PlatoonParams())
    check_fits(_ctrl("cacc:kp=0.5,kd=0.3"), make_scenario("brake-v1"), 8, PlatoonParams())


def test_mpc_builds_one_problem_per_class_and_keeps_the_string_safe() -> None:
    sc = make_scenario("catchup-v1:classes=car*3+van+car*3+bus")
    ctrl = _ctrl("mpc-qp")
    traj = rollout(ctrl, sc, 8, 2000, PlatoonParams())
    assert not traj.collided
    built = sorted((p.lag_s, p.accel_max_mps2) for p, _ in ctrl._groups)
    assert built == sorted((VEHICLE_CLASSES[n].lag_s, min(VEHICLE_CLASSES[n].accel_max_mps2, 2.5))
                           for n in ("car", "van", "bus"))
    bus_params = next(p for p, seats in ctrl._groups if seats.tolist() == [7])
    assert bus_params.accel_max_mps2 == VEHICLE_CLASSES["bus"].accel_max_mps2
    assert np.all(traj.command_mps2[:, -1] <= bus_params.accel_max_mps2 + 1e-12)


def test_safety_filter_uses_each_class_and_prevents_the_collision_acc_makes() -> None:
    sc = make_scenario(HEAVY_FIRST)
    assert rollout(_ctrl("acc"), sc, 8, 2000, PlatoonParams()).collided
    safe = rollout(_ctrl("safe:acc"), sc, 8, 2000, PlatoonParams())
    assert not safe.collided


@pytest.mark.parametrize("name", ["bdc", "cmpc"])
def test_models_of_one_vehicle_are_refused_with_what_runs(name: str) -> None:
    with pytest.raises(ConfigError, match="mpc, mpc-qp"):
        check_fits(_ctrl(name), make_scenario(HEAVY_FIRST), 8, PlatoonParams())
