"""Head-to-tail string stability of a heterogeneous or mixed string: analytic and measured.

With humans or vehicle classes one follower pair may amplify while the string as a whole damps:
the test is the head-to-tail gain ``|A_N / A_0|`` of the last follower's acceleration over the
leader's, the product of the per-vehicle factors (Ge and Orosz, IEEE T-ITS 18(8), 2017; Wang,
Zheng et al., arXiv 2012.04313). Here each factor is the simulator's exact discrete loop, as
:func:`analysis.stability.discrete_gamma_response` is for one homogeneous pair, with the
vehicle's own actuator lag (its class, :mod:`envs.vehicle_classes`), its own controller and the
V2V delay in whole steps (``z^-d``: exact at every frequency).

The chain
---------
In ``z`` (step ``dt``), for follower ``i`` with lag gain ``beta_i = 1 - exp(-dt/tau_i)``::

    A_i = P_i C_i,  P_i = beta_i z / (z - 1 + beta_i)        (realised accel / command)
    V_i = dt P_i C_i / (z - 1)                                (speed)
    G_i = T (V_{i-1} - V_i),  T = dt (z + 1) / (2 (z - 1))    (trapezoidal gap)

and its command ``C_i = N_i V_{i-1} + F_i C_{i-1}`` with

- ``acc``/``cacc`` (Ploeg, :mod:`controllers.linear`; ``alpha = exp(-dt/h_i)``)::

      C_i (1 - alpha/z) = (1 - alpha) (kp (G_i - h_i V_i) + kd (V_{i-1} - V_i - h_i A_i / z)
                                       + M_i),     M_i = z^-(d+1) C_{i-1}

  (``M_i = 0`` for ``acc`` and behind a human, who sends nothing);
- a human, the IDM linearised about the equilibrium at the leader's mean speed
  (:func:`idm_partials`), its reaction delay ``r`` steps: ``C_i = z^-r (f_s G_i + f_v V_i +
  f_p V_{i-1})``.

The leader's command is its acceleration (``C_0 = A_0``, ``V_0 = dt C_0 / (z - 1)``), so
``C_i / C_{i-1} = N_i V_{i-1} / C_{i-1} + F_i`` and the head-to-tail transfer function is
``H(z) = P_N prod_i (C_i / C_{i-1})``: built with python-control, one transfer function per
vehicle (:func:`vehicle_factors`), multiplied (:func:`head_to_tail_gain`).

Measured: :func:`measured_head_to_tail` runs the ``sine-v1`` sweep of
:func:`analysis.stability.empirical_gain` on the arrangement and multiplies the measured pair
gains (the product of ``|A_i / A_{i-1}|`` is ``|A_N / A_0|``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from infra.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    import control

#: Controllers with an analytic per-vehicle model here.
ANALYTIC_CONTROLLERS: tuple[str, ...] = ("acc", "cacc", "idm")


@dataclass(frozen=True)
class VehicleLoop:
    """One follower of the chain: its lag and its law.

    Attributes
    ----------
    lag_s : float
        Actuator lag ``tau`` (0: none).
    law : {"ploeg", "idm"}
        Ploeg's law (``acc``/``cacc``) or a linearised IDM human.
    kp, kd, time_gap_s : float
        Ploeg's gains and this vehicle's time gap (``law="ploeg"``).
    feedforward : bool
        Whether it uses its predecessor's command over V2V (a predecessor that is human sends
        nothing: then False).
    idm_partials : (float, float, float)
        ``(f_s, f_v, f_p)`` of the linearised IDM (``law="idm"``).
    reaction_steps : int
        The human's reaction delay in steps.
    """

    lag_s: float
    law: str
    kp: float = 0.2
    kd: float = 0.7
    time_gap_s: float = 0.5
    feedforward: bool = False
    idm_partials: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reaction_steps: int = 0


def idm_partials(speed_mps: float, idm: Any = None) -> tuple[float, float, float, float]:
    """The IDM linearised at its equilibrium at ``speed_mps`` (own and predecessor's speed
    equal): ``(gap_m, f_s, f_v, f_p)`` with ``a ~ f_s ds + f_v dv + f_p dv_p``.

    From ``a = A [1 - (v/v0)^delta - (s*/s)^2]``, ``s* = s0 + v T + v (v - v_p) / (2 sqrt(A b))``
    at ``s*(v, 0) / s = sqrt(1 - (v/v0)^delta)``.
    """
    from envs.humans import IDMParams

    p = IDMParams() if idm is None else idm
    v = float(speed_mps)
    a_max, root = p.accel_max_mps2, 2.0 * math.sqrt(p.accel_max_mps2 * p.decel_comfort_mps2)
    s_star = p.standstill_m + v * p.time_gap_s
    gap = s_star / math.sqrt(1.0 - (v / p.desired_speed_mps) ** p.delta)
    f_s = 2.0 * a_max * s_star**2 / gap**3
    f_v = -a_max * (p.delta * v ** (p.delta - 1) / p.desired_speed_mps**p.delta
                    + 2.0 * s_star * (p.time_gap_s + v / root) / gap**2)
    f_p = a_max * 2.0 * s_star * (v / root) / gap**2
    return gap, f_s, f_v, f_p


def chain_of(scenario: Any, n_vehicles: int, controller: str, options: Mapping[str, Any] | None,
             delay_s: float = 0.0, lag_s: float = 0.0, dt_s: float = 0.1) -> list[VehicleLoop]:
    """The :class:`VehicleLoop` of every follower of ``scenario`` (its classes and humans) driven
    by ``controller`` (``acc``, ``cacc`` or the human model ``idm`` on the automated seats,
    with ``options``) at its target speed.

    Raises
    ------
    ConfigError
        For a controller without an analytic model, or humans other than the IDM.
    """
    from controllers.registry import make_controller
    from envs.params import PlatoonParams

    if controller not in ANALYTIC_CONTROLLERS:
        raise ConfigError(f"{controller} has no analytic head-to-tail model; analytic: "
                          f"{', '.join(ANALYTIC_CONTROLLERS)}")
    cfg: Any = make_controller(controller, **dict(options or {})).config
    arrangement = scenario.arrangement(n_vehicles)
    if not arrangement.homogeneous and arrangement.human_model != "idm":
        raise ConfigError("the analytic chain linearises IDM humans only; give human_model=idm")
    vehicles = scenario.vehicle_arrays(n_vehicles, PlatoonParams(lag_s=lag_s))
    lags = np.full(n_vehicles, lag_s) if vehicles is None else vehicles.lag_s
    h = (np.full(n_vehicles, getattr(cfg, "time_gap_s", 0.0)) if vehicles is None
         or controller == "idm" else cfg.time_gaps_s(vehicles.lag_s, delay_s))
    _, f_s, f_v, f_p = idm_partials(scenario.target_speed_mps)
    if controller == "idm":  # every seat a human (the controller's own IDM on automated ones)
        own = idm_partials(scenario.target_speed_mps, cfg.params)[1:]
        steps = arrangement.delay_steps(dt_s) if cfg.reaction_delay_s is None else int(
            round(cfg.reaction_delay_s / dt_s + 1e-9))
        return [VehicleLoop(float(lags[i]), "idm", idm_partials=(f_s, f_v, f_p) if not
                            arrangement.automated[i] else own,
                            reaction_steps=arrangement.delay_steps(dt_s) if not
                            arrangement.automated[i] else steps) for i in range(n_vehicles)]
    out = []
    for i in range(n_vehicles):
        if not arrangement.automated[i]:
            out.append(VehicleLoop(float(lags[i]), "idm", idm_partials=(f_s, f_v, f_p),
                                   reaction_steps=arrangement.delay_steps(dt_s)))
        else:
            sends = i == 0 or arrangement.automated[i - 1]
            out.append(VehicleLoop(float(lags[i]), "ploeg", cfg.kp, cfg.kd, float(h[i]),
                                   bool(cfg.feedforward) and sends))
    return out


def vehicle_ratio_tf(loop: VehicleLoop, pred_lag_s: float | None, delay_steps: int,
                     dt_s: float = 0.1) -> control.TransferFunction:
    """``C_i / C_{i-1}`` of one vehicle behind a predecessor with lag ``pred_lag_s`` (None: the
    leader, whose command is its acceleration), as a python-control transfer function in z."""
    import control

    dt = float(dt_s)
    z = control.tf([1.0, 0.0], [1.0], dt)
    one = control.tf([1.0], [1.0], dt)

    def lag(tau: float | None) -> control.TransferFunction:
        if not tau:
            return one
        beta = 1.0 - math.exp(-dt / tau)
        return beta * z / (z - (1.0 - beta))

    p_own, p_pred = lag(loop.lag_s), lag(pred_lag_s)
    integ = dt / (z - 1.0)
    v_own, v_pred = p_own * integ, p_pred * integ  # speed per command
    t_gap = dt * (z + 1.0) / (2.0 * (z - 1.0))
    if loop.law == "idm":
        f_s, f_v, f_p = loop.idm_partials
        d = one if loop.reaction_steps == 0 else one / z**loop.reaction_steps
        num = d * (f_s * t_gap + f_p) * v_pred
        den = one - d * (f_v - f_s * t_gap) * v_own
        return num / den
    h, kp, kd = loop.time_gap_s, loop.kp, loop.kd
    alpha = math.exp(-dt / h) if h > 0 else 0.0
    den = (one - alpha / z) + (1.0 - alpha) * ((kp * t_gap + kp * h + kd) * v_own
                                               + kd * h * p_own / z)
    num = (1.0 - alpha) * (kp * t_gap + kd) * v_pred
    if loop.feedforward:
        num = num + (1.0 - alpha) / z ** (delay_steps + 1)
    return num / den


def vehicle_factors(chain: Sequence[VehicleLoop], delay_s: float = 0.0, dt_s: float = 0.1
                    ) -> list[control.TransferFunction]:
    """The factors of ``H(z) = A_N / A_0``: every vehicle's :func:`vehicle_ratio_tf`, then the
    last vehicle's lag ``A_N / C_N`` (python-control transfer functions in z)."""
    import control

    if not chain:
        raise ConfigError("a chain needs at least one follower")
    d = int(round(delay_s / dt_s + 1e-9))
    factors = []
    pred: float | None = None
    for loop in chain:
        factors.append(vehicle_ratio_tf(loop, pred, d, dt_s))
        pred = loop.lag_s
    tau = chain[-1].lag_s
    if tau:
        beta = 1.0 - math.exp(-dt_s / tau)
        factors.append(control.tf([beta, 0.0], [1.0, -(1.0 - beta)], dt_s))
    return factors


