"""Battery power models of an electric car: efficiency-map model, fitted polynomial, VT-CPEM.

Follows ``spec/energy.md``. Three models of the battery power ``P(v, u)`` (kW) of one car driving
at speed ``v`` (m/s) with acceleration ``u`` (m/s^2):

``"map"``
    The efficiency-map model of a BMW i3 built from the public SUMO MMPEVEM data
    (``data/energy/bmw_i3.dat``, EPL-2.0, Koch et al., ITSC 2021): wheel force -> wheel torque ->
    motor torque through the gearbox -> motor torque and power limits -> battery power
    ``P_batt = T_m omega_m + P_loss(n, T_m) + P_aux`` with the motor + inverter loss from the loss
    map. See :func:`map_operating_point`.
``"poly"``
    The 5 x 5 polynomial ``P(v, u) = sum_k sum_j p[k, j] v^k u^j`` fitted to the map model by
    :func:`fit_power_polynomial` and shipped in ``data/energy/power_poly.json``. This is the one
    model that the reward, the MPC cost and the energy metric use. :class:`PowerPolynomial` is
    its fast evaluator.
``"vtcpem"``
    The VT-CPEM model of a Nissan Leaf (Fiori, Ahn, Rakha, Applied Energy 168, 2016), for
    sensitivity studies. See :func:`vtcpem_battery_power_kw`.

Sign convention: positive power is drawn from the battery, negative power (regeneration) flows
into it. Only numpy is imported; nothing here reads files outside the package's data folder.
"""

from __future__ import annotations

import datetime as _dt
import functools
import hashlib
import json
import math
import threading
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from envs.errors import ConfigError

__all__ = [
    "DATA_DIR",
    "DEFAULT_POLYNOMIAL_FILE",
    "DEFAULT_VEHICLE_FILE",
    "MODELS",
    "EnergyDataError",
    "LossMap",
    "MotorOperatingPoint",
    "PowerFit",
    "PowerPolynomial",
    "VTCPEMParams",
    "VehicleParams",
    "battery_power_kw",
    "energy_kwh",
    "fit_power_polynomial",
    "kwh_per_100km",
    "load_loss_map",
    "load_power_polynomial",
    "load_vehicle_params",
    "map_battery_power_kw",
    "map_operating_point",
    "vtcpem_battery_power_kw",
]

FloatArray = NDArray[np.floating[Any]]

#: Folder of the energy data shipped with the package.
DATA_DIR: Path = Path(__file__).resolve().parent / "data" / "energy"
#: The BMW i3 parameters and loss map (SUMO MMPEVEM, EPL-2.0).
DEFAULT_VEHICLE_FILE: Path = DATA_DIR / "bmw_i3.dat"
#: The shipped polynomial fit (coefficients and provenance).
DEFAULT_POLYNOMIAL_FILE: Path = DATA_DIR / "power_poly.json"
#: Model names accepted by :func:`battery_power_kw`.
MODELS: tuple[str, ...] = ("poly", "map", "vtcpem")
#: Version string written into the provenance of a fit (the package version when not installed).
CACC_BENCH_VERSION = "0.1.0"
#: Format tag of ``power_poly.json``.
POLYNOMIAL_FORMAT = "cacc-bench power polynomial 1"

_SPEED_EPS_MPS = 1e-6  # below this the car stands: no rolling resistance (as SUMO)


class EnergyDataError(ConfigError):
    """A missing or malformed energy data file (a ``ValueError``; the message names the file)."""


