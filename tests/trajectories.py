"""Hand-built trajectories for the metric tests (one builder, shared)."""

from __future__ import annotations

import numpy as np

from benchmark.rollout import Trajectory
from envs.energy import battery_power_kw

DT_S = 0.1


def hand_trajectory(speed_mps: np.ndarray, leader_speed_mps: np.ndarray, *,
                    accel_mps2: np.ndarray | None = None, power_kw: np.ndarray | None = None,
                    automated: np.ndarray | None = None, settle_steps: int = 0,
                    ring: bool = False) -> Trajectory:
    """Rows 0..T of N followers (row 0 the initial state): gaps 20 m, accelerations the speeds'
    differences over dt unless given, powers from the shipped model unless given."""
    rows, n = speed_mps.shape
    steps = rows - 1
    if accel_mps2 is None:
        accel_mps2 = np.zeros((rows, n))
        accel_mps2[1:] = np.diff(speed_mps, axis=0) / DT_S
    if power_kw is None:
        power_kw = np.asarray(battery_power_kw(speed_mps, accel_mps2), dtype=float)
        power_kw[0] = 0.0
    return Trajectory(
        gap_m=np.full((rows, n), 20.0), speed_mps=speed_mps, accel_mps2=accel_mps2,
        power_kw=power_kw, leader_speed_mps=leader_speed_mps,
        leader_accel_mps2=np.zeros(rows), reward=np.zeros(steps),
        tracking_reward=np.zeros(steps), command_mps2=accel_mps2[1:].copy(),
        compute_s=np.full(steps, 1e-3), collided=False, steps=steps, bits_sent=0,
        solver_failures=0, dt_s=DT_S, automated=automated, settle_steps=settle_steps, ring=ring)
