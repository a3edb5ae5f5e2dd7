"""Physical battery power models: the efficiency-map model of the BMW i3 (wheel force, gearbox,
motor limits and loss map, ``docs/spec/energy.md``) and VT-CPEM of a Nissan Leaf (Fiori et al.
2016) for sensitivity studies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from envs.energy.vehicle import (
    _SPEED_EPS_MPS,
    LossMap,
    VehicleParams,
    _bilinear,
    _default_vehicle,
)
from infra.errors import ConfigError

FloatArray = NDArray[np.floating[Any]]

# --------------------------------------------------------------------------------------- map model


class MotorOperatingPoint(NamedTuple):
    """Operating point of the map model (all arrays broadcast to one shape).

    Attributes
    ----------
    motor_speed_rpm : ndarray
        ``n = v i / r * 60 / (2 pi)``.
    motor_torque_demand_nm : ndarray
        Torque the demanded acceleration needs, before the limits.
    motor_torque_nm : ndarray
        Torque after the torque and power limits.
    motor_power_w : ndarray
        Mechanical motor power ``T_m omega_m`` after the limits.
    loss_w : ndarray
        Motor + inverter loss from the map.
    battery_power_w : ndarray
        ``motor_power_w + loss_w + aux`` (plus the battery's own loss if asked for).
    reachable : ndarray of bool
        False where the motor cannot deliver the demanded (motoring) torque or power. Braking
        beyond the regeneration limits is reachable: friction brakes take the rest.
    regen_limited : ndarray of bool
        True where braking demand exceeds a regeneration limit.
    """

    motor_speed_rpm: FloatArray
    motor_torque_demand_nm: FloatArray
    motor_torque_nm: FloatArray
    motor_power_w: FloatArray
    loss_w: FloatArray
    battery_power_w: FloatArray
    reachable: NDArray[np.bool_]
    regen_limited: NDArray[np.bool_]


def map_operating_point(
    speed_mps: ArrayLike,
    accel_mps2: ArrayLike,
    params: VehicleParams | None = None,
    loss_map: LossMap | None = None,
    *,
    road_grade_rad: ArrayLike = 0.0,
    include_battery_loss: bool = False,
) -> MotorOperatingPoint:
    """Operating point and battery power of the efficiency-map model (numpy broadcasting).

    Steps (``docs/spec/energy.md``):

    1. Wheel force ``F = m g f cos(a) + m g sin(a) + 0.5 rho A Cd v^2 + (m + Theta/r^2) u``
       (``a`` = road grade, 0 by default). Rolling resistance is 0 at standstill (as SUMO).
    2. Motor torque ``T = F r / i``, divided by the gear efficiency when motoring (``F >= 0``),
       multiplied by it when regenerating.
    3. Limits. Motoring: torque to ``motor_torque_max_nm``, then power to ``motor_power_max_w``.
       A demand beyond them cannot be driven; the model returns the power at the limit (what the
       motor would draw trying) and marks the point ``reachable = False``, like SUMO, which flags
       it invalid. Regenerating: torque to ``-regen_torque_max_nm``, then power to
       ``-regen_power_max_w``; friction brakes dissipate the rest.
    4. Motor speed ``omega = v i / r``; loss ``P_loss(n, T_m)`` by bilinear interpolation on the
       loss map (``nan`` cells filled with the nearest valid value of the same speed column,
       arguments clipped to the axes).
    5. ``P_batt = T_m omega + P_loss + P_aux``.

    With ``include_battery_loss=True`` the battery's internal resistance loss is added as in
    SUMO's MMPEVEM, ``P = U0^2/(2R) - U0 sqrt((U0^2 - 4 R P_batt) / (4 R^2))``. The spec's model
    (the default) leaves it out; the reference table of ``docs/spec/energy.md`` matches the variant
    with it to 0.4 % and the default to 1.2 %.

    Negative speeds are treated as 0 (the platoon never reverses). Instantaneous: SUMO's
    averaging of the speed over the previous step is not applied. Below about 1 m/s the map's
    loss exceeds what regeneration recovers, so braking there draws a little power (as in SUMO).

    Parameters
    ----------
    speed_mps, accel_mps2 : array_like
        Speed (m/s) and acceleration (m/s^2); broadcast together.
    params : VehicleParams, optional
        Vehicle; the shipped BMW i3 parameters when omitted.
    loss_map : LossMap, optional
        Loss map; the shipped BMW i3 map when omitted.
    road_grade_rad : array_like, optional
        Road grade angle (rad), 0 = flat road.
    include_battery_loss : bool, optional
        Add the battery's internal resistance loss (SUMO's ``P_total``). Default False.

    Returns
    -------
    MotorOperatingPoint
    """
    if loss_map is None:
        _, loss_map, table = _default_vehicle()
    else:
        table = loss_map.filled()
    p = _default_vehicle()[0] if params is None else params
    v = np.maximum(np.asarray(speed_mps, dtype=np.float64), 0.0)
    u = np.asarray(accel_mps2, dtype=np.float64)
    grade = np.asarray(road_grade_rad, dtype=np.float64)
    v, u, grade = np.broadcast_arrays(v, u, grade)

    rolling = p.mass_kg * p.gravity_mps2 * p.rolling_coeff * np.cos(grade)
    rolling = np.where(v > _SPEED_EPS_MPS, rolling, 0.0)
    force_n = (
        rolling
        + p.mass_kg * p.gravity_mps2 * np.sin(grade)
        + 0.5 * p.air_density_kgm3 * p.frontal_area_m2 * p.drag_coeff * v * v
        + p.equivalent_mass_kg * u
    )
    torque_wheel = force_n * p.wheel_radius_m / p.gear_ratio
    demand = np.where(
        force_n >= 0, torque_wheel / p.gear_efficiency, torque_wheel * p.gear_efficiency
    )
    omega = v * (p.gear_ratio / p.wheel_radius_m)  # rad/s
    speed_rpm = omega * (60.0 / (2.0 * math.pi))

    motoring = demand >= 0
    torque = np.clip(demand, -p.regen_torque_max_nm, p.motor_torque_max_nm)
    safe_omega = np.where(omega > 0, omega, 1.0)
    power = torque * omega
    over_power = motoring & (power > p.motor_power_max_w)
    under_power = ~motoring & (power < -p.regen_power_max_w)
    torque = np.where(over_power, p.motor_power_max_w / safe_omega, torque)
    torque = np.where(under_power, -p.regen_power_max_w / safe_omega, torque)
    power = torque * omega

    reachable = ~motoring | (
        (demand <= p.motor_torque_max_nm) & (demand * omega <= p.motor_power_max_w)
    )
    regen_limited = ~motoring & (
        (demand < -p.regen_torque_max_nm) | (demand * omega < -p.regen_power_max_w)
    )
    loss = _bilinear(loss_map.speed_rpm, loss_map.torque_nm, table, speed_rpm, torque)
    battery = power + loss + p.aux_power_w
    if include_battery_loss:
        u0, r_b = p.battery_voltage_v, p.battery_resistance_ohm
        battery = u0 * u0 / (2.0 * r_b) - u0 * np.sqrt(
            (u0 * u0 - 4.0 * r_b * battery) / (4.0 * r_b * r_b)
        )
    return MotorOperatingPoint(
        motor_speed_rpm=speed_rpm,
        motor_torque_demand_nm=demand,
        motor_torque_nm=torque,
        motor_power_w=power,
        loss_w=loss,
        battery_power_w=battery,
        reachable=reachable,
        regen_limited=regen_limited,
    )


def map_battery_power_kw(
    speed_mps: ArrayLike,
    accel_mps2: ArrayLike,
    params: VehicleParams | None = None,
    loss_map: LossMap | None = None,
    *,
    road_grade_rad: ArrayLike = 0.0,
    include_battery_loss: bool = False,
) -> FloatArray:
    """Battery power (kW) of the efficiency-map model; see :func:`map_operating_point`."""
    return map_operating_point(speed_mps, accel_mps2, params, loss_map,
                               road_grade_rad=road_grade_rad,
                               include_battery_loss=include_battery_loss).battery_power_w / 1000.0


# --------------------------------------------------------------------------- VT-CPEM (Nissan Leaf)


@dataclass(frozen=True)
class VTCPEMParams:
    """Parameters of VT-CPEM (Fiori, Ahn, Rakha 2016), defaults: Nissan Leaf.

    Attributes
    ----------
    mass_kg : float
        1521 kg.
    frontal_area_m2, drag_coeff : float
        2.3316 m^2, 0.28.
    rolling_coeff : float
        ``Cr`` = 1.75 (the rolling term is ``m g Cr/1000 (c1 v_kmh + c2)``).
    rolling_c1, rolling_c2 : float
        0.0328 and 4.575.
    air_density_kgm3 : float
        1.2256 kg/m^3.
    driveline_efficiency, motor_efficiency : float
        ``eta_D`` = 0.92, ``eta_EM`` = 0.91.
    regen_alpha_mps2 : float
        ``alpha`` of ``eta_rb = exp(-alpha / |a|)``, 0.0411 m/s^2.
    gravity_mps2 : float
        9.81 m/s^2.
    aux_power_w : float
        Auxiliary load added to the battery power, 0 W (the published model has none).
    """

    mass_kg: float = 1521.0
    frontal_area_m2: float = 2.3316
    drag_coeff: float = 0.28
    rolling_coeff: float = 1.75
    rolling_c1: float = 0.0328
    rolling_c2: float = 4.575
    air_density_kgm3: float = 1.2256
    driveline_efficiency: float = 0.92
    motor_efficiency: float = 0.91
    regen_alpha_mps2: float = 0.0411
    gravity_mps2: float = 9.81
    aux_power_w: float = 0.0


def vtcpem_battery_power_kw(
    speed_mps: ArrayLike,
    accel_mps2: ArrayLike,
    params: VTCPEMParams | None = None,
    *,
    regen_limit_kw: float | None = None,
    road_grade_rad: ArrayLike = 0.0,
) -> FloatArray:
    """Battery power (kW) of VT-CPEM.

    Wheel power ``P_w = (m a + m g (Cr/1000)(c1 v_kmh + c2) + m g sin(grade)
    + 0.5 rho A Cd v^2) v``; motoring ``P = P_w / (eta_D eta_EM)``; regenerating
    ``P = P_w eta_D eta_EM eta_rb`` with ``eta_rb = exp(-alpha / |a|)`` for ``a < 0`` (0 for
    ``a >= 0``, as published). Negative speeds are treated as 0.

    Parameters
    ----------
    speed_mps, accel_mps2 : array_like
        Speed (m/s) and acceleration (m/s^2); broadcast together.
    params : VTCPEMParams, optional
        Vehicle; the Nissan Leaf when omitted.
    regen_limit_kw : float, optional
        Regeneration power limit (kW, positive), e.g. 50; the published model has none (default
        None). Use it when a controller optimises against this model.
    road_grade_rad : array_like, optional
        Road grade (rad), 0 = flat.

    Returns
    -------
    ndarray
        Battery power in kW (negative = regeneration).
    """
    p = VTCPEMParams() if params is None else params
    v = np.maximum(np.asarray(speed_mps, dtype=np.float64), 0.0)
    a = np.asarray(accel_mps2, dtype=np.float64)
    grade = np.asarray(road_grade_rad, dtype=np.float64)
    mg = p.mass_kg * p.gravity_mps2
    force = (
        p.mass_kg * a
        + mg * (p.rolling_coeff / 1000.0) * (p.rolling_c1 * 3.6 * v + p.rolling_c2) * np.cos(grade)
        + mg * np.sin(grade)
        + 0.5 * p.air_density_kgm3 * p.frontal_area_m2 * p.drag_coeff * v * v
    )
    wheel_w = force * v
    eta = p.driveline_efficiency * p.motor_efficiency
    abs_a = np.where(a < 0, -a, 1.0)
    eta_rb = np.where(a < 0, np.exp(-p.regen_alpha_mps2 / abs_a), 0.0)
    battery_w = np.where(wheel_w >= 0, wheel_w / eta, wheel_w * eta * eta_rb) + p.aux_power_w
    if regen_limit_kw is not None:
        if not regen_limit_kw >= 0:
            raise ConfigError(f"regen_limit_kw must be >= 0, got {regen_limit_kw}")
        battery_w = np.maximum(battery_w, -1000.0 * regen_limit_kw)
    return battery_w / 1000.0
