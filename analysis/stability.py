"""String stability of platoon controllers: analytic for Ploeg's linear loop, measured for any.

Analytic (``docs/spec/controllers.md``), vehicle ``G(s) = 1 / (s^2 (tau s + 1))``, ``K(s) = kp + kd s``,
``H(s) = 1 + h s``, ``D(s) = exp(-theta s)``::

    Gamma(s) = (G K + D) / (H (1 + G K))      (CACC)
    Gamma(s) = G K / (H (1 + G K))            (ACC, no feedforward)

- :func:`gamma_response` evaluates it exactly on a frequency grid (``exp(-j w theta)``);
  :func:`gamma_tf` builds a python-control model with a Pade delay of a given order.
- :func:`hinf_norm` finds ``||Gamma||_inf`` and its frequency (dense log grid + bounded local
  refinement); :func:`hinf_norm_pade` is the second way (``control.norm(sys, p='inf')``).
- :func:`internally_stable` checks that ``tau s^3 + s^2 + kd s + kp`` is Hurwitz; :func:`h_min`
  bisects the time gap for the smallest string-stable ``h``.
- :func:`discrete_gamma_response` and :func:`discrete_gamma_tf`: the exact discrete closed loop of
  the simulator (``controllers.linear``'s discretised law + the env's discrete physics: speed
  Euler step, trapezoidal gap, exact first-order actuator lag, V2V delay in whole steps), which
  is what the empirical curve of ``cacc``/``acc`` must reproduce.

Measured, for any registered controller:

- :func:`empirical_gain` drives the ``sine-v1`` leader profile at each frequency (all frequencies
  in one env batch), drops the transient and fits a sinusoid at the driving frequency by least
  squares to every vehicle's acceleration: the amplitude ratio of consecutive vehicles is the
  empirical ``|Gamma(j w)|``. The measurement is :func:`benchmark.sweep.measure_gains` (the
  harness's standard sweep, which every leaderboard row carries, is the same measurement on a
  fixed grid: :func:`benchmark.sweep.sweep_peak`); :func:`fit_sinusoid` is re-exported here.
- :func:`time_domain_string_gain` (accelerations) and :func:`spacing_string_gain` (spacing errors)
  work on any run; they live in :mod:`benchmark.string_gain` (the harness's metrics use them)
  and are re-exported here.

``control`` (python-control) is imported inside the functions that need it (it costs > 1 s).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from benchmark.string_gain import STRING_GAIN_TOL as STRING_GAIN_TOL
from benchmark.string_gain import spacing_string_gain as spacing_string_gain
from benchmark.string_gain import time_domain_string_gain as time_domain_string_gain
from benchmark.sweep import Measured
from benchmark.sweep import fit_sinusoid as fit_sinusoid
from infra.errors import ConfigError
from infra.interrupt import raise_if_interrupted
from infra.limits import check_nonnegative

if TYPE_CHECKING:  # pragma: no cover
    import control

#: Tolerance of the analytic norm against the bound 1 (``Gamma(0) = 1`` exactly).
ANALYTIC_TOL = 1e-9


@dataclass(frozen=True)
class PloegLoop:
    """Parameters of Ploeg's loop for analysis (one follower pair of a homogeneous platoon).

    Attributes
    ----------
    kp, kd : float
        Controller gains (> 0).
    time_gap_s : float
        Time gap h (>= 0).
    delay_s : float
        V2V delay theta of the feedforward (>= 0; irrelevant without feedforward).
    lag_s : float
        Actuator lag tau (>= 0).
    feedforward : bool
        CACC (True) or ACC (False).
    """

    kp: float = 0.2
    kd: float = 0.7
    time_gap_s: float = 0.5
    delay_s: float = 0.0
    lag_s: float = 0.0
    feedforward: bool = True

    def __post_init__(self) -> None:
        check_nonnegative(self.kp, "kp", positive=True)
        check_nonnegative(self.kd, "kd", positive=True)
        check_nonnegative(self.time_gap_s, "time_gap_s")
        check_nonnegative(self.delay_s, "delay_s")
        check_nonnegative(self.lag_s, "lag_s")

    def replace(self, **changes: Any) -> PloegLoop:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_controller(
        cls, controller: Any, delay_s: float = 0.0, lag_s: float = 0.0
    ) -> PloegLoop:
        """The loop of a ``controllers.linear`` controller (``acc``/``cacc``) in a run's settings."""
        cfg = getattr(controller, "config", None)
        needed = ("kp", "kd", "time_gap_s", "feedforward")
        if cfg is None or not all(hasattr(cfg, k) for k in needed):
            raise ConfigError(
                f"controller {getattr(controller, 'name', controller)!r} has no analytic "
                "string-stability model (only Ploeg's linear laws acc and cacc have one)"
            )
        return cls(cfg.kp, cfg.kd, cfg.time_gap_s, delay_s, lag_s, bool(cfg.feedforward))


