"""String gains measured on any run, in the time domain (the harness's metrics and the analysis).

- :func:`time_domain_string_gain`: ``max_i ||a_i||_2 / ||a_{i-1}||_2`` on accelerations.
- :func:`spacing_string_gain`: the same ratio on the followers' spacing errors.

The controller's own string stability, the same frequency sweep for every controller that each
leaderboard row carries, is :mod:`benchmark.sweep`.

:mod:`analysis.stability` re-exports both with the analytic and empirical gains.
"""

from __future__ import annotations

import math

import numpy as np

#: Tolerance of the time-domain and empirical string gains: string stable if gain <= 1 + tol
#: (also the leaderboard's mark on the standard frequency sweep, ``benchmark.sweep.SWEEP_TOL``).
STRING_GAIN_TOL = 1e-2


def is_string_stable(gain: float) -> bool:
    """Whether a measured string gain is at most ``1 + STRING_GAIN_TOL`` (NaN, inf: never)."""
    return bool(math.isfinite(gain) and gain <= 1.0 + STRING_GAIN_TOL)


def time_domain_string_gain(accel_mps2: np.ndarray, min_norm: float = 1e-9) -> np.ndarray | float:
    """``max_i ||a_i||_2 / ||a_{i-1}||_2`` over the followers of a run.

    Parameters
    ----------
    accel_mps2 : (..., T, N+1)
        Accelerations over time, the leader in column 0 (leading batch axes allowed).
    min_norm : float
        Pairs whose predecessor's norm is at most this (e.g. a leader at constant speed) are
        skipped; NaN if no pair is left.

    Returns
    -------
    float or (...) array
        String stable if ``<= 1 + STRING_GAIN_TOL``.
    """
    norms = np.linalg.norm(np.asarray(accel_mps2, dtype=np.float64), axis=-2)  # (..., V)
    num, den = norms[..., 1:], norms[..., :-1]
    ok = den > min_norm
    ratio = np.where(ok, num / np.where(ok, den, 1.0), -np.inf)
    out = np.max(ratio, axis=-1)
    out = np.where(np.isfinite(out), out, np.nan)
    return float(out) if out.ndim == 0 else out


def spacing_string_gain(spacing_error_m: np.ndarray, min_norm: float = 1e-9) -> np.ndarray | float:
    """``max_{i>=2} ||e_i||_2 / ||e_{i-1}||_2`` on spacing errors ``(..., T, N)`` of followers."""
    return time_domain_string_gain(spacing_error_m, min_norm)