def head_to_tail_gain(omega_rad_s: np.ndarray | float, chain: Sequence[VehicleLoop],
                      delay_s: float = 0.0, dt_s: float = 0.1) -> np.ndarray:
    """``|H(e^{j w dt})|`` at the frequencies ``omega_rad_s``: the product of the factors'
    responses (:func:`vehicle_factors`, each evaluated exactly on the unit circle)."""
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=np.float64))
    z = np.exp(1j * w * dt_s)
    out = np.ones(w.shape, dtype=np.complex128)
    for f in vehicle_factors(chain, delay_s, dt_s):
        out *= np.asarray(f(z)).reshape(w.shape)
    return np.abs(out)


@dataclass(frozen=True)
class HeadToTail:
    """Analytic and measured head-to-tail gains of one arrangement and controller.

    Attributes
    ----------
    omegas_rad_s : (W,)
    analytic, measured : (W,)
        ``|A_N / A_0|`` by :func:`head_to_tail_gain` and by the sweep.
    """

    scenario: str
    controller: str
    omegas_rad_s: np.ndarray
    analytic: np.ndarray
    measured: np.ndarray

    @property
    def max_relative_error(self) -> float:
        """Largest ``|measured - analytic| / analytic`` over the frequencies."""
        return float(np.max(np.abs(self.measured - self.analytic) / self.analytic))