@dataclass(frozen=True)
class NormResult:
    """``||Gamma||_inf`` and where it is reached (``omega_rad_s = 0`` when the sup is Gamma(0))."""

    gain: float
    omega_rad_s: float

    @property
    def string_stable(self) -> bool:
        """Whether the gain is within the bound 1 (tolerance :data:`ANALYTIC_TOL`)."""
        return self.gain <= 1.0 + ANALYTIC_TOL


# ----------------------------------------------------------------------------------- continuous


def gamma_response(omega_rad_s: np.ndarray | float, loop: PloegLoop) -> np.ndarray:
    """Exact ``Gamma(j w)`` (complex, same shape as ``omega_rad_s``), delay as ``exp(-j w theta)``."""
    s = 1j * np.asarray(omega_rad_s, dtype=np.float64)
    k = loop.kp + loop.kd * s
    plant_inv = s * s * (loop.lag_s * s + 1.0)  # 1 / G
    num = k + np.exp(-s * loop.delay_s) * plant_inv if loop.feedforward else k
    return num / ((1.0 + loop.time_gap_s * s) * (plant_inv + k))


def gamma_tf(loop: PloegLoop, pade_order: int = 5) -> control.TransferFunction:
    """``Gamma(s)`` as a python-control transfer function, the delay by a Pade approximant.

    ``Gamma = (K + D / G) / (H (1 / G + K))`` written as one ratio of polynomials.
    """
    import control

    if pade_order < 1:
        raise ConfigError(f"the Pade order must be >= 1, got {pade_order}")
    if loop.feedforward and loop.delay_s > 0:
        d_num, d_den = (
            np.asarray(p, dtype=np.float64) for p in control.pade(loop.delay_s, pade_order)
        )
    else:
        d_num = d_den = np.array([1.0])
    k = np.array([loop.kd, loop.kp])
    plant_inv = np.array([loop.lag_s, 1.0, 0.0, 0.0])
    h = np.array([loop.time_gap_s, 1.0])
    if loop.feedforward:
        num = np.polyadd(np.polymul(k, d_den), np.polymul(d_num, plant_inv))
        den = np.polymul(h, np.polymul(np.polyadd(plant_inv, k), d_den))
    else:
        num, den = k, np.polymul(h, np.polyadd(plant_inv, k))
    return control.tf(np.trim_zeros(num, "f"), np.trim_zeros(den, "f"))


def _peak(fun: Any, omega_min: float, omega_max: float, n_grid: int) -> NormResult:
    """sup over [omega_min, omega_max] of ``|fun(w)|``, with the value 1 at w = 0 included."""
    from scipy.optimize import minimize_scalar

    w = np.geomspace(omega_min, omega_max, n_grid)
    g = np.abs(fun(w))
    i = int(np.argmax(g))
    best_g, best_w = float(g[i]), float(w[i])
    lo, hi = w[max(i - 1, 0)], w[min(i + 1, n_grid - 1)]
    if hi > lo:
        res = minimize_scalar(
            lambda x: -float(np.abs(fun(np.array([x])))[0]),
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 1e-10 * max(1.0, hi)},
        )
        if -res.fun > best_g:
            best_g, best_w = float(-res.fun), float(res.x)
    if best_g <= 1.0:
        return NormResult(1.0, 0.0)
    return NormResult(best_g, best_w)


