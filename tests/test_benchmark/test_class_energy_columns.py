"""Energy per vehicle class in runs.csv (issue 55 item 2): each class's energy over its own
vehicles' distance, the string's as before, NaN where a class is absent or there are no classes,
and the drag-saving model named."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from trajectories import hand_trajectory

from benchmark.export import CLASS_ENERGY_COLUMNS, RUN_COLUMNS, runs_frame
from benchmark.metrics import class_energy_columns, run_metrics
from benchmark.record_schema import RunRecord
from envs.vehicle_classes import VEHICLE_CLASSES


def test_per_class_energy_by_hand() -> None:
    """Two buses and a car at constant powers: each class's kWh/100 km is its energy over its
    distance; the string's column is unchanged (all energy over all distance, per vehicle)."""
    rows = 101  # 10 s
    speed = np.tile([10.0, 20.0, 10.0], (rows, 1))
    power = np.tile([50.0, 30.0, 70.0], (rows, 1))
    power[0] = 0.0
    t = dataclasses.replace(hand_trajectory(speed, np.full(rows, 10.0), power_kw=power),
                            vehicle_classes=("bus", "car", "bus"))
    m = run_metrics(t, 20.0, 15.0)
    hours = 10 / 3600
    bus_km, car_km = 2 * 10 * 10 / 1000, 20 * 10 / 1000
    assert m["energy_kwh_per_100km_bus"] == pytest.approx((50 + 70) * hours / bus_km * 100)
    assert m["energy_kwh_per_100km_car"] == pytest.approx(30 * hours / car_km * 100)
    assert m["energy_kwh_per_100km"] == pytest.approx(150 * hours / 3 / ((bus_km + car_km) / 3)
                                                      * 100)
    for absent in ("van", "i3", "truck"):
        assert math.isnan(m[f"energy_kwh_per_100km_{absent}"])
    assert m["energy_drag_saving"] == "none"


def test_homogeneous_platoon_has_no_class_energy() -> None:
    rows = 11
    t = hand_trajectory(np.full((rows, 2), 15.0), np.full(rows, 15.0))
    m = run_metrics(t, 20.0, 15.0)
    assert all(math.isnan(m[c]) for c in CLASS_ENERGY_COLUMNS if c != "energy_drag_saving")


def test_columns_cover_every_class_and_the_record_schema_declares_them() -> None:
    assert CLASS_ENERGY_COLUMNS == class_energy_columns()
    assert {f"energy_kwh_per_100km_{c}" for c in VEHICLE_CLASSES} < set(CLASS_ENERGY_COLUMNS)
    assert set(CLASS_ENERGY_COLUMNS) <= set(RUN_COLUMNS)
    assert set(CLASS_ENERGY_COLUMNS) <= set(RunRecord.model_fields)


def test_a_record_stored_before_the_columns_reads_as_unknown() -> None:
    old = {"controller": "acc", "scenario": "catchup-v1", "n_vehicles": 4, "seed": 1,
           "comm_delay_s": 0.0, "packet_loss": 0.0, "lag_s": 0.0, "status": "ok"}
    row = runs_frame([old]).iloc[0]
    assert all(row[c] is None or (isinstance(row[c], float) and math.isnan(row[c]))
               for c in CLASS_ENERGY_COLUMNS)
