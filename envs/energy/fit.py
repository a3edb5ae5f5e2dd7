"""The offline fit of the power polynomial to the map model (``cacc-bench fit-power``), with its
quality and provenance.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from envs.energy.map_model import map_battery_power_kw, map_operating_point
from envs.energy.power import POLYNOMIAL_FORMAT, PowerPolynomial
from envs.energy.vehicle import (
    DEFAULT_VEHICLE_FILE,
    LossMap,
    VehicleParams,
    _as_path,
    load_vehicle_params,
)
from infra.errors import ConfigError

FloatArray = NDArray[np.floating[Any]]

#: Version string written into the provenance of a fit (the package version when not installed).
CACC_BENCH_VERSION = "0.1.0"


@dataclass(frozen=True)
class PowerFit:
    """A least-squares fit of the power model to the map model, with its quality.

    Attributes
    ----------
    coefficients_kw : ndarray, shape (degree+1, degree+1)
        ``p[k, j]`` in SI units (kW, m/s, m/s^2), the coefficient of ``v^k u^j``.
    floor_kw : ndarray, shape (4,), or None
        ``f[i]``, the coefficient of ``v^i`` of the regeneration floor (the model is
        ``max(polynomial, floor)``); None for a plain polynomial.
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
    floor_kw: NDArray[np.float64] | None = None

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
        return PowerPolynomial(self.coefficients_kw, {"quality": self.quality(), "grid": self.grid},
                               self.floor_kw)

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
                "polynomial of speed v (m/s) and acceleration u (m/s^2), bounded below by the "
                "regeneration-limited power, a cubic in v; negative = regeneration."
            ),
            "formula": (
                "P_kW = sum_k sum_j coefficients_kw[k][j] * v_mps**k * u_mps2**j"
                if self.floor_kw is None else
                "P_kW = max(sum_k sum_j coefficients_kw[k][j] * v_mps**k * u_mps2**j, "
                "sum_i floor_kw[i] * v_mps**i)"
            ),
            "units": {"speed": "m/s", "acceleration": "m/s^2", "power": "kW"},
            "coefficients_kw": [[float(c) for c in row] for row in self.coefficients_kw],
            **({} if self.floor_kw is None else {"floor_kw": [float(c) for c in self.floor_kw]}),
            "quality": self.quality(),
            "grid": self.grid,
            "provenance": {
                "model": (
                    "envs.energy.map_battery_power_kw (docs/spec/energy.md): wheel force, gearbox, motor "
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
                    "envs.energy.fit_power_polynomial, written by commands.fit_power "
                    "(`cacc-bench fit-power --write`)"
                ),
                "cacc_bench_version": _package_version(),
                "numpy_version": np.__version__,
            },
        }


#: The operating points of the map model's reference table in ``docs/spec/energy.md``
#: (speed m/s, acceleration m/s^2), where ``cacc-bench fit-power`` reports the polynomial's error.
REFERENCE_POINTS: tuple[tuple[float, float], ...] = (
    (5.0, 0.0), (11.1, 0.0), (20.0, 0.0), (11.0, 1.0), (11.0, -1.0), (11.0, -3.0),
)


def reference_errors(
    polynomial: PowerPolynomial,
    params: VehicleParams | None = None,
    loss_map: LossMap | None = None,
) -> list[tuple[float, float, float, float, float]]:
    """The polynomial against the map model at :data:`REFERENCE_POINTS`.

    Returns
    -------
    list of (v_mps, u_mps2, map_kw, polynomial_kw, relative_error)
        ``relative_error = (polynomial_kw - map_kw) / |map_kw|``.
    """
    v, u = np.array(REFERENCE_POINTS).T
    ref = map_battery_power_kw(v, u, params, loss_map)
    got = polynomial(v, u)
    return [(float(a), float(b), float(m), float(g), float((g - m) / abs(m)))
            for a, b, m, g in zip(v, u, ref, got, strict=True)]