# ---------------------------------------------------------------------------------------------
# Vehicle parameters and loss map
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VehicleParams:
    """Parameters of the efficiency-map model (defaults: BMW i3, ``spec/energy.md``).

    Attributes
    ----------
    mass_kg : float
        Vehicle mass ``m``, 1417 kg.
    theta_kgm2 : float
        Rotating inertia ``Theta``, 12.5 kg m^2, added as the mass ``Theta / r^2`` to the
        acceleration force.
    wheel_radius_m : float
        Wheel radius ``r``, 0.3498 m.
    rolling_coeff : float
        Rolling resistance coefficient ``f``, 0.007.
    drag_coeff : float
        Air drag coefficient ``Cd``, 0.29.
    frontal_area_m2 : float
        Frontal area ``A``, 2.38 m^2.
    gear_ratio : float
        Gear ratio ``i = n_motor / n_wheel``, 9.665.
    gear_efficiency : float
        Gearbox efficiency, 0.96.
    motor_torque_max_nm, motor_power_max_w : float
        Motoring limits, 250 Nm and 125 kW.
    regen_torque_max_nm, regen_power_max_w : float
        Regeneration limits (positive numbers), 77 Nm and 50 kW; friction brakes take the rest.
    aux_power_w : float
        Constant auxiliary load, 360 W.
    air_density_kgm3 : float
        Air density, 1.204 kg/m^3 (SUMO's constant; not in the data file).
    gravity_mps2 : float
        Gravitational acceleration, 9.81 m/s^2 (SUMO's constant; not in the data file).
    battery_resistance_ohm, battery_voltage_v : float
        Internal resistance (0.0768 Ohm) and nominal voltage (370 V) of the battery. Used only
        by the optional battery-loss term (``include_battery_loss=True``), which the spec's
        model does not have.
    """

    mass_kg: float = 1417.0
    theta_kgm2: float = 12.5
    wheel_radius_m: float = 0.3498
    rolling_coeff: float = 0.007
    drag_coeff: float = 0.29
    frontal_area_m2: float = 2.38
    gear_ratio: float = 9.665
    gear_efficiency: float = 0.96
    motor_torque_max_nm: float = 250.0
    motor_power_max_w: float = 125000.0
    regen_torque_max_nm: float = 77.0
    regen_power_max_w: float = 50000.0
    aux_power_w: float = 360.0
    air_density_kgm3: float = 1.204
    gravity_mps2: float = 9.81
    battery_resistance_ohm: float = 0.0768
    battery_voltage_v: float = 370.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, int | float) and math.isfinite(value)):
                raise ConfigError(f"VehicleParams.{f.name} must be a finite number, got {value!r}")
        positive = (
            "mass_kg",
            "wheel_radius_m",
            "gear_ratio",
            "motor_torque_max_nm",
            "motor_power_max_w",
            "gravity_mps2",
            "battery_resistance_ohm",
            "battery_voltage_v",
        )
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(
                    f"VehicleParams.{name} must be positive, got {getattr(self, name)}"
                )
        nonnegative = (
            "theta_kgm2",
            "rolling_coeff",
            "drag_coeff",
            "frontal_area_m2",
            "regen_torque_max_nm",
            "regen_power_max_w",
            "aux_power_w",
            "air_density_kgm3",
        )
        for name in nonnegative:
            if getattr(self, name) < 0:
                raise ConfigError(f"VehicleParams.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 < self.gear_efficiency <= 1:
            raise ConfigError(
                f"VehicleParams.gear_efficiency must be in (0, 1], got {self.gear_efficiency}"
            )

    @property
    def equivalent_mass_kg(self) -> float:
        """Mass seen by the acceleration force, ``m + Theta / r^2`` (kg)."""
        return self.mass_kg + self.theta_kgm2 / self.wheel_radius_m**2


#: ``.dat`` key -> :class:`VehicleParams` field.
_DAT_KEYS: dict[str, str] = {
    "m": "mass_kg",
    "r_wheel": "wheel_radius_m",
    "Theta": "theta_kgm2",
    "c_rr": "rolling_coeff",
    "c_d": "drag_coeff",
    "A_front": "frontal_area_m2",
    "i_gear": "gear_ratio",
    "eta_gear": "gear_efficiency",
    "M_max": "motor_torque_max_nm",
    "P_max": "motor_power_max_w",
    "M_recup_max": "regen_torque_max_nm",
    "P_recup_max": "regen_power_max_w",
    "R_battery": "battery_resistance_ohm",
    "U_battery_0": "battery_voltage_v",
    "P_const": "aux_power_w",
}
_LOSS_MAP_KEY = "powerLossMapString"


def _read_dat(path: Path) -> dict[str, str]:
    """``key = value`` lines of a SUMO MMPEVEM ``.dat`` file (``#`` starts a comment)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise EnergyDataError(f"energy data file {path}: not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise EnergyDataError(f"energy data file {path}: cannot be read ({exc})") from None
    entries: dict[str, str] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        key, sep, value = line.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key or not value:
            raise EnergyDataError(
                f"energy data file {path}, line {lineno}: expected 'key = value', got {raw.strip()!r}"
            )
        if key in entries:
            raise EnergyDataError(f"energy data file {path}, line {lineno}: duplicate key {key!r}")
        entries[key] = value
    return entries


def _as_path(path: str | Path | None, default: Path) -> Path:
    return default if path is None else Path(path)


def load_vehicle_params(path: str | Path | None = None) -> VehicleParams:
    """Read the vehicle parameters of a SUMO MMPEVEM ``.dat`` file.

    Parameters
    ----------
    path : str or Path, optional
        The file; the shipped BMW i3 file when omitted.

    Returns
    -------
    VehicleParams
        The file's values; air density and gravity keep their defaults (not in the file).

    Raises
    ------
    EnergyDataError
        (a ``ValueError``) if the file is missing, a key is missing or a value is not a number.
    """
    p = _as_path(path, DEFAULT_VEHICLE_FILE)
    entries = _read_dat(p)
    values: dict[str, float] = {}
    for key, name in _DAT_KEYS.items():
        if key not in entries:
            raise EnergyDataError(f"energy data file {p}: missing parameter {key!r}")
        try:
            values[name] = float(entries[key])
        except ValueError:
            raise EnergyDataError(
                f"energy data file {p}: parameter {key!r} is not a number: {entries[key]!r}"
            ) from None
    try:
        return VehicleParams(**values)
    except ConfigError as exc:
        raise EnergyDataError(f"energy data file {p}: {exc}") from None


class LossMap(NamedTuple):
    """Power loss map of the electric machine + inverter.

    Attributes
    ----------
    speed_rpm : ndarray, shape (n_speed,)
        Motor speed axis (rpm), strictly increasing.
    torque_nm : ndarray, shape (n_torque,)
        Motor torque axis (Nm), strictly increasing (negative = regeneration).
    loss_w : ndarray, shape (n_torque, n_speed)
        Loss (W); rows are torque, columns speed; ``nan`` marks unreachable points.
    """

    speed_rpm: NDArray[np.float64]
    torque_nm: NDArray[np.float64]
    loss_w: NDArray[np.float64]

    def filled(self) -> NDArray[np.float64]:
        """The loss values with every ``nan`` cell replaced by the nearest valid cell of its column.

        "Nearest" is along the torque axis within the same speed column (ties go to the smaller
        torque). Outside the motor's envelope the model clips the torque first, so these cells
        are only reached by interpolation next to the envelope's edge.
        """
        loss = np.array(self.loss_w, dtype=np.float64, copy=True)
        bad = np.isnan(loss)
        if not bad.any():
            return loss
        torque = np.asarray(self.torque_nm, dtype=np.float64)
        for col in np.flatnonzero(bad.any(axis=0)):
            valid = np.flatnonzero(~bad[:, col])
            missing = np.flatnonzero(bad[:, col])
            # valid is non-empty: load_loss_map rejects all-nan columns
            dist = np.abs(torque[missing, None] - torque[None, valid])
            loss[missing, col] = loss[valid[np.argmin(dist, axis=1)], col]
        return loss

    def interpolate(self, speed_rpm: ArrayLike, torque_nm: ArrayLike) -> FloatArray:
        """Bilinear interpolation of the loss (W) at motor speed (rpm) and torque (Nm).

        ``nan`` cells are filled first (see :meth:`filled`); points outside the axes take the
        value at the nearest edge (the arguments are clipped to the axes).
        """
        return _bilinear(self.speed_rpm, self.torque_nm, self.filled(), speed_rpm, torque_nm)


def _bilinear(
    x_axis: NDArray[np.float64],
    y_axis: NDArray[np.float64],
    table: NDArray[np.float64],
    x: ArrayLike,
    y: ArrayLike,
) -> FloatArray:
    """Bilinear interpolation of ``table[y_index, x_index]``; arguments clipped to the axes."""
    xa = np.clip(np.asarray(x, dtype=np.float64), x_axis[0], x_axis[-1])
    ya = np.clip(np.asarray(y, dtype=np.float64), y_axis[0], y_axis[-1])
    ix = np.clip(np.searchsorted(x_axis, xa, side="right") - 1, 0, x_axis.size - 2)
    iy = np.clip(np.searchsorted(y_axis, ya, side="right") - 1, 0, y_axis.size - 2)
    wx = (xa - x_axis[ix]) / (x_axis[ix + 1] - x_axis[ix])
    wy = (ya - y_axis[iy]) / (y_axis[iy + 1] - y_axis[iy])
    low = table[iy, ix] * (1.0 - wx) + table[iy, ix + 1] * wx
    high = table[iy + 1, ix] * (1.0 - wx) + table[iy + 1, ix + 1] * wx
    return low * (1.0 - wy) + high * wy


def _parse_numbers(text: str, what: str, path: Path) -> NDArray[np.float64]:
    try:
        return np.array([float(tok) for tok in text.split(",")], dtype=np.float64)
    except ValueError:
        bad = next(t for t in text.split(",") if not _is_float(t))
        raise EnergyDataError(
            f"energy data file {path}: {_LOSS_MAP_KEY}: {what} has a non-number entry {bad.strip()!r}"
        ) from None


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def load_loss_map(path: str | Path | None = None) -> LossMap:
    """Parse the ``powerLossMapString`` of a SUMO MMPEVEM ``.dat`` file.

    The format is ``2,1|<speed axis, rpm>;<torque axis, Nm>|<values, W>``, values row-major with
    rows = torque and columns = speed; ``nan`` marks unreachable points.

    Parameters
    ----------
    path : str or Path, optional
        The file; the shipped BMW i3 file when omitted.

    Returns
    -------
    LossMap
        Speed axis (rpm), torque axis (Nm), loss values (W, ``nan`` kept).

    Raises
    ------
    EnergyDataError
        (a ``ValueError``) naming the file and the problem: missing key, wrong dimensions, a
        non-number, axes not strictly increasing, a wrong number of values, negative or infinite
        losses, or a speed column without any valid value.
    """
    p = _as_path(path, DEFAULT_VEHICLE_FILE)
    entries = _read_dat(p)
    if _LOSS_MAP_KEY not in entries:
        raise EnergyDataError(f"energy data file {p}: missing {_LOSS_MAP_KEY!r}")
    parts = entries[_LOSS_MAP_KEY].split("|")
    if len(parts) != 3:
        raise EnergyDataError(
            f"energy data file {p}: {_LOSS_MAP_KEY} must have 3 '|'-separated parts "
            f"(dimensions|axes|values), found {len(parts)}"
        )
    if [s.strip() for s in parts[0].split(",")] != ["2", "1"]:
        raise EnergyDataError(
            f"energy data file {p}: {_LOSS_MAP_KEY} dimensions must be '2,1', got {parts[0]!r}"
        )
    axes = parts[1].split(";")
    if len(axes) != 2:
        raise EnergyDataError(
            f"energy data file {p}: {_LOSS_MAP_KEY} needs 2 ';'-separated axes, found {len(axes)}"
        )
    speed = _parse_numbers(axes[0], "speed axis", p)
    torque = _parse_numbers(axes[1], "torque axis", p)
    for name, axis in (("speed axis", speed), ("torque axis", torque)):
        if axis.size < 2 or not np.all(np.isfinite(axis)) or np.any(np.diff(axis) <= 0):
            raise EnergyDataError(
                f"energy data file {p}: {_LOSS_MAP_KEY}: the {name} must have at least 2 finite, "
                "strictly increasing values"
            )
    values = _parse_numbers(parts[2], "values", p)
    if values.size != speed.size * torque.size:
        raise EnergyDataError(
            f"energy data file {p}: {_LOSS_MAP_KEY} has {values.size} values, expected "
            f"{torque.size} torques x {speed.size} speeds = {torque.size * speed.size}"
        )
    if np.any(np.isinf(values)) or np.any(values < 0):
        raise EnergyDataError(
            f"energy data file {p}: {_LOSS_MAP_KEY} has infinite or negative losses"
        )
    loss = values.reshape(torque.size, speed.size)
    empty = np.flatnonzero(np.isnan(loss).all(axis=0))
    if empty.size:
        raise EnergyDataError(
            f"energy data file {p}: {_LOSS_MAP_KEY}: speed column {speed[empty[0]]} rpm has no valid value"
        )
    return LossMap(speed_rpm=speed, torque_nm=torque, loss_w=loss)


@functools.lru_cache(maxsize=1)
def _default_vehicle() -> tuple[VehicleParams, LossMap, NDArray[np.float64]]:
    params = load_vehicle_params()
    loss_map = load_loss_map()
    return params, loss_map, loss_map.filled()


# ---------------------------------------------------------------------------------------------
# Map model
# ---------------------------------------------------------------------------------------------


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

    Steps (``spec/energy.md``):

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
    (the default) leaves it out; the reference table of ``spec/energy.md`` matches the variant
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
    if params is None or loss_map is None:
        default_params, default_map, default_table = _default_vehicle()
        params = default_params if params is None else params
    if loss_map is None:
        table = default_table
        loss_map = default_map
    else:
        table = loss_map.filled()
    p = params
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
    op = map_operating_point(
        speed_mps,
        accel_mps2,
        params,
        loss_map,
        road_grade_rad=road_grade_rad,
        include_battery_loss=include_battery_loss,
    )
    return op.battery_power_w / 1000.0


# ---------------------------------------------------------------------------------------------
# VT-CPEM (Nissan Leaf)
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# The polynomial
# ---------------------------------------------------------------------------------------------


_HORNER_BLOCK = 8192  # elements per block: the (K * block) scratch stays in cache


class _Horner2D:
    """Evaluation of ``sum_{k,j} c[k, j] v^k u^j`` with few numpy calls on flat arrays.

    Per block of at most ``_HORNER_BLOCK`` elements: the powers ``u^0..u^(J-1)`` are formed as
    the rows of a ``(J, n)`` scratch array, one matrix product ``c @ U`` gives the K polynomials
    in ``u`` at once (BLAS), and Horner's scheme in ``v`` combines them into the output. About
    ``J + 2 K`` ufunc calls and one small GEMM per block, all on contiguous rows (several times
    faster than a Horner scheme of ufunc calls in both variables).
    """

    __slots__ = ("coef", "rows", "_typed", "_local")

    def __init__(self, coef: NDArray[np.float64]) -> None:
        self.coef = coef
        self.rows = tuple(tuple(float(c) for c in row) for row in coef)
        self._typed: dict[np.dtype[Any], FloatArray] = {}
        # scratch per thread and dtype: fresh large arrays every call would page-fault
        self._local = threading.local()

    def _scratch(self, dtype: np.dtype[Any], block: int) -> tuple[FloatArray, FloatArray]:
        cache = getattr(self._local, "cache", None)
        if cache is None:
            cache = self._local.cache = {}
        bufs = cache.get(dtype)
        if bufs is None or bufs[0].shape[1] < block:
            n_v, n_u = self.coef.shape
            bufs = cache[dtype] = (
                np.empty((n_u, block), dtype=dtype),
                np.empty((n_v, block), dtype=dtype),
            )
        return bufs

    def __call__(self, v: FloatArray, u: FloatArray, out: FloatArray) -> None:
        """Evaluate into ``out`` (1-D contiguous); ``v``, ``u``: 1-D of its size, or 0-d."""
        size = out.size
        if size == 0:
            return
        n_v, n_u = self.coef.shape
        dtype = out.dtype
        coef = self._typed.get(dtype)
        if coef is None:
            coef = self._typed[dtype] = np.ascontiguousarray(self.coef, dtype=dtype)
        block = min(size, _HORNER_BLOCK)
        upow_buf, inner_buf = self._scratch(dtype, block)
        mul, add = np.multiply, np.add
        for start in range(0, size, block):
            stop = min(start + block, size)
            n = stop - start
            upow = upow_buf[:, :n] if n == upow_buf.shape[1] else np.empty((n_u, n), dtype=dtype)
            inner = inner_buf[:, :n] if n == inner_buf.shape[1] else np.empty((n_v, n), dtype=dtype)
            ub = u if u.ndim == 0 else u[start:stop]
            upow[0] = 1.0
            if n_u > 1:
                upow[1] = ub
            for j in range(2, n_u):
                mul(upow[j - 1], ub, out=upow[j])
            np.matmul(coef, upow, out=inner)
            vb = v if v.ndim == 0 else v[start:stop]
            ob = out[start:stop]
            if n_v == 1:
                ob[...] = inner[0]
                continue
            mul(inner[n_v - 1], vb, out=ob)
            for k in range(n_v - 2, 0, -1):
                add(ob, inner[k], out=ob)
                mul(ob, vb, out=ob)
            add(ob, inner[0], out=ob)


def _flat(a: NDArray[Any], shape: tuple[int, ...]) -> NDArray[Any]:
    """``a`` as a 1-D array of the broadcast shape's size (a 0-d array stays 0-d)."""
    if a.ndim == 0:
        return a
    if a.shape != shape:
        a = np.broadcast_to(a, shape)
    return a.reshape(-1)


class PowerPolynomial:
    """Fast evaluator of ``P(v, u) = sum_{k,j} p[k, j] v^k u^j`` (kW, SI arguments).

    Evaluation forms the powers of ``u``, multiplies by the coefficient matrix (one small GEMM per
    block of 8192 elements) and applies Horner's scheme in ``v``; no Python loop over elements. float32 inputs give
    float32 results (computed in float32); anything else gives float64. Safe to share between
    threads (no shared scratch).

    Parameters
    ----------
    coefficients_kw : array_like, shape (K, J)
        ``p[k, j]``, the coefficient of ``v^k u^j`` (kW / (m/s)^k / (m/s^2)^j); K, J >= 2.
    metadata : mapping, optional
        Provenance and fit quality (what ``power_poly.json`` holds besides the coefficients).
    """

    __slots__ = ("_coef", "_p", "_p_dv", "_p_du", "metadata")

    def __init__(
        self, coefficients_kw: ArrayLike, metadata: Mapping[str, Any] | None = None
    ) -> None:
        coef = np.array(coefficients_kw, dtype=np.float64, copy=True)
        if coef.ndim != 2 or coef.shape[0] < 2 or coef.shape[1] < 2:
            raise ConfigError(
                f"power polynomial coefficients must be a 2-D array, at least 2x2, got shape {coef.shape}"
            )
        if not np.all(np.isfinite(coef)):
            raise ConfigError("power polynomial coefficients must be finite")
        coef.setflags(write=False)
        self._coef = coef
        k = np.arange(coef.shape[0], dtype=np.float64)[:, None]
        j = np.arange(coef.shape[1], dtype=np.float64)[None, :]
        dv = (coef * k)[1:]
        du = (coef * j)[:, 1:]
        self._p = _Horner2D(coef)
        self._p_dv = _Horner2D(dv)
        self._p_du = _Horner2D(du)
        self.metadata: dict[str, Any] = dict(metadata or {})

    @property
    def coefficients_kw(self) -> NDArray[np.float64]:
        """``p[k, j]`` (read-only array, shape (K, J)): the coefficient of ``v^k u^j``."""
        return self._coef

    @property
    def degree(self) -> tuple[int, int]:
        """Highest powers of speed and acceleration."""
        return self._coef.shape[0] - 1, self._coef.shape[1] - 1

    def __repr__(self) -> str:
        return f"PowerPolynomial(degree={self.degree})"

    def __call__(
        self, speed_mps: ArrayLike, accel_mps2: ArrayLike, out: FloatArray | None = None
    ) -> FloatArray:
        """Battery power (kW) at speed (m/s) and acceleration (m/s^2).

        Parameters
        ----------
        speed_mps, accel_mps2 : array_like
            Broadcast together.
        out : ndarray, optional
            Floating array of the broadcast shape to write into (may be one of the inputs).

        Returns
        -------
        ndarray
            ``out`` if given; a 0-d array for scalar arguments.
        """
        return self._evaluate(self._p, speed_mps, accel_mps2, out)

    def dP_dv(
        self, speed_mps: ArrayLike, accel_mps2: ArrayLike, out: FloatArray | None = None
    ) -> FloatArray:
        """Partial derivative ``dP/dv`` (kW per m/s); arguments as :meth:`__call__`."""
        return self._evaluate(self._p_dv, speed_mps, accel_mps2, out)

    def dP_du(
        self, speed_mps: ArrayLike, accel_mps2: ArrayLike, out: FloatArray | None = None
    ) -> FloatArray:
        """Partial derivative ``dP/du`` (kW per m/s^2); arguments as :meth:`__call__`."""
        return self._evaluate(self._p_du, speed_mps, accel_mps2, out)

    def expression(self, speed: Any, accel: Any) -> Any:
        """Evaluate with plain ``*`` and ``+`` (Horner): for Python floats or symbolic types.

        Works with CasADi ``SX``/``MX``, sympy symbols, Python floats (fast for one point).
        """
        result: Any = None
        for row in self._p.rows[::-1]:
            inner: Any = row[-1]
            for c in row[-2::-1]:
                inner = inner * accel + c
            result = inner if result is None else result * speed + inner
        return result

    @staticmethod
    def _evaluate(
        plan: _Horner2D,
        speed_mps: ArrayLike,
        accel_mps2: ArrayLike,
        out: FloatArray | None,
    ) -> FloatArray:
        v = speed_mps if isinstance(speed_mps, np.ndarray) else np.asarray(speed_mps)
        u = accel_mps2 if isinstance(accel_mps2, np.ndarray) else np.asarray(accel_mps2)
        if v.dtype == np.float32 and u.dtype == np.float32:
            dtype: type[np.floating[Any]] = np.float32
        else:
            dtype = np.float64
        shape = v.shape if v.shape == u.shape else np.broadcast_shapes(v.shape, u.shape)
        if (
            out is None
            and v.ndim > 1
            and v.shape == u.shape
            and v.strides == u.strides
            and v.flags.f_contiguous
            and not v.flags.c_contiguous
        ):
            # Fortran-ordered inputs (the env's (B, N) state): flatten in memory order, no copy
            result = np.empty(shape, dtype=dtype, order="F")
            plan(v.ravel(order="F"), u.ravel(order="F"), result.ravel(order="F"))
            return result
        vf, uf = _flat(v, shape), _flat(u, shape)
        if out is None:
            result = np.empty(shape, dtype=dtype)
            plan(vf, uf, result.reshape(-1))
            return result
        if not isinstance(out, np.ndarray) or out.dtype.kind != "f":
            raise TypeError("out must be a floating-point numpy array")
        if out.shape != shape:
            raise ValueError(f"out has shape {out.shape}, the arguments broadcast to {shape}")
        if (
            out.flags.c_contiguous
            and not np.may_share_memory(out, v)
            and not np.may_share_memory(out, u)
        ):
            plan(vf, uf, out.reshape(-1))
            return out
        result = np.empty(shape, dtype=out.dtype)
        plan(vf, uf, result.reshape(-1))
        out[...] = result
        return out


def load_power_polynomial(path: str | Path | None = None) -> PowerPolynomial:
    """Load a fitted polynomial (``power_poly.json`` format).

    Parameters
    ----------
    path : str or Path, optional
        The JSON file; the shipped fit when omitted.

    Returns
    -------
    PowerPolynomial
        With the file's other entries (quality, grid, provenance) in ``metadata``.

    Raises
    ------
    EnergyDataError
        (a ``ValueError``) naming the file if it is missing, not JSON, or has no valid
        ``coefficients_kw``.
    """
    p = _as_path(path, DEFAULT_POLYNOMIAL_FILE)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise EnergyDataError(
            f"power polynomial file {p}: not found (make it with `cacc-bench fit-power --write`)"
        ) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise EnergyDataError(
            f"power polynomial file {p}: cannot be read as JSON ({exc})"
        ) from None
    if not isinstance(data, dict) or "coefficients_kw" not in data:
        raise EnergyDataError(f"power polynomial file {p}: no 'coefficients_kw' entry")
    try:
        coef = np.array(data["coefficients_kw"], dtype=np.float64)
    except (TypeError, ValueError):
        raise EnergyDataError(
            f"power polynomial file {p}: 'coefficients_kw' is not a numeric matrix"
        ) from None
    if coef.ndim != 2 or coef.shape[0] < 2 or coef.shape[1] < 2 or not np.all(np.isfinite(coef)):
        raise EnergyDataError(
            f"power polynomial file {p}: 'coefficients_kw' must be a finite matrix of at least "
            f"2x2, got shape {coef.shape}"
        )
    metadata = {k: v for k, v in data.items() if k != "coefficients_kw"}
    return PowerPolynomial(coef, metadata)


@functools.lru_cache(maxsize=1)
def _default_polynomial() -> PowerPolynomial:
    return load_power_polynomial()


# ---------------------------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PowerFit:
    """A least-squares fit of the polynomial to the map model, with its quality.

    Attributes
    ----------
    coefficients_kw : ndarray, shape (degree+1, degree+1)
        ``p[k, j]`` in SI units (kW, m/s, m/s^2), the coefficient of ``v^k u^j``.
    r2, rmse_kw, max_abs_error_kw : float
        Quality over the whole fit grid (reachable points).
    r2_low_speed, rmse_kw_low_speed, max_abs_error_kw_low_speed : float
        The same over the grid points with ``v <= low_speed_max_mps`` (20 m/s: the range the
        spec cites), of the same fit.
    n_points, n_points_low_speed : int
        Grid points used (reachable), and those with ``v <= low_speed_max_mps``.
    grid : dict
        Description of the grid and the selection rule (JSON-ready).
    """

    coefficients_kw: NDArray[np.float64]
    r2: float
    rmse_kw: float
    max_abs_error_kw: float
    r2_low_speed: float
    rmse_kw_low_speed: float
    max_abs_error_kw_low_speed: float
    n_points: int
    n_points_low_speed: int
    grid: dict[str, Any] = field(default_factory=dict)

    def quality(self) -> dict[str, float | int]:
        """The quality numbers as a JSON-ready dict."""
        return {
            "r2": self.r2,
            "rmse_kw": self.rmse_kw,
            "max_abs_error_kw": self.max_abs_error_kw,
            "n_points": self.n_points,
            "r2_low_speed": self.r2_low_speed,
            "rmse_kw_low_speed": self.rmse_kw_low_speed,
            "max_abs_error_kw_low_speed": self.max_abs_error_kw_low_speed,
            "n_points_low_speed": self.n_points_low_speed,
        }

    def polynomial(self) -> PowerPolynomial:
        """The fitted polynomial as a :class:`PowerPolynomial`."""
        return PowerPolynomial(self.coefficients_kw, {"quality": self.quality(), "grid": self.grid})

    def to_json_dict(
        self,
        params: VehicleParams | None = None,
        source_file: str | Path | None = None,
        fitted_on: str | None = None,
    ) -> dict[str, Any]:
        """Everything ``power_poly.json`` holds: coefficients, quality, grid, provenance.

        Parameters
        ----------
        params : VehicleParams, optional
            The vehicle the fit used (shipped BMW i3 when omitted).
        source_file : str or Path, optional
            The ``.dat`` file of the vehicle (shipped file when omitted); its SHA-256 is recorded.
        fitted_on : str, optional
            ISO date of the fit; today (UTC) when omitted.
        """
        src = _as_path(source_file, DEFAULT_VEHICLE_FILE)
        vehicle = load_vehicle_params(src) if params is None else params
        try:
            rel = src.resolve().relative_to(Path(__file__).resolve().parent.parent).as_posix()
        except ValueError:
            rel = src.as_posix()
        digest = hashlib.sha256(src.read_bytes()).hexdigest() if src.exists() else None
        date = fitted_on or _dt.datetime.now(_dt.UTC).date().isoformat()
        return {
            "format": POLYNOMIAL_FORMAT,
            "description": (
                "Battery power P(v, u) in kW of a BMW i3 (efficiency-map model, flat road) as a "
                "polynomial of speed v (m/s) and acceleration u (m/s^2); negative = regeneration."
            ),
            "formula": "P_kW = sum_k sum_j coefficients_kw[k][j] * v_mps**k * u_mps2**j",
            "units": {"speed": "m/s", "acceleration": "m/s^2", "power": "kW"},
            "coefficients_kw": [[float(c) for c in row] for row in self.coefficients_kw],
            "quality": self.quality(),
            "grid": self.grid,
            "provenance": {
                "model": (
                    "envs.energy.map_battery_power_kw (spec/energy.md): wheel force, gearbox, motor "
                    "torque/power limits, bilinear loss-map lookup, P_batt = T_m omega_m + P_loss + "
                    "P_aux; no battery internal-resistance loss"
                ),
                "source_data": rel,
                "source_sha256": digest,
                "source_upstream": (
                    "eclipse-sumo/sumo data/emissions/MMPEVEM/bmw_i3.dat (EPL-2.0), Koch et al., "
                    "IEEE ITSC 2021, doi:10.1109/ITSC48978.2021.9564463"
                ),
                "vehicle_params": asdict(vehicle),
                "fitted_on": date,
                "generator": (
                    "envs.energy.fit_power_polynomial, written by benchmark.fit_power "
                    "(`cacc-bench fit-power --write`)"
                ),
                "cacc_bench_version": _package_version(),
                "numpy_version": np.__version__,
            },
        }


def _package_version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version
    except ImportError:  # pragma: no cover
        return CACC_BENCH_VERSION
    try:
        return version("cacc-bench")
    except PackageNotFoundError:
        return CACC_BENCH_VERSION


def _axis(lo: float, hi: float, step: float) -> NDArray[np.float64]:
    n = int(round((hi - lo) / step)) + 1
    if n < 2 or not hi > lo:
        raise ConfigError(f"bad grid range [{lo}, {hi}] with step {step}")
    return np.linspace(lo, hi, n)


def _monomial_to_si(n: int, center: float, scale: float) -> NDArray[np.float64]:
    """Matrix ``M`` (n x n) with ``((x - center) / scale)^k = sum_a M[k, a] x^a``."""
    m = np.zeros((n, n))
    base = np.array([-center / scale, 1.0 / scale])
    cur = np.array([1.0])
    for k in range(n):
        m[k, : cur.size] = cur
        cur = np.convolve(cur, base)
    return m


def fit_power_polynomial(
    params: VehicleParams | None = None,
    loss_map: LossMap | None = None,
    *,
    degree: int = 4,
    speed_range_mps: tuple[float, float] = (0.5, 30.0),
    accel_range_mps2: tuple[float, float] = (-3.0, 2.5),
    speed_step_mps: float = 0.1,
    accel_step_mps2: float = 0.05,
    low_speed_max_mps: float = 20.0,
) -> PowerFit:
    """Least-squares fit of ``P(v, u) = sum p[k, j] v^k u^j`` to the map model.

    The grid is the full tensor grid of ``speed_range_mps`` x ``accel_range_mps2`` with the given
    steps (both ends included). A point enters the fit when the motor can reach it: motoring
    demand within the motor torque and power limits. Braking beyond the regeneration limits is
    kept (friction brakes take the rest, the battery sees the regeneration limit), so that the
    polynomial does not promise unlimited regeneration for hard braking. Unweighted least squares
    in centred and scaled variables ``x = (v - c_v)/s_v``, ``y = (u - c_u)/s_u`` (well
    conditioned); the result is converted exactly to SI coefficients. Deterministic.

    Parameters
    ----------
    params, loss_map : optional
        Vehicle and loss map; the shipped BMW i3 when omitted.
    degree : int
        Highest power of each variable (4: 25 coefficients).
    speed_range_mps, accel_range_mps2 : (float, float)
        Grid ranges, default [0.5, 30] m/s and [-3, 2.5] m/s^2.
    speed_step_mps, accel_step_mps2 : float
        Grid steps, default 0.1 m/s and 0.05 m/s^2 (296 x 111 points).
    low_speed_max_mps : float
        Upper speed of the second quality report (20 m/s, the range the spec cites).

    Returns
    -------
    PowerFit
    """
    if degree < 1:
        raise ConfigError(f"degree must be >= 1, got {degree}")
    speeds = _axis(*speed_range_mps, speed_step_mps)
    accels = _axis(*accel_range_mps2, accel_step_mps2)
    vg, ug = np.meshgrid(speeds, accels, indexing="ij")
    op = map_operating_point(vg, ug, params, loss_map)
    mask = op.reachable
    v, u, y = vg[mask], ug[mask], op.battery_power_w[mask] / 1000.0

    cv, sv = 0.5 * (speeds[0] + speeds[-1]), 0.5 * (speeds[-1] - speeds[0])
    cu, su = 0.5 * (accels[0] + accels[-1]), 0.5 * (accels[-1] - accels[0])
    x, z = (v - cv) / sv, (u - cu) / su
    xp = np.vander(x, degree + 1, increasing=True)
    zp = np.vander(z, degree + 1, increasing=True)
    design = (xp[:, :, None] * zp[:, None, :]).reshape(x.size, -1)
    q, *_ = np.linalg.lstsq(design, y, rcond=None)
    q = q.reshape(degree + 1, degree + 1)
    mv = _monomial_to_si(degree + 1, cv, sv)
    mu = _monomial_to_si(degree + 1, cu, su)
    coef = mv.T @ q @ mu

    pred = PowerPolynomial(coef)(v, u)
    err = pred - y
    low = v <= low_speed_max_mps + 1e-9

    def _quality(sel: NDArray[np.bool_]) -> tuple[float, float, float]:
        e, t = err[sel], y[sel]
        ss_res = float(np.sum(e * e))
        ss_tot = float(np.sum((t - t.mean()) ** 2))
        return 1.0 - ss_res / ss_tot, math.sqrt(ss_res / e.size), float(np.max(np.abs(e)))

    r2, rmse, mx = _quality(np.ones_like(low))
    r2_l, rmse_l, mx_l = _quality(low)
    grid = {
        "speed_range_mps": [float(speeds[0]), float(speeds[-1])],
        "speed_step_mps": float(speed_step_mps),
        "accel_range_mps2": [float(accels[0]), float(accels[-1])],
        "accel_step_mps2": float(accel_step_mps2),
        "n_grid": int(vg.size),
        "low_speed_range_mps": [float(speeds[0]), float(low_speed_max_mps)],
        "degree": int(degree),
        "selection": (
            "points the motor can reach: motoring demand within the motor torque and power limits; "
            "braking beyond the regeneration limits kept (friction brakes take the rest)"
        ),
        "method": (
            "unweighted linear least squares in centred, scaled variables, converted exactly to SI "
            "coefficients; quality evaluated with the SI coefficients"
        ),
    }
    return PowerFit(
        coefficients_kw=coef,
        r2=r2,
        rmse_kw=rmse,
        max_abs_error_kw=mx,
        r2_low_speed=r2_l,
        rmse_kw_low_speed=rmse_l,
        max_abs_error_kw_low_speed=mx_l,
        n_points=int(mask.sum()),
        n_points_low_speed=int(low.sum()),
        grid=grid,
    )


# ---------------------------------------------------------------------------------------------
# Public entry points
# ---------------------------------------------------------------------------------------------


def battery_power_kw(
    speed_mps: ArrayLike, accel_mps2: ArrayLike, model: str = "poly"
) -> FloatArray:
    """Battery power (kW, negative = regeneration) at speed (m/s) and acceleration (m/s^2).

    Parameters
    ----------
    speed_mps, accel_mps2 : array_like
        Broadcast together.
    model : {"poly", "map", "vtcpem"}
        ``"poly"``: the shipped polynomial (loaded once, cached) - the model of the reward, the MPC
        and the energy metric. ``"map"``: the BMW i3 efficiency-map model
        (:func:`map_battery_power_kw`). ``"vtcpem"``: VT-CPEM, Nissan Leaf, no regeneration limit
        (:func:`vtcpem_battery_power_kw` has the options).

    Returns
    -------
    ndarray
        A 0-d array for scalar arguments.

    Raises
    ------
    ConfigError
        (a ``ValueError``) for an unknown model name.
    """
    if model == "poly":
        return _default_polynomial()(speed_mps, accel_mps2)
    if model == "map":
        return map_battery_power_kw(speed_mps, accel_mps2)
    if model == "vtcpem":
        return vtcpem_battery_power_kw(speed_mps, accel_mps2)
    raise ConfigError(f"unknown energy model {model!r}; valid models are: {', '.join(MODELS)}")


def energy_kwh(power_kw: ArrayLike, dt_s: float, axis: int = 0) -> Any:
    """Energy (kWh) of a power trace sampled every ``dt_s`` seconds (rectangle rule).

    Regeneration (negative power) counts negative. ``sum(power_kw) * dt_s / 3600``.

    Parameters
    ----------
    power_kw : array_like
        Power over time (kW); time along ``axis``.
    dt_s : float
        Sample period (s), positive.
    axis : int
        Time axis (default 0); other axes (e.g. vehicles) are kept.

    Returns
    -------
    float or ndarray
        A float for a 1-D trace, else an array over the other axes.
    """
    if not (dt_s > 0 and math.isfinite(dt_s)):
        raise ConfigError(f"dt_s must be positive, got {dt_s}")
    total = np.sum(np.asarray(power_kw, dtype=np.float64), axis=axis) * (dt_s / 3600.0)
    return float(total) if np.ndim(total) == 0 else total


def kwh_per_100km(energy_kwh_: ArrayLike, distance_m: ArrayLike) -> Any:
    """Consumption in kWh per 100 km from energy (kWh) and distance (m); ``nan`` at 0 m."""
    e = np.asarray(energy_kwh_, dtype=np.float64)
    d = np.asarray(distance_m, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        res = np.where(d > 0, e * 1e5 / np.where(d > 0, d, 1.0), np.nan)
    return float(res) if res.ndim == 0 else res
