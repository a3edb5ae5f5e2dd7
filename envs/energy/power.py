"""Runtime battery power: the fitted model ``P(v, u) = max(polynomial(v, u), floor(v))`` that the
reward, the MPC cost and the energy metric use (its fast evaluator and loader), the model dispatch
and energy integration.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from envs.energy.horner import FloatArray, Horner2D, evaluate
from envs.energy.vehicle import DEFAULT_POLYNOMIAL_FILE, _as_path, _bad
from infra.errors import ConfigError

#: Model names accepted by :func:`battery_power_kw`.
MODELS: tuple[str, ...] = ("poly", "map", "vtcpem")
#: Format tag of ``power_poly.json`` (version 2 adds the regeneration floor ``floor_kw``).
POLYNOMIAL_FORMAT = "cacc-bench power polynomial 2"
#: Format tags :func:`load_power_polynomial` reads.
READABLE_FORMATS: tuple[str, ...] = ("cacc-bench power polynomial 1", POLYNOMIAL_FORMAT)


class PowerPolynomial:
    """Fast evaluator of ``P(v, u) = max(sum_{k,j} p[k, j] v^k u^j, floor(v))`` (kW, SI arguments).

    The polynomial models the drive where regeneration is not limited; ``floor(v) = sum_i f[i] v^i``
    (optional) is the battery power when the regeneration limit holds it flat (hard braking, the
    friction brakes take the rest). Evaluation forms the powers of ``u``, multiplies by the
    coefficient matrix (one small GEMM per block of 8192 elements) and applies Horner's scheme in
    ``v``; no Python loop over elements. float32 inputs give float32 results (computed in
    float32); anything else gives float64. Safe to share between threads (no shared scratch).

    Parameters
    ----------
    coefficients_kw : array_like, shape (K, J)
        ``p[k, j]``, the coefficient of ``v^k u^j`` (kW / (m/s)^k / (m/s^2)^j); K, J >= 2.
    metadata : mapping, optional
        Provenance and fit quality (what ``power_poly.json`` holds besides the coefficients).
    floor_kw : array_like, shape (I,), optional
        ``f[i]``, the coefficient of ``v^i`` of the regeneration floor (kW / (m/s)^i); none when
        omitted (a plain polynomial).
    """

    __slots__ = ("_coef", "_floor", "_p", "_p_dv", "_p_du", "metadata")

    def __init__(
        self,
        coefficients_kw: ArrayLike,
        metadata: Mapping[str, Any] | None = None,
        floor_kw: ArrayLike | None = None,
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
        self._floor: NDArray[np.float64] | None = None
        if floor_kw is not None:
            floor = np.array(floor_kw, dtype=np.float64, copy=True)
            if floor.ndim != 1 or floor.size < 1 or not np.all(np.isfinite(floor)):
                raise ConfigError(
                    f"the regeneration floor must be a finite 1-D coefficient array, got {floor!r}"
                )
            floor.setflags(write=False)
            self._floor = floor
        k = np.arange(coef.shape[0], dtype=np.float64)[:, None]
        j = np.arange(coef.shape[1], dtype=np.float64)[None, :]
        self._p = Horner2D(coef)
        self._p_dv = Horner2D((coef * k)[1:])
        self._p_du = Horner2D((coef * j)[:, 1:])
        self.metadata: dict[str, Any] = dict(metadata or {})

    @property
    def coefficients_kw(self) -> NDArray[np.float64]:
        """``p[k, j]`` (read-only array, shape (K, J)): the coefficient of ``v^k u^j``."""
        return self._coef

    @property
    def floor_kw(self) -> NDArray[np.float64] | None:
        """``f[i]`` (read-only), the coefficient of ``v^i`` of the regeneration floor; or None."""
        return self._floor

    @property
    def degree(self) -> tuple[int, int]:
        """Highest powers of speed and acceleration."""
        return self._coef.shape[0] - 1, self._coef.shape[1] - 1

    @property
    def fingerprint(self) -> str:
        """12 hex digits identifying the coefficients (and floor): the energy model a policy was
        trained with, recorded in its checkpoint."""
        h = hashlib.sha256(self._coef.astype("<f8").tobytes())
        if self._floor is not None:
            h.update(b"floor")
            h.update(self._floor.astype("<f8").tobytes())
        return h.hexdigest()[:12]

    def __repr__(self) -> str:
        floor = "" if self._floor is None else f", floor degree {self._floor.size - 1}"
        return f"PowerPolynomial(degree={self.degree}{floor})"

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
        if self._floor is None:
            return evaluate(self._p, speed_mps, accel_mps2, out)
        v = np.asarray(speed_mps)
        floor = self.floor_at(v)
        result = evaluate(self._p, v, accel_mps2, out)
        return np.maximum(result, floor.astype(result.dtype, copy=False), out=result)

    def floor_at(self, speed_mps: ArrayLike) -> FloatArray:
        """The regeneration floor (kW) at speed (m/s); ``-inf`` without a floor."""
        v = np.asarray(speed_mps)
        dtype = np.float32 if v.dtype == np.float32 else np.float64
        if self._floor is None:
            return np.full(v.shape, -np.inf, dtype=dtype)
        f = self._floor.astype(dtype)
        out = np.full(v.shape, f[-1], dtype=dtype)
        for c in f[-2::-1]:
            out *= v
            out += c
        return out

    def _floor_binds(self, speed_mps: ArrayLike, accel_mps2: ArrayLike) -> NDArray[np.bool_]:
        v = np.asarray(speed_mps)
        return np.asarray(evaluate(self._p, v, accel_mps2, None) < self.floor_at(v))

    def dP_dv(
        self, speed_mps: ArrayLike, accel_mps2: ArrayLike, out: FloatArray | None = None
    ) -> FloatArray:
        """Partial derivative ``dP/dv`` (kW per m/s); arguments as :meth:`__call__` (the floor's
        slope where the floor binds)."""
        if self._floor is None:
            return evaluate(self._p_dv, speed_mps, accel_mps2, out)
        binds = self._floor_binds(speed_mps, accel_mps2)
        slope = np.polynomial.polynomial.polyval(np.asarray(speed_mps, dtype=np.float64),
                                                 np.polynomial.polynomial.polyder(self._floor))
        result = evaluate(self._p_dv, speed_mps, accel_mps2, out)
        result[...] = np.where(binds, slope, result)
        return result

    def dP_du(
        self, speed_mps: ArrayLike, accel_mps2: ArrayLike, out: FloatArray | None = None
    ) -> FloatArray:
        """Partial derivative ``dP/du`` (kW per m/s^2); arguments as :meth:`__call__` (0 where
        the floor binds)."""
        if self._floor is None:
            return evaluate(self._p_du, speed_mps, accel_mps2, out)
        binds = self._floor_binds(speed_mps, accel_mps2)
        result = evaluate(self._p_du, speed_mps, accel_mps2, out)
        result[...] = np.where(binds, 0.0, result)
        return result

    def expression(
        self, speed: Any, accel: Any, maximum: Callable[[Any, Any], Any] = max
    ) -> Any:
        """Evaluate with plain ``*`` and ``+`` (Horner): for Python floats or symbolic types.

        Works with CasADi ``SX``/``MX``, sympy symbols, Python floats (fast for one point).
        ``maximum(polynomial, floor)`` combines the two parts when there is a floor: the
        built-in ``max`` suits floats; pass ``casadi.fmax``, ``sympy.Max`` or a smooth maximum
        for symbolic arguments.
        """
        result: Any = None
        for row in self._p.rows[::-1]:
            inner: Any = row[-1]
            for c in row[-2::-1]:
                inner = inner * accel + c
            result = inner if result is None else result * speed + inner
        if self._floor is None:
            return result
        floor: Any = float(self._floor[-1])
        for c in self._floor[-2::-1]:
            floor = floor * speed + float(c)
        return maximum(result, floor)


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
    kind = "power polynomial file"
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise _bad(p, "not found (make it with `cacc-bench fit-power --write`)", kind) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _bad(p, f"cannot be read as JSON ({exc})", kind) from None
    if not isinstance(data, dict) or "coefficients_kw" not in data:
        raise _bad(p, "no 'coefficients_kw' entry", kind)
    try:
        coef = np.array(data["coefficients_kw"], dtype=np.float64)
    except (TypeError, ValueError):
        raise _bad(p, "'coefficients_kw' is not a numeric matrix", kind) from None
    if coef.ndim != 2 or coef.shape[0] < 2 or coef.shape[1] < 2 or not np.all(np.isfinite(coef)):
        raise _bad(p, "'coefficients_kw' must be a finite matrix of at least 2x2, got shape "
                      f"{coef.shape}", kind)
    fmt = data.get("format", READABLE_FORMATS[0])
    if fmt not in READABLE_FORMATS:
        raise _bad(p, f"format {fmt!r}, this cacc-bench reads "
                      f"{' or '.join(repr(f) for f in READABLE_FORMATS)}; remake it with "
                      "`cacc-bench fit-power --write`", kind)
    floor = data.get("floor_kw")
    if floor is not None:
        try:
            floor = np.array(floor, dtype=np.float64)
        except (TypeError, ValueError):
            floor = np.array([np.nan])
        if floor.ndim != 1 or floor.size < 1 or not np.all(np.isfinite(floor)):
            raise _bad(p, "'floor_kw' must be a finite list of coefficients", kind)
    metadata = {k: v for k, v in data.items() if k not in ("coefficients_kw", "floor_kw")}
    return PowerPolynomial(coef, metadata, floor)


@functools.lru_cache(maxsize=1)
def _default_polynomial() -> PowerPolynomial:
    return load_power_polynomial()


# ----------------------------------------------------------------------------- public entry points


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
    from envs.energy.map_model import map_battery_power_kw, vtcpem_battery_power_kw

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