def hinf_norm(
    loop: PloegLoop, omega_min: float = 1e-3, omega_max: float = 1e2, n_grid: int = 3000
) -> NormResult:
    """``||Gamma||_inf`` with the exact delay: dense log grid, then a bounded local refinement.

    Returns ``NormResult(1, 0)`` when the sup is ``Gamma(0) = 1`` (string stable).
    """
    return _peak(lambda w: gamma_response(w, loop), omega_min, omega_max, n_grid)


def hinf_norm_pade(loop: PloegLoop, pade_order: int = 5, tol: float = 1e-9) -> float:
    """``||Gamma||_inf`` of the Pade model by ``control.norm(sys, p='inf')`` (second method)."""
    import control

    return float(control.norm(gamma_tf(loop, pade_order), p="inf", tol=tol))


def internally_stable(loop: PloegLoop) -> bool:
    """Whether ``tau s^3 + s^2 + kd s + kp`` is Hurwitz (then Gamma is stable too for h >= 0)."""
    poly = [loop.lag_s, 1.0, loop.kd, loop.kp] if loop.lag_s > 0 else [1.0, loop.kd, loop.kp]
    return bool(np.all(np.roots(poly).real < 0))


def _excess(loop: PloegLoop, w: np.ndarray) -> float:
    """max over w of ``(|Gamma(jw)|^2 - 1) / w^2``: > 0 iff string unstable (tends to the
    low-frequency curvature as w -> 0, so it changes sign linearly in h at h_min)."""
    g = gamma_response(w, loop)
    return float(np.max((g.real**2 + g.imag**2 - 1.0) / (w * w)))


def h_min(
    kp: float = 0.2,
    kd: float = 0.7,
    delay_s: float = 0.0,
    lag_s: float = 0.0,
    feedforward: bool = True,
    h_max_s: float = 20.0,
    tol_s: float = 1e-7,
) -> float:
    """Smallest string-stable time gap (s) by bisection on h (``inf`` if none up to ``h_max_s``).

    Criterion: ``max_w (|Gamma(jw)|^2 - 1) / w^2 <= 0`` on a log grid 1e-4..1e2 rad/s.
    Raises :class:`ConfigError` if the loop is not internally stable.
    """
    loop = PloegLoop(kp, kd, 0.0, delay_s, lag_s, feedforward)
    if not internally_stable(loop):
        raise ConfigError(
            f"kd = {kd} <= lag_s * kp = {lag_s * kp}: the loop is not internally stable"
        )
    w = np.geomspace(1e-4, 1e2, 3000)
    if _excess(loop.replace(time_gap_s=h_max_s), w) > 0:
        return math.inf
    lo, hi = 0.0, float(h_max_s)
    if _excess(loop, w) <= 0:
        return 0.0
    while hi - lo > tol_s:
        raise_if_interrupted()
        mid = 0.5 * (lo + hi)
        if _excess(loop.replace(time_gap_s=mid), w) > 0:
            lo = mid
        else:
            hi = mid
    return hi


