"""Runtime battery power: the fitted polynomial ``P(v, u)`` that the reward, the MPC cost and the
energy metric use (its fast evaluator and loader), the model dispatch and energy integration.
"""


from __future__ import annotations

import functools
import json
import math
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from envs.energy.vehicle import DEFAULT_POLYNOMIAL_FILE, EnergyDataError, _as_path
from envs.errors import ConfigError

FloatArray = NDArray[np.floating[Any]]

#: Model names accepted by :func:`battery_power_kw`.
MODELS: tuple[str, ...] = ("poly", "map", "vtcpem")
#: Format tag of ``power_poly.json``.
POLYNOMIAL_FORMAT = "cacc-bench power polynomial 1"

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