def measured_head_to_tail(controller: str, scenario_options: Mapping[str, Any],
                          omegas_rad_s: Sequence[float] | np.ndarray, n_vehicles: int,
                          options: Mapping[str, Any] | None = None, delay_s: float = 0.0,
                          **sweep: Any) -> np.ndarray:
    """``|A_N / A_0|`` measured by :func:`analysis.stability.empirical_gain` on the ``sine-v1``
    leader with the arrangement ``scenario_options`` (the product of its pair gains)."""
    from analysis.stability import empirical_gain

    res = empirical_gain(controller, omegas_rad_s, options, n_vehicles=n_vehicles,
                         delay_s=delay_s, scenario_options=scenario_options, **sweep)
    return np.asarray(np.prod(res.pair_gain, axis=1))


def compare(controller: str, scenario_options: Mapping[str, Any],
            omegas_rad_s: Sequence[float] | np.ndarray, n_vehicles: int,
            options: Mapping[str, Any] | None = None, delay_s: float = 0.0,
            **sweep: Any) -> HeadToTail:
    """Analytic against measured head-to-tail gain of ``controller`` on ``sine-v1`` with the
    arrangement ``scenario_options`` (classes, humans; human noise is switched off)."""
    from envs.scenarios import make_scenario

    opts = {"human_noise_mps2": 0.0, **dict(scenario_options)}
    sc = make_scenario("sine-v1", **opts)
    chain = chain_of(sc, n_vehicles, controller, options, delay_s)
    w = np.asarray(omegas_rad_s, dtype=np.float64)
    return HeadToTail(sc.label, controller, w, head_to_tail_gain(w, chain, delay_s),
                      measured_head_to_tail(controller, opts, w, n_vehicles, options, delay_s,
                                            **sweep))