def peak_gain_grid(
    time_gaps_s: Sequence[float] | np.ndarray,
    delays_s: Sequence[float] | np.ndarray,
    kp: float = 0.2,
    kd: float = 0.7,
    lag_s: float = 0.0,
    feedforward: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """``||Gamma||_inf`` and its frequency over a grid of time gaps x delays, ``(n_h, n_theta)``."""
    hs = np.asarray(time_gaps_s, dtype=np.float64)
    ths = np.asarray(delays_s, dtype=np.float64)
    gain = np.empty((len(hs), len(ths)))
    omega = np.empty_like(gain)
    for i, h in enumerate(hs):
        for j, th in enumerate(ths):
            raise_if_interrupted()
            res = hinf_norm(PloegLoop(kp, kd, float(h), float(th), lag_s, feedforward), n_grid=1500)
            gain[i, j], omega[i, j] = res.gain, res.omega_rad_s
    return gain, omega


# ------------------------------------------------------------------------------------- discrete


def _discrete_parts(loop: PloegLoop, dt_s: float) -> tuple[float, float, int]:
    dt = check_nonnegative(dt_s, "dt_s", positive=True)
    h = loop.time_gap_s
    alpha = math.exp(-dt / h) if h > 0 else 0.0
    beta = 1.0 if loop.lag_s == 0 else 1.0 - math.exp(-dt / loop.lag_s)
    d = int(round(loop.delay_s / dt + 1e-9))
    return alpha, beta, d


def discrete_gamma_response(
    omega_rad_s: np.ndarray | float, loop: PloegLoop, dt_s: float = 0.1, pair: str = "follower"
) -> np.ndarray:
    """``Gamma(e^{j w dt})`` of the simulator's exact discrete loop (complex).

    Model (deviations from equilibrium, step ``k``)::

        a[k]   = a[k-1] + beta (c[k] - a[k-1])                 beta = 1 - exp(-dt/tau)
        v[k+1] = v[k] + dt a[k]
        gap[k+1] = gap[k] + dt/2 (v_p[k] + v_p[k+1] - v[k] - v[k+1])
        c[k]   = alpha c[k-1] + (1 - alpha) (kp e[k] + kd (v_p[k] - v[k] - h a[k-1]) + m[k])
        m[k]   = c_{i-1}[k - 1 - d]                             d = round(theta/dt)

    Parameters
    ----------
    pair : {"follower", "leader"}
        ``follower``: acceleration of follower i over follower i-1 (= the command ratio; what
        string stability is about). ``leader``: follower 1 over the leader, whose acceleration
        is its speed profile's difference (no lag), so it differs when ``lag_s > 0``.
    """
    if pair not in ("follower", "leader"):
        raise ConfigError(f"pair must be 'follower' or 'leader', got {pair!r}")
    alpha, beta, d = _discrete_parts(loop, dt_s)
    z = np.exp(1j * np.asarray(omega_rad_s, dtype=np.float64) * dt_s)
    zi = 1.0 / z
    pa = beta * z / (z - (1.0 - beta))  # accel / command
    pv = dt_s * pa / (z - 1.0)  # speed / command
    tg = dt_s * (z + 1.0) / (2.0 * (z - 1.0))  # gap / (v_p - v)
    kp, kd, h = loop.kp, loop.kd, loop.time_gap_s
    den = (1.0 - alpha * zi) + (1.0 - alpha) * ((kp * tg + kp * h + kd) * pv + kd * h * zi * pa)
    ff = zi ** (d + 1) if loop.feedforward else 0.0
    if pair == "follower":
        return (1.0 - alpha) * ((kp * tg + kd) * pv + ff) / den
    pv0 = dt_s / (z - 1.0)  # leader: accel = its "command", no lag
    return pa * (1.0 - alpha) * ((kp * tg + kd) * pv0 + ff) / den


def discrete_gamma_tf(loop: PloegLoop, dt_s: float = 0.1) -> control.TransferFunction:
    """The follower-pair discrete ``Gamma(z)`` of :func:`discrete_gamma_response` as a
    python-control transfer function with sampling time ``dt_s`` (polynomials in z)."""
    import control

    alpha, beta, d = _discrete_parts(loop, dt_s)
    kp, kd, h, dt, lam = loop.kp, loop.kd, loop.time_gap_s, float(dt_s), 1.0 - beta
    P = np.polynomial.Polynomial
    z = P([0.0, 1.0])
    zm1, zl, za = z - 1.0, z - lam, z - alpha
    core = dt * beta * z**2 * (kp * dt * (z + 1.0) + 2.0 * kd * zm1)
    den_core = dt * beta * z**2 * (kp * dt * (z + 1.0) + 2.0 * (kp * h + kd) * zm1)
    den_core = den_core + 2.0 * kd * h * beta * zm1**2 * z
    den = 2.0 * zm1**2 * zl * za + (1.0 - alpha) * den_core
    if loop.feedforward:
        num = (1.0 - alpha) * (core * z**d + 2.0 * zm1**2 * zl)
        den = den * z**d
    else:
        num = (1.0 - alpha) * core
    # numpy Polynomial coefficients are lowest order first; python-control wants highest first
    num_c = np.trim_zeros(num.coef[::-1], "f")
    den_c = np.trim_zeros(den.coef[::-1], "f")
    return control.tf(num_c, den_c, dt)


def discrete_hinf_norm(loop: PloegLoop, dt_s: float = 0.1, n_grid: int = 3000) -> NormResult:
    """``sup_w |Gamma(e^{j w dt})|`` over (0, pi/dt] for the follower pair of the discrete loop."""
    return _peak(lambda w: discrete_gamma_response(w, loop, dt_s), 1e-3, math.pi / dt_s, n_grid)


def discrete_internally_stable(loop: PloegLoop, dt_s: float = 0.1) -> bool:
    """Whether the poles of the discrete loop lie strictly inside the unit circle."""
    tf = discrete_gamma_tf(loop, dt_s)
    return bool(np.all(np.abs(np.roots(np.asarray(tf.den[0][0]))) < 1.0))


# ------------------------------------------------------------------------------- empirical


@dataclass(frozen=True)
class EmpiricalGain(Measured):
    """A measured frequency sweep of one controller: :class:`benchmark.sweep.Measured` (its
    ``gain`` the empirical ``|Gamma(jw)|``), and what was measured in what setting.

    Attributes
    ----------
    controller : str
        Registered name.
    n_vehicles : int
    amplitude_mps : float
        The leader's speed amplitude.
    delay_s, lag_s : float
        V2V delay and actuator lag.
    transient_s : float
        The discarded start.
    """

    controller: str
    n_vehicles: int
    amplitude_mps: float
    delay_s: float
    lag_s: float
    transient_s: float


def empirical_gain(
    controller_name: str,
    omegas_rad_s: Sequence[float] | np.ndarray,
    options: Mapping[str, Any] | None = None,
    *,
    n_vehicles: int = 4,
    amplitude_mps: float = 0.1,
    delay_s: float = 0.0,
    lag_s: float = 0.0,
    packet_loss: float = 0.0,
    transient_s: float = 60.0,
    periods: float = 2.0,
    min_window_s: float = 30.0,
    seed: int = 2000,
    scenario_options: Mapping[str, Any] | None = None,
) -> EmpiricalGain:
    """Measure ``|Gamma(jw)|`` of any registered controller with the ``sine-v1`` leader.

    All frequencies run as one batch of episodes (episode k's leader follows the ``sine-v1``
    profile at ``f = w_k / 2 pi``, built by the scenario itself), lengthened when needed so that
    after ``transient_s`` at least ``max(periods / f, min_window_s)`` remain for the fit.

    Parameters
    ----------
    controller_name : str
        Registered controller name.
    omegas_rad_s : (W,) floats
        Driving frequencies, in (0, pi/dt).
    options : mapping, optional
        Controller options (as on the command line).
    n_vehicles : int
        Followers N (>= 2; the gain is taken over follower pairs).
    amplitude_mps : float
        Leader speed amplitude; keep it small so that nothing saturates.
    delay_s, lag_s, packet_loss : float
        V2V delay, actuator lag and packet loss of the run.
    transient_s : float
        Start discarded before the fit.
    periods, min_window_s : float
        Fit window length: at least this many periods and this many seconds.
    seed : int
        Seed of the first episode (episode k gets ``seed + 10 k``; only the channel uses it).
    scenario_options : mapping, optional
        Arrangement options of the ``sine-v1`` episodes (``classes``, ``humans``, ...; the
        head-to-tail analysis of :mod:`analysis.head_to_tail`).
    """
    from benchmark.sweep import measure_gains
    from controllers.registry import make_controller
    from envs.channel import ChannelConfig
    from envs.params import PlatoonParams

    params = PlatoonParams(lag_s=check_nonnegative(lag_s, "lag_s"))
    channel = ChannelConfig(check_nonnegative(delay_s, "delay_s"), packet_loss, params.dt_s)
    check_nonnegative(amplitude_mps, "amplitude_mps", positive=True)
    ctrl = make_controller(controller_name, **dict(options or {}))
    m = measure_gains(ctrl, omegas_rad_s, amplitude_mps, n_vehicles=n_vehicles, params=params,
                      channel=channel, transient_s=transient_s, periods=periods,
                      min_window_s=min_window_s, seed=seed, scenario_options=scenario_options)
    return EmpiricalGain(
        **{f.name: getattr(m, f.name) for f in dataclasses.fields(m)},
        controller=controller_name, n_vehicles=int(n_vehicles),
        amplitude_mps=float(amplitude_mps), delay_s=float(delay_s), lag_s=float(lag_s),
        transient_s=float(transient_s),
    )
