"""Ploeg's constant time-gap laws: ``acc`` (no V2V) and ``cacc`` (predecessor's command over V2V).

The law (Ploeg, van de Wouw, Nijmeijer, IEEE TCST 22(2), 2014) for follower ``i``::

    h du_i/dt = -u_i + kp e_i + kd de_i/dt + u_{i-1}(t - theta),   e_i = gap_i - (r + h v_i)

with ``de_i/dt = (v_{i-1} - v_i) - h a_i`` (the measured relative speed is exactly the gap's
derivative; ``a_i`` is the vehicle's realised acceleration, the actuator state). ``acc`` is the
same law with the feedforward ``u_{i-1}`` switched off.

Discretisation (dt of the run, 0.1 s)
--------------------------------------
The filter ``h du/dt = -u + w`` is discretised exactly for an input held over a step
(``alpha = exp(-dt/h)``), with the current measurement entering the command of the current step::

    c_i[k] = clip(alpha c_i[k-1] + (1 - alpha) (kp e_i[k] + kd de_i[k] + m_i[k]), a_min, a_max)

``c_i[k]`` is the command applied over step ``k`` and it is Ploeg's filter state ``u_i``. The
state is clipped to the command bounds, i.e. it is exactly what the env applies (anti-windup:
the filter never integrates a command the actuator does not get). With ``h = 0`` the law is
algebraic (``alpha = 0``).

V2V timing: every vehicle broadcasts the command it applies over step ``k`` (the leader its planned
acceleration ``(v0[k+1] - v0[k]) / dt``) through its declared message ``cacc_u`` (width 1),
after computing it; a message that arrives after ``d = round(theta / dt)`` steps is used from the
next control update on (one step of computation latency), so ``m_i[k] = c_{i-1}[k - 1 - d]`` and
losses hold the last message. This timing is the same for the leader-follower pair and every
follower pair, and its closed loop with the env's discrete physics is modelled exactly by
:func:`analysis.stability.discrete_gamma_response`. The filter path from a held (ZOH) message to
``u_i`` is the exact step-invariant transform of ``1 / (1 + h s)``, which is why this timing
stays within 1-2 % of the continuous ``||Gamma||_inf`` at dt = 0.1 s (e.g. 1.0628 against
1.0486 for h = 0.5 s, theta = 0.2 s, tau = 0.1 s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controllers.base import Controller, EpisodeContext, Message, SpacingPolicy
from envs.channel import V2VChannel
from envs.params import PlatoonParams
from envs.platoon import PlatoonState
from envs.scenarios import Scenario
from infra.errors import ConfigError
from infra.limits import MAX_LINEAR_GAIN, MAX_SPACING_M, MAX_TIME_GAP_S


def _finite(value: float, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    return float(value)


#: How ``acc``/``cacc`` choose each vehicle's time gap on a string of vehicle classes.
TIME_GAP_RULES: tuple[str, ...] = ("fixed", "xiao")


@dataclass(frozen=True)
class PloegConfig:
    """Gains and spacing policy of Ploeg's constant time-gap law (Plexe's defaults).

    Attributes
    ----------
    time_gap_s : float
        Time gap h of the spacing policy ``r + h v`` (s), in [0, ``MAX_TIME_GAP_S``]
        (:data:`infra.limits.MAX_TIME_GAP_S`).
    kp : float
        Gain on the spacing error (1/s^2), > 0.
    kd : float
        Gain on the spacing-error rate (1/s), > 0; internal stability needs ``kd > lag_s kp``
        (checked at reset, when the run's actuator lag is known).
    standstill_m : float or None
        Standstill distance r (m), in [0, ``MAX_SPACING_M``] (:data:`infra.limits.MAX_SPACING_M`);
        None chooses ``r = d* - h v*`` so that the scenario's target gap holds at its target
        speed (r may then be negative for a large h).
    feedforward : bool
        Use the predecessor's commanded acceleration received over V2V (CACC).
    time_gap_rule : {"fixed", "xiao"}
        On a string of vehicle classes (:mod:`envs.vehicle_classes`): ``fixed`` gives every
        vehicle ``time_gap_s``; ``xiao`` gives vehicle ``i`` the time gap
        ``h_i = max(time_gap_s, 2 (theta + tau_i))`` of Xiao, Darbha and Gao's condition
        (ITSC 2008) for its own lag ``tau_i`` and the run's V2V delay ``theta``, with its
        standstill distance ``d* - h_i v*`` (the scenario's target gap held at its target speed
        by every vehicle). The homogeneous platoon ignores the rule.
    """

    time_gap_s: float = 0.5
    kp: float = 0.2
    kd: float = 0.7
    standstill_m: float | None = None
    feedforward: bool = True
    time_gap_rule: str = "fixed"

    def __post_init__(self) -> None:
        h = _finite(self.time_gap_s, "time_gap_s")
        kp = _finite(self.kp, "kp")
        kd = _finite(self.kd, "kd")
        if h < 0:
            raise ConfigError(f"time_gap_s must be >= 0 s, got {h}")
        if h > MAX_TIME_GAP_S:
            raise ConfigError(f"time_gap_s must be at most {MAX_TIME_GAP_S:g} s, got {h:g}")
        if kp <= 0:
            raise ConfigError(f"kp must be > 0 (spacing feedback), got {kp}")
        if kd <= 0:
            raise ConfigError(
                f"kd must be > 0: tau s^3 + s^2 + kd s + kp is not Hurwitz otherwise, got {kd}"
            )
        for name, gain in (("kp", kp), ("kd", kd)):
            if gain > MAX_LINEAR_GAIN:
                raise ConfigError(f"{name} must be at most {MAX_LINEAR_GAIN:g} (a larger gain "
                                  f"only switches between the acceleration bounds), got {gain:g}")
        if self.standstill_m is not None:
            r = _finite(self.standstill_m, "standstill_m")
            if r < 0:
                raise ConfigError(f"standstill_m must be >= 0 m, got {r}")
            if r > MAX_SPACING_M:
                raise ConfigError(f"standstill_m must be at most {MAX_SPACING_M:g} m, got {r:g}")
        if not isinstance(self.feedforward, bool):
            raise ConfigError(f"feedforward must be true or false, got {self.feedforward!r}")
        if self.time_gap_rule not in TIME_GAP_RULES:
            raise ConfigError(f"time_gap_rule must be one of {', '.join(TIME_GAP_RULES)}, got "
                              f"{self.time_gap_rule!r}")
        if self.time_gap_rule != "fixed" and self.standstill_m is not None:
            raise ConfigError("time_gap_rule=xiao sets each vehicle's standstill distance "
                              "d* - h_i v*; leave standstill_m out")

    def time_gaps_s(self, lag_s: np.ndarray, delay_s: float) -> np.ndarray:
        """Each vehicle's time gap ``(N,)`` by :attr:`time_gap_rule` for lags ``lag_s (N,)``
        and the V2V delay ``delay_s``."""
        h = np.full(np.shape(lag_s), float(self.time_gap_s))
        if self.time_gap_rule == "xiao":
            h = np.maximum(h, 2.0 * (delay_s + np.asarray(lag_s, dtype=np.float64)))
        return h

    def check_lag(self, lag_s: float) -> None:
        """Raise :class:`ConfigError` if the loop is not internally stable with this lag.

        ``tau s^3 + s^2 + kd s + kp`` is Hurwitz iff ``kp > 0``, ``kd > 0`` and ``kd > tau kp``.
        """
        if lag_s > 0 and self.kd <= lag_s * self.kp:
            raise ConfigError(
                f"kd = {self.kd} <= lag_s * kp = {lag_s} * {self.kp} = {lag_s * self.kp}: "
                "the vehicle loop tau s^3 + s^2 + kd s + kp is unstable with this actuator lag; "
                "raise kd or lower kp"
            )

    def standstill_for(self, target_gap_m: float, target_speed_mps: float) -> float:
        """Standstill distance r (m): the configured one, or ``d* - h v*``."""
        if self.standstill_m is not None:
            return float(self.standstill_m)
        return float(target_gap_m - self.time_gap_s * target_speed_mps)


@dataclass(frozen=True)
class ACCConfig(PloegConfig):
    """Ploeg's law without V2V feedforward (``acc``); ``feedforward`` must stay False."""

    feedforward: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.feedforward:
            raise ConfigError("acc has no V2V feedforward; use the cacc controller for it")


class CACCController(Controller):
    """``cacc``: Ploeg's constant time-gap law for every follower, batched over episodes, the
    predecessor's commanded acceleration as feedforward over V2V (``acc``: without it).

    Parameters
    ----------
    **options
        Fields of the config dataclass (strings are coerced, see
        :func:`infra.naming.build_config`).
    """

    name = "cacc"
    family = "linear"
    batch_invariant = True
    config_cls: type[PloegConfig] = PloegConfig
    config: PloegConfig

    def __init__(self, **options: object) -> None:
        super().__init__(**options)
        self._channel: V2VChannel | None = None
        self._alpha: float | np.ndarray = 0.0
        self._standstill_m: float | np.ndarray = 0.0
        self._command: np.ndarray = np.zeros((0, 0))
        self._received: np.ndarray = np.zeros((0, 0))

    @property
    def standstill_m(self) -> float | np.ndarray:
        """Standstill distance r used in the current batch (m), known after :meth:`reset`
        (``(N,)`` per vehicle with ``time_gap_rule=xiao`` on a string of vehicle classes)."""
        return self._standstill_m

    def spacing_policy(self, target_gap_m: float, target_speed_mps: float) -> SpacingPolicy:
        """Ploeg's constant time-gap policy ``r + h v`` (``r`` from :meth:`PloegConfig.standstill_for`)."""
        cfg = self.config
        return SpacingPolicy(cfg.standstill_for(target_gap_m, target_speed_mps), cfg.time_gap_s)

    def preflight(self, scenario: Scenario, n_vehicles: int, params: PlatoonParams | None = None
                  ) -> None:
        """The loop must be stable with the run's actuator lag (each vehicle's own on a string of
        vehicle classes)."""
        if params is not None:
            self.config.check_lag(params.lag_s)
            vehicles = scenario.vehicle_arrays(n_vehicles, params)
            if vehicles is not None:
                for lag in sorted(set(vehicles.lag_s.tolist())):
                    self.config.check_lag(lag)

    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """The command applied over the step (1 float to the follower behind), with feedforward."""
        return (Message("cacc_u", 1, "predecessor"),) if self.config.feedforward else ()

    def reset(self, ctx: EpisodeContext) -> None:
        cfg = self.config
        cfg.check_lag(ctx.params.lag_s)
        self.params = ctx.params
        self._standstill_m = cfg.standstill_for(ctx.target_gap_m, ctx.target_speed_mps)
        h = cfg.time_gap_s
        self._alpha = math.exp(-ctx.params.dt_s / h) if h > 0 else 0.0
        b, n = ctx.batch_size, ctx.n_vehicles
        self._command = np.zeros((b, n))
        self._received = np.zeros((b, n))
        self._channel = ctx.channel("cacc_u") if cfg.feedforward else None
        #: per-vehicle time gaps, standstill distances and bounds of a string of vehicle classes
        #: (None: the homogeneous platoon, whose scalars above are used)
        self._vehicles = ctx.scenario.vehicle_arrays(n, ctx.params)
        self._h: float | np.ndarray = h
        self._bounds: tuple[float | np.ndarray, float | np.ndarray] = (
            ctx.params.accel_min_mps2, ctx.params.accel_max_mps2)
        if self._vehicles is not None:
            for lag in sorted(set(self._vehicles.lag_s.tolist())):
                cfg.check_lag(lag)
            hv = cfg.time_gaps_s(self._vehicles.lag_s, ctx.channel_config.delay_s)
            self._h = hv
            self._alpha = np.where(hv > 0, np.exp(-ctx.params.dt_s / np.where(hv > 0, hv, 1.0)),
                                   0.0)
            if cfg.time_gap_rule == "xiao":
                self._standstill_m = ctx.target_gap_m - hv * ctx.target_speed_mps
            self._bounds = (self._vehicles.accel_min_mps2, self._vehicles.accel_max_mps2)

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        cfg = self.config
        h = self._h
        v = state.speed_mps
        # w = kp e + kd de/dt (+ received feedforward)
        w = state.gap_m - self._standstill_m - h * v
        w *= cfg.kp
        edot = state.pred_speed_mps - v
        edot -= h * state.realised_accel_mps2
        w += cfg.kd * edot
        if self._channel is not None:
            w += self._received
        c = self._command
        c *= self._alpha
        c += (1.0 - self._alpha) * w
        np.clip(c, *self._bounds, out=c)
        if self._channel is not None:
            payload = np.empty((c.shape[0], c.shape[1] + 1))
            payload[:, 0] = state.leader_accel_now_mps2
            payload[:, 1:] = c
            self._received = self._channel.transmit(payload)[:, :, 0].copy()
        return c.copy()


class ACCController(CACCController):
    """``acc``: the same constant time-gap law with the feedforward off and no V2V."""

    name = "acc"
    config_cls = ACCConfig
