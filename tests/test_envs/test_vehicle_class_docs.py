"""The vehicle-classes page quotes the presets and the energy check as the code has them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from envs.energy import battery_power_kw
from envs.energy.classes import class_power_kw, cycle_kwh_per_100km, nedc_speed_mps
from envs.vehicle_classes import VEHICLE_CLASSES

PAGE = Path(__file__).resolve().parents[2] / "docs" / "vehicle-classes.md"


def _rows(header: str) -> list[list[str]]:
    lines = PAGE.read_text().splitlines()
    start = lines.index(header)
    out = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        out.append([c.strip() for c in line.strip("|").split("|")])
    return out


def test_class_table_is_the_presets() -> None:
    rows = _rows("| class | mass kg | C_d | A m^2 | c_rr | lag s | accel / decel m/s^2 | length m "
                 "| powertrain |")
    assert [r[0] for r in rows] == list(VEHICLE_CLASSES)
    for name, mass, cd, area, crr, lag, bounds, length, powertrain in rows:
        c = VEHICLE_CLASSES[name]
        accel, decel = (float(x) for x in bounds.split("/"))
        assert (float(mass), float(cd), float(area), float(crr), float(lag), accel, decel,
                float(length), powertrain) == (c.mass_kg, c.drag_coeff, c.frontal_area_m2,
                                               c.rolling_coeff, c.lag_s, c.accel_max_mps2,
                                               c.decel_max_mps2, c.length_m, c.powertrain)


def test_energy_table_is_what_the_models_give() -> None:
    from test_vehicle_class_energy import HEAVY_PUBLISHED, PUBLISHED_NEDC, _cycle

    rows = _rows("| class | cycle | model kWh/100 km | published kWh/100 km | agreement | source |")
    assert sorted(r[0] for r in rows) == sorted(VEHICLE_CLASSES)
    for name, _, model, published, _, _ in rows:
        cls = VEHICLE_CLASSES[name]
        if cls.powertrain == "i3-map":
            got = cycle_kwh_per_100km(lambda s, u: np.asarray(battery_power_kw(s, u, "map")),
                                      nedc_speed_mps(0.1), 0.1)
        else:
            cycle = HEAVY_PUBLISHED[name][0] if name in HEAVY_PUBLISHED else "nedc"
            got = cycle_kwh_per_100km(lambda s, u, c=cls: class_power_kw(c, s, u),
                                      _cycle(cycle), 0.1)
        assert float(model.split()[0]) == pytest.approx(round(got, 1))
        if name in PUBLISHED_NEDC:
            assert float(published) == PUBLISHED_NEDC[name]
        elif name == "truck":
            lo, hi = (float(x) for x in published.split("-"))
            _, mid, rlo, rhi = HEAVY_PUBLISHED[name]
            assert (lo, hi) == pytest.approx((mid * rlo, mid * rhi))
        else:
            assert float(published.split()[0]) == pytest.approx(
                round(HEAVY_PUBLISHED[name][1], 1))


def test_drag_table_is_the_model() -> None:
    from envs.energy.classes import drag_reduction

    rows = _rows("| gap / predecessor length | 0.5 | 1 | 2 | 3 | 4.5 | 6 |")
    head = [float(x) for x in "0.5 1 2 3 4.5 6".split()]
    got = [f"{round(100 * r):.0f} %" for r in drag_reduction(np.array(head))]
    assert rows[0][1:] == got


def test_drag_saving_numbers_of_the_page() -> None:
    """The page's catchup-v1 example (cacc, seed 2000), with and without the drag saving."""
    from benchmark.metrics import run_metrics
    from benchmark.rollout import rollout
    from controllers.registry import make_controller
    from envs.scenarios import make_scenario

    text = PAGE.read_text()

    def energy(label: str) -> float:
        sc = make_scenario(label)
        m = run_metrics(rollout(make_controller("cacc"), sc, 8, 2000), sc.target_gap_m,
                        sc.target_speed_mps)
        return float(m["energy_kwh_per_100km"])

    off, on = energy("catchup-v1"), energy("catchup-v1:drag_saving=cerutti2021")
    assert (f"falls from {off:.2f} to {on:.2f} kWh/100 km ({100 * (off - on) / off:.1f} %)"
            in text)
    classes = "catchup-v1:classes=bus+van+car*6"
    off, on = energy(classes), energy(classes + ",drag_saving=cerutti2021")
    assert f"from {off:.1f} to {on:.1f} ({100 * (off - on) / off:.1f} %)" in text