def _package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

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
    regeneration_floor: bool = True,
    weight_offset_kw: float | None = 2.0,
) -> PowerFit:
    """Least-squares fit of ``P(v, u) = max(sum p[k, j] v^k u^j, floor(v))`` to the map model.

    The grid is the full tensor grid of ``speed_range_mps`` x ``accel_range_mps2`` with the given
    steps (both ends included). A point enters the fit when the motor can reach it: motoring
    demand within the motor torque and power limits. Braking beyond the regeneration limits is
    kept (friction brakes take the rest, the battery sees the regeneration limit). With
    ``regeneration_floor`` the battery power there (flat in ``u``: the map model's value at the
    lowest acceleration of each speed) is fitted as a cubic ``floor(v)`` and the polynomial only
    on the points above it; a polynomial cannot follow that kink and flat region (the plain fit
    errs by 9.5 % at 11 m/s, -3 m/s^2; ``docs/energy-fit.md``). Least squares weighted by
    ``1 / (|P| + weight_offset_kw)`` per residual (relative errors at low power count; None:
    unweighted), in centred and scaled variables ``x = (v - c_v)/s_v``, ``y = (u - c_u)/s_u``
    (well conditioned); the result is converted exactly to SI coefficients. Deterministic.

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
    regeneration_floor : bool
        Fit the regeneration-limited power as its own term (default True).
    weight_offset_kw : float or None
        Offset of the residual weights (default 2 kW); None for unweighted least squares.

    Returns
    -------
    PowerFit

    Raises
    ------
    ConfigError
        Bad degree, ranges or offset, or (with the floor) a lowest acceleration at which the
        regeneration limit does not hold at every speed.
    """
    if degree < 1:
        raise ConfigError(f"degree must be >= 1, got {degree}")
    if weight_offset_kw is not None and not weight_offset_kw > 0:
        raise ConfigError(f"weight_offset_kw must be positive or None, got {weight_offset_kw}")
    speeds = _axis(*speed_range_mps, speed_step_mps)
    accels = _axis(*accel_range_mps2, accel_step_mps2)
    vg, ug = np.meshgrid(speeds, accels, indexing="ij")
    op = map_operating_point(vg, ug, params, loss_map)
    power_kw = op.battery_power_w / 1000.0
    mask = op.reachable
    v_all, u_all, y_all = vg[mask], ug[mask], power_kw[mask]
    floor_kw = None
    fit_mask = mask
    if regeneration_floor:
        limited = power_kw[:, 0]
        if not np.allclose(power_kw[:, 1], limited, atol=1e-6):
            raise ConfigError(
                f"the regeneration limit does not hold at u = {accels[0]:g} m/s^2 at every speed: "
                "extend accel_range_mps2 downwards or fit with regeneration_floor=False"
            )
        floor_kw = np.polynomial.polynomial.polyfit(speeds, limited, 3)
        fit_mask = mask & ~np.isclose(power_kw, limited[:, None], atol=1e-6)
    v, u, y = vg[fit_mask], ug[fit_mask], power_kw[fit_mask]

    cv, sv = 0.5 * (speeds[0] + speeds[-1]), 0.5 * (speeds[-1] - speeds[0])
    cu, su = 0.5 * (accels[0] + accels[-1]), 0.5 * (accels[-1] - accels[0])
    x, z = (v - cv) / sv, (u - cu) / su
    xp = np.vander(x, degree + 1, increasing=True)
    zp = np.vander(z, degree + 1, increasing=True)
    design = (xp[:, :, None] * zp[:, None, :]).reshape(x.size, -1)
    w = np.ones_like(y) if weight_offset_kw is None else 1.0 / (np.abs(y) + weight_offset_kw)
    q, *_ = np.linalg.lstsq(design * w[:, None], y * w, rcond=None)
    q = q.reshape(degree + 1, degree + 1)
    mv = _monomial_to_si(degree + 1, cv, sv)
    mu = _monomial_to_si(degree + 1, cu, su)
    coef = mv.T @ q @ mu

    pred = PowerPolynomial(coef, floor_kw=floor_kw)(v_all, u_all)
    err = pred - y_all
    low = v_all <= low_speed_max_mps + 1e-9

    def _quality(sel: NDArray[np.bool_]) -> tuple[float, float, float]:
        e, t = err[sel], y_all[sel]
        ss_res = float(np.sum(e * e))
        ss_tot = float(np.sum((t - t.mean()) ** 2))
        return 1.0 - ss_res / ss_tot, math.sqrt(ss_res / e.size), float(np.max(np.abs(e)))

    weighting = ("unweighted" if weight_offset_kw is None
                 else f"weighted by 1 / (|P| + {weight_offset_kw:g} kW) per residual")
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
            (f"regeneration floor: cubic least squares of the map model's power at u = "
             f"{accels[0]:g} m/s^2 (regeneration-limited at every speed) over v; polynomial: "
             f"linear least squares, {weighting}, on the {int(fit_mask.sum())} reachable points "
             "above the floor" if regeneration_floor else
             f"linear least squares, {weighting}, on the reachable points")
            + ", in centred, scaled variables, converted exactly to SI coefficients; quality "
            "(all reachable points) evaluated with the SI coefficients and the floor"
        ),
    }
    # the fields in order: r2, rmse_kw, max_abs_error_kw, then the same at low speed
    return PowerFit(coef, *_quality(np.ones_like(low)), *_quality(low), n_points=int(mask.sum()),
                    n_points_low_speed=int(low.sum()), grid=grid, floor_kw=floor_kw)
