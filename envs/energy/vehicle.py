"""Energy data of the efficiency-map model: the vehicle parameters and the motor loss map of the
BMW i3 (SUMO MMPEVEM ``.dat`` file, ``data/energy/bmw_i3.dat``), read and checked.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from infra.errors import ConfigError

FloatArray = NDArray[np.floating[Any]]

#: Folder of the energy data shipped with the package.
DATA_DIR: Path = Path(__file__).resolve().parent.parent / "data" / "energy"
#: The BMW i3 parameters and loss map (SUMO MMPEVEM, EPL-2.0).
DEFAULT_VEHICLE_FILE: Path = DATA_DIR / "bmw_i3.dat"
#: The shipped polynomial fit (coefficients and provenance).
DEFAULT_POLYNOMIAL_FILE: Path = DATA_DIR / "power_poly.json"

_SPEED_EPS_MPS = 1e-6  # below this the car stands: no rolling resistance (as SUMO)


class EnergyDataError(ConfigError):
    """A missing or malformed energy data file (a ``ValueError``; the message names the file)."""


def _bad(path: Path, what: str, kind: str = "energy data file") -> EnergyDataError:
    """The one message of a bad data file: ``<kind> <path>: <what>``."""
    return EnergyDataError(f"{kind} {path}: {what}")


@dataclass(frozen=True)
class VehicleParams:
    """Parameters of the efficiency-map model (defaults: BMW i3, ``docs/spec/energy.md``).

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
        for name in ("mass_kg", "wheel_radius_m", "gear_ratio", "motor_torque_max_nm",
                     "motor_power_max_w", "gravity_mps2", "battery_resistance_ohm",
                     "battery_voltage_v"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"VehicleParams.{name} must be positive, got "
                                  f"{getattr(self, name)}")
        for name in ("theta_kgm2", "rolling_coeff", "drag_coeff", "frontal_area_m2",
                     "regen_torque_max_nm", "regen_power_max_w", "aux_power_w", "air_density_kgm3"):
            if getattr(self, name) < 0:
                raise ConfigError(f"VehicleParams.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 < self.gear_efficiency <= 1:
            raise ConfigError(f"VehicleParams.gear_efficiency must be in (0, 1], got "
                              f"{self.gear_efficiency}")

    @property
    def equivalent_mass_kg(self) -> float:
        """Mass seen by the acceleration force, ``m + Theta / r^2`` (kg)."""
        return self.mass_kg + self.theta_kgm2 / self.wheel_radius_m**2


#: ``.dat`` key -> :class:`VehicleParams` field.
_DAT_KEYS: dict[str, str] = {
    "m": "mass_kg", "r_wheel": "wheel_radius_m", "Theta": "theta_kgm2", "c_rr": "rolling_coeff",
    "c_d": "drag_coeff", "A_front": "frontal_area_m2", "i_gear": "gear_ratio",
    "eta_gear": "gear_efficiency", "M_max": "motor_torque_max_nm", "P_max": "motor_power_max_w",
    "M_recup_max": "regen_torque_max_nm", "P_recup_max": "regen_power_max_w",
    "R_battery": "battery_resistance_ohm", "U_battery_0": "battery_voltage_v",
    "P_const": "aux_power_w",
}
_LOSS_MAP_KEY = "powerLossMapString"


def _read_dat(path: Path) -> dict[str, str]:
    """``key = value`` lines of a SUMO MMPEVEM ``.dat`` file (``#`` starts a comment)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise _bad(path, "not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise _bad(path, f"cannot be read ({exc})") from None
    entries: dict[str, str] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        key, sep, value = line.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key or not value:
            raise EnergyDataError(f"energy data file {path}, line {lineno}: expected "
                                  f"'key = value', got {raw.strip()!r}")
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
            raise _bad(p, f"missing parameter {key!r}")
        try:
            values[name] = float(entries[key])
        except ValueError:
            raise _bad(p, f"parameter {key!r} is not a number: {entries[key]!r}") from None
    try:
        return VehicleParams(**values)
    except ConfigError as exc:
        raise _bad(p, str(exc)) from None


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


def _bilinear(x_axis: NDArray[np.float64], y_axis: NDArray[np.float64],
              table: NDArray[np.float64], x: ArrayLike, y: ArrayLike) -> FloatArray:
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
    numbers = []
    for token in text.split(","):
        try:
            numbers.append(float(token))
        except ValueError:
            raise _bad(path, f"{_LOSS_MAP_KEY}: {what} has a non-number entry {token.strip()!r}"
                       ) from None
    return np.array(numbers, dtype=np.float64)


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
        raise _bad(p, f"missing {_LOSS_MAP_KEY!r}")
    parts = entries[_LOSS_MAP_KEY].split("|")
    if len(parts) != 3:
        raise _bad(p, f"{_LOSS_MAP_KEY} must have 3 '|'-separated parts (dimensions|axes|values), "
                      f"found {len(parts)}")
    if [s.strip() for s in parts[0].split(",")] != ["2", "1"]:
        raise _bad(p, f"{_LOSS_MAP_KEY} dimensions must be '2,1', got {parts[0]!r}")
    axes = parts[1].split(";")
    if len(axes) != 2:
        raise _bad(p, f"{_LOSS_MAP_KEY} needs 2 ';'-separated axes, found {len(axes)}")
    speed = _parse_numbers(axes[0], "speed axis", p)
    torque = _parse_numbers(axes[1], "torque axis", p)
    for name, axis in (("speed axis", speed), ("torque axis", torque)):
        if axis.size < 2 or not np.all(np.isfinite(axis)) or np.any(np.diff(axis) <= 0):
            raise _bad(p, f"{_LOSS_MAP_KEY}: the {name} must have at least 2 finite, strictly "
                          "increasing values")
    values = _parse_numbers(parts[2], "values", p)
    if values.size != speed.size * torque.size:
        raise _bad(p, f"{_LOSS_MAP_KEY} has {values.size} values, expected {torque.size} torques "
                      f"x {speed.size} speeds = {torque.size * speed.size}")
    if np.any(np.isinf(values)) or np.any(values < 0):
        raise _bad(p, f"{_LOSS_MAP_KEY} has infinite or negative losses")
    loss = values.reshape(torque.size, speed.size)
    empty = np.flatnonzero(np.isnan(loss).all(axis=0))
    if empty.size:
        raise _bad(p, f"{_LOSS_MAP_KEY}: speed column {speed[empty[0]]} rpm has no valid value")
    return LossMap(speed_rpm=speed, torque_nm=torque, loss_w=loss)


@functools.lru_cache(maxsize=1)
def _default_vehicle() -> tuple[VehicleParams, LossMap, NDArray[np.float64]]:
    loss_map = load_loss_map()
    return load_vehicle_params(), loss_map, loss_map.filled()
