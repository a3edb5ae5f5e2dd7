"""A safety filter for any controller: ``safe:<controller>`` (worst-case braking envelope).

``safe:cacc``, ``safe:mpc-qp``, ``safe:bdc:scenario=catchup-v1``: the wrapped controller acts as
it would alone (its options, its V2V messages, its observations), and every follower's
acceleration command then passes through the same filter before it reaches the actuator, whether
a control law, an optimiser or a learned policy computed it. The filter lowers a command only
where it would leave the collision-free envelope below, and then only as much as needed; a
command inside the envelope is returned unchanged, to the last bit. How often and how much it
intervened is kept per episode (:meth:`SafetyFilter.intervention_totals`) and reported in
``runs.csv`` (``safety_interventions``, ``safety_correction_mps2``). The derivation, in more
words and with a worked example: ``docs/safety-filter.md``.

What the filter senses
----------------------
Per follower, what its own sensors give: the gap ``d`` to its predecessor (m), its own speed
``v``, its predecessor's speed ``v_p`` (m/s; radar range rate), and its own realised
acceleration ``a`` (m/s^2, the actuator state of the env's first-order lag). Nothing over V2V,
nothing of the leader's plan. Bounds and step come from :class:`envs.params.PlatoonParams`:
``dt``, ``u_min = accel_min_mps2 < 0``, ``u_max = accel_max_mps2``, the lag gain
``g = 1 - exp(-dt / tau)`` (1 without lag), ``q = 1 - g``.

The envelope (a worst-case-braking rule on the env's discrete dynamics)
----------------------------------------------------------------------
Assumption: a predecessor never slows by more than ``beta_p = b_p dt`` per step, with ``b_p`` =
``pred_brake_mps2`` (default ``-u_min`` = 2.5 m/s^2: every simulated follower satisfies it,
because its realised acceleration stays in ``[u_min, u_max]``; the published leaders brake at
2.5 m/s^2 at most). The follower's own full braking is ``b = -u_min`` (``beta = b dt``), and
``b_p >= b`` is required.

*Braking distance.* A vehicle at speed ``w`` whose speed drops by ``beta`` per step, clipped at
0, covers with the env's trapezoidal rule ``gap += dt/2 (v_p + v_p' - v - v')``::

    D(w; beta) = dt ((m + 1) w - beta m (m + 1) / 2 - w / 2),   m = floor(w / beta)

(exact; convex and piecewise linear in ``w``, ``D(m beta) = dt beta m^2 / 2``, and ``w^2 / 2b``
as ``dt -> 0``). With lag, the follower's full-braking plan (command ``u_min`` from the next step
on, realised ``a_k = u_min + (a_1 - u_min) q^(k-1)``) is slower to bite; summing the lag's
deficit bounds its speeds by those of an undelayed braking from the *effective speed*::

    V(v, a) = v + (a - u_min) dt q / g          (V = v without lag)

so the follower stops within ``D(V; beta)`` (exact without lag).

*Safe set.* With ``h_1(x) = d - d_min`` and
``h_2(x) = d + D(v_p; beta_p) - D(V(v, a); beta) - d_min``, the set ``S = {h_1 >= 0, h_2 >= 0}``
holds the states from which the follower, braking fully, stops at least ``d_min`` behind a
predecessor that brakes as hard as it can from now on. Along that plan the gap first grows, then
shrinks (the speed difference ``v_p - v`` only falls while both move, because the follower brakes
no harder than ``b_p``), so its minimum is at the start or at the end: the gap stays ``>= d_min``
at every step, and a predecessor that brakes less only widens it. ``S`` is invariant: from a
state in ``S``, the command ``u_min`` keeps the next state in ``S`` whatever the predecessor does
within its bound (the plan from the next state is the tail of this one; ``D`` grows with the
speed). ``d_min = min_gap_m`` (default 2 m) must be at least the env's collision gap
``gap_min_m`` (1 m), so a platoon that starts in ``S`` never collides.

*The filter (the one-step condition).* For a command ``u``, the next state under the
predecessor's worst step is ``a_1 = a + (clip(u) - a) g``, ``v_1 = clip(v + a_1 dt, 0, v_max)``,
``v_p1 = max(v_p - beta_p, 0)``, ``d_1 = d + dt/2 (v_p + v_p1 - v - v_1)``; the margin
``h(u) = min(h_1, h_2)`` of that state falls as ``u`` grows. If ``h(clip(u_nom)) >= 0`` the
command is kept as given. Otherwise the filter applies the largest ``u`` with ``h(u) >= 0``,
found in closed form: with ``s = v_1`` and ``c = q (v - beta)``, ``V_1 = (s - c) / g``, and
``h_2 >= 0`` reads ``G(V_1) = dt/2 (g V_1 + c) + D(V_1; beta) <= R`` with
``R = d + dt/2 (v_p + v_p1 - v) + D(v_p1; beta_p) - d_min``; ``G`` is piecewise linear, its
piece is ``m = floor((-g + sqrt(g^2 + 4 (2 R / dt - c) / beta)) / 2)`` (from
``G(m beta) <= R``), and inverting that piece gives ``s``; ``h_1 >= 0`` gives
``s <= 2 (R - D(v_p1; beta_p)) / dt``. A follower that must stop within the step (``s < 0``)
takes the largest ``a_1`` with ``D(V_1; beta) <= R``. The answer is checked by evaluating
``h`` at it; where the check fails (rounding, the ``v_max`` clip) the filter brakes fully,
``u_min``, which the invariance makes safe. So, with ``h >= 0`` at the start, ``h >= 0`` at
every step (``tests/test_controllers/test_safety_filter.py`` checks it in closed loop, with and without lag).

Parameters (options, written with a ``safe_`` prefix: ``safe:cacc:safe_min_gap_m=3``)
--------------------------------------------------------------------------------------
``min_gap_m`` (2.0 m, at most 100): ``d_min``, the gap kept after a worst-case stop;
``pred_brake_mps2`` (None: ``-accel_min_mps2``; at most 10 m/s^2): ``b_p``, the hardest braking
assumed of a predecessor. Any other option is the wrapped controller's.

What it does not do: it does not change what the wrapped controller sends over V2V (``cacc``
still broadcasts its own, unfiltered command), and a leader that brakes harder than ``b_p``
(a real OpenACC record can) is outside its guarantee for follower 1.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.base import Controller, EpisodeContext, Message, SpacingPolicy
from envs.params import PlatoonParams
from envs.platoon import PlatoonState
from envs.scenarios import Scenario
from infra.errors import ConfigError

#: Prefix of the filter's own options among the wrapped controller's (``safe_min_gap_m``).
OPTION_PREFIX = "safe_"
#: Slack (m) allowed when the filter checks its own answer (rounding of the closed form).
CHECK_TOL_M = 1e-9
#: Largest ``min_gap_m`` (m): a spacing kept after a stop, far beyond any platoon's.
MAX_MIN_GAP_M = 100.0
#: Hardest ``pred_brake_mps2`` (m/s^2): about 1 g, more than tyres on a road can give.
MAX_PRED_BRAKE_MPS2 = 10.0


@dataclass(frozen=True)
class SafetyFilterConfig:
    """Parameters of the worst-case-braking envelope.

    Attributes
    ----------
    min_gap_m : float
        ``d_min``: the gap kept after both vehicles have stopped in the worst case (m); at
        least the env's collision gap ``gap_min_m`` (checked when the run's params are known).
    pred_brake_mps2 : float or None
        ``b_p``: the hardest braking assumed of a predecessor (m/s^2, > 0); None: the env's
        ``-accel_min_mps2``. Must be at least ``-accel_min_mps2``.
    """

    min_gap_m: float = 2.0
    pred_brake_mps2: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_gap_m) and 0 < self.min_gap_m <= MAX_MIN_GAP_M):
            raise ConfigError(f"safe_min_gap_m must be a positive number of metres, at most "
                              f"{MAX_MIN_GAP_M:g}, got {self.min_gap_m!r}")
        b = self.pred_brake_mps2
        if b is not None and not (math.isfinite(b) and 0 < b <= MAX_PRED_BRAKE_MPS2):
            raise ConfigError(f"safe_pred_brake_mps2 must be a positive deceleration in m/s^2, "
                              f"at most {MAX_PRED_BRAKE_MPS2:g} (about 1 g), got {b!r}")

    def check(self, params: PlatoonParams) -> None:
        """Refuse parameters that void the guarantee with the run's ``params``."""
        if self.min_gap_m < params.gap_min_m:
            raise ConfigError(
                f"safe_min_gap_m = {self.min_gap_m:g} m is below the collision gap "
                f"{params.gap_min_m:g} m; the filter would allow collisions")
        if self.brake_mps2(params) < -params.accel_min_mps2:
            raise ConfigError(
                f"safe_pred_brake_mps2 = {self.pred_brake_mps2:g} m/s^2 is below the follower's "
                f"own full braking {-params.accel_min_mps2:g} m/s^2: a predecessor can brake "
                "that hard, so the envelope would not hold")

    def brake_mps2(self, params: PlatoonParams) -> float:
        """``b_p`` for ``params`` (m/s^2)."""
        return -params.accel_min_mps2 if self.pred_brake_mps2 is None else self.pred_brake_mps2


# ------------------------------------------------------------------ the envelope, pure numpy


def braking_distance_m(speed_mps: np.ndarray, step_mps: float, dt_s: float) -> np.ndarray:
    """Distance ``D(w; beta)`` (m) covered by a vehicle at speed ``w`` whose speed drops by
    ``beta = step_mps`` each step, clipped at 0, under the env's trapezoidal gap update.

    Parameters
    ----------
    speed_mps : array
        Speeds ``w`` (m/s); negative values count as 0.
    step_mps : float
        Speed lost per step ``beta = b dt`` (m/s), > 0.
    dt_s : float
        Step (s).
    """
    w = np.maximum(speed_mps, 0.0)
    m = np.floor(w / step_mps)
    return dt_s * ((m + 1.0) * w - step_mps * m * (m + 1.0) / 2.0 - w / 2.0)


def _inverse_braking_distance_mps(dist_m: np.ndarray, step_mps: float, dt_s: float) -> np.ndarray:
    """The largest speed ``w >= 0`` with ``D(w; beta) <= dist_m`` (``dist_m >= 0``)."""
    r = np.maximum(dist_m, 0.0)
    m = np.floor(np.sqrt(2.0 * r / (dt_s * step_mps)))
    return (r / dt_s + step_mps * m * (m + 1.0) / 2.0) / (m + 0.5)


def effective_speed_mps(speed_mps: np.ndarray, realised_accel_mps2: np.ndarray,
                        params: PlatoonParams) -> np.ndarray:
    """``V(v, a) = v + (a - u_min) dt q / g``: the speed whose undelayed full braking bounds
    the follower's braking through the actuator lag (``V = v`` without lag)."""
    g = params.lag_gain
    if g == 1.0:
        return np.asarray(speed_mps, dtype=np.float64)
    return speed_mps + (realised_accel_mps2 - params.accel_min_mps2) * (params.dt_s * (1 - g) / g)


def barrier_m(gap_m: np.ndarray, speed_mps: np.ndarray, pred_speed_mps: np.ndarray,
              realised_accel_mps2: np.ndarray, params: PlatoonParams,
              config: SafetyFilterConfig = SafetyFilterConfig()) -> np.ndarray:
    """The envelope's margin ``h(x) = min(h_1, h_2)`` (m) of the current state, ``(B, N)``:
    ``>= 0`` inside the safe set (exact without lag, a lower bound of the exact one with lag).

    Parameters
    ----------
    gap_m, speed_mps, pred_speed_mps, realised_accel_mps2 : (B, N)
        What each follower senses: gap (m), own and predecessor's speed (m/s), own realised
        acceleration (m/s^2).
    params : PlatoonParams
    config : SafetyFilterConfig
    """
    dt = params.dt_s
    stop_pred = braking_distance_m(pred_speed_mps, config.brake_mps2(params) * dt, dt)
    stop_own = braking_distance_m(effective_speed_mps(speed_mps, realised_accel_mps2, params),
                                  -params.accel_min_mps2 * dt, dt)
    h1 = gap_m - config.min_gap_m
    return np.minimum(h1, h1 + stop_pred - stop_own)


def next_margin_m(command_mps2: np.ndarray, gap_m: np.ndarray, speed_mps: np.ndarray,
                  pred_speed_mps: np.ndarray, realised_accel_mps2: np.ndarray,
                  params: PlatoonParams, config: SafetyFilterConfig = SafetyFilterConfig()
                  ) -> np.ndarray:
    """``h(u)``: the margin of the next state (m) if each follower applies ``command_mps2``
    (clipped to the bounds, through the lag) and its predecessor brakes as hard as assumed."""
    dt, g = params.dt_s, params.lag_gain
    u = np.clip(command_mps2, params.accel_min_mps2, params.accel_max_mps2)
    a1 = u if g == 1.0 else realised_accel_mps2 + (u - realised_accel_mps2) * g
    v1 = np.clip(speed_mps + a1 * dt, 0.0, params.speed_max_mps)
    vp1 = np.maximum(pred_speed_mps - config.brake_mps2(params) * dt, 0.0)
    d1 = gap_m + dt / 2.0 * (pred_speed_mps + vp1 - speed_mps - v1)
    return barrier_m(d1, v1, vp1, a1, params, config)


def max_safe_command_mps2(gap_m: np.ndarray, speed_mps: np.ndarray, pred_speed_mps: np.ndarray,
                          realised_accel_mps2: np.ndarray, params: PlatoonParams,
                          config: SafetyFilterConfig = SafetyFilterConfig()) -> np.ndarray:
    """The largest command ``u*`` (m/s^2) with ``next_margin_m(u*) >= 0``, in closed form (may
    lie outside the bounds: above ``u_max`` nothing binds, below ``u_min`` nothing is safe).
    See the module docstring for the derivation."""
    dt, g = params.dt_s, params.lag_gain
    q = 1.0 - g
    beta = -params.accel_min_mps2 * dt
    beta_p = config.brake_mps2(params) * dt
    d, v, vp, a = gap_m, speed_mps, pred_speed_mps, realised_accel_mps2
    vp1 = np.maximum(vp - beta_p, 0.0)
    r1 = d + dt / 2.0 * (vp + vp1 - v) - config.min_gap_m  # h_1 >= 0:  dt/2 s <= r1
    r = r1 + braking_distance_m(vp1, beta_p, dt)            # h_2 >= 0:  G(V_1) <= r
    c = q * (v - beta)
    k = np.maximum(2.0 * r / dt - c, 0.0)
    m = np.maximum(np.floor((-g + np.sqrt(g * g + 4.0 * k / beta)) / 2.0), 0.0)
    v_eff = (r / dt + beta * m * (m + 1.0) / 2.0 - c / 2.0) / (m + (1.0 + g) / 2.0)
    s = np.minimum(g * v_eff + c, 2.0 * r1 / dt)
    a1 = (s - v) / dt
    # must stop within the step (s < 0): v_1 = 0 and V_1 = (a_1 - u_min) dt q / g
    stopping = s < 0
    if np.any(stopping):
        if q > 0:
            v_stop = _inverse_braking_distance_mps(r, beta, dt)
            a_stop = np.minimum(params.accel_min_mps2 + v_stop * g / (q * dt), -v / dt)
        else:
            a_stop = -v / dt
        a_stop = np.where((r < 0) | (r1 < 0), -np.inf, a_stop)
        a1 = np.where(stopping, a_stop, a1)
    return a1 if g == 1.0 else a + (a1 - a) / g


def filter_commands(command_mps2: np.ndarray, gap_m: np.ndarray, speed_mps: np.ndarray,
                    pred_speed_mps: np.ndarray, realised_accel_mps2: np.ndarray,
                    params: PlatoonParams, config: SafetyFilterConfig = SafetyFilterConfig()
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correct the commands that would leave the envelope.

    Parameters
    ----------
    command_mps2 : (B, N)
        The wrapped controller's commands (m/s^2), as it returned them.
    gap_m, speed_mps, pred_speed_mps, realised_accel_mps2 : (B, N)
        What each follower senses (see :func:`barrier_m`).
    params, config
        The run's physics and the filter's parameters.

    Returns
    -------
    command_mps2 : (B, N)
        The filtered commands: equal to the given ones (to the last bit) where they are safe,
        the largest safe command otherwise (``u_min`` where none is).
    changed : (B, N) bool
        Where the command was lowered (what the actuator gets differs).
    correction_mps2 : (B, N)
        ``clip(given) - clip(filtered) >= 0`` (m/s^2): how much the applied command was lowered.
    """
    given = np.asarray(command_mps2, dtype=np.float64)
    lo, hi = params.accel_min_mps2, params.accel_max_mps2
    applied = np.clip(given, lo, hi)
    margin = next_margin_m(applied, gap_m, speed_mps, pred_speed_mps, realised_accel_mps2,
                           params, config)
    unsafe = (margin < 0) & (applied > lo)
    if not np.any(unsafe):
        return given.copy(), np.zeros(given.shape, dtype=bool), np.zeros(given.shape)
    best = np.clip(max_safe_command_mps2(gap_m, speed_mps, pred_speed_mps, realised_accel_mps2,
                                         params, config), lo, hi)
    ok = next_margin_m(best, gap_m, speed_mps, pred_speed_mps, realised_accel_mps2,
                       params, config) >= -CHECK_TOL_M
    best = np.where(ok, best, lo)
    changed = unsafe & (best < applied)
    out = np.where(changed, best, given)
    return out, changed, np.where(changed, applied - best, 0.0)


# ------------------------------------------------------------------ the controller wrapper


def _split_options(owner: str, options: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The filter's own options (``safe_*``, prefix removed) and the wrapped controller's."""
    fields = {f"{OPTION_PREFIX}{k}" for k in SafetyFilterConfig.__dataclass_fields__}
    own: dict[str, Any] = {}
    inner: dict[str, Any] = {}
    for key, value in options.items():
        if key.startswith(OPTION_PREFIX):
            if key not in fields:
                raise ConfigError(f"{owner} has no option {key!r}; the filter's options are: "
                                  f"{', '.join(sorted(fields))}")
            own[key[len(OPTION_PREFIX):]] = value
        else:
            inner[key] = value
    return own, inner


class SafetyFilter(Controller):
    """A registered controller whose commands pass the worst-case-braking filter.

    Parameters
    ----------
    inner : str
        Registered name of the wrapped controller (not itself ``safe:...``, not a record).
    **options
        ``safe_min_gap_m``, ``safe_pred_brake_mps2`` (:class:`SafetyFilterConfig`); every other
        option goes to the wrapped controller.
    """

    #: The filter's own options: :class:`SafetyFilterConfig`'s fields with this prefix (the
    #: registry reads both from the class, without importing this module by name).
    filter_config_cls = SafetyFilterConfig
    option_prefix = OPTION_PREFIX

    def __init__(self, inner: str, **options: Any) -> None:
        super().__init__()
        from controllers.registry import make_controller, resolve
        from infra.naming import build_config

        spec = resolve(f"safe:{inner}")  # refuses nesting, unknown names and records
        own, inner_options = _split_options(spec.name, options)
        self.config: SafetyFilterConfig = build_config(SafetyFilterConfig, own, spec.name)
        self.inner: Controller = make_controller(inner, **inner_options)
        self.name = spec.name
        for trait in ("family", "deterministic", "needs_observation", "batch_invariant",
                      "needs_leader"):
            setattr(self, trait, getattr(self.inner, trait))
        # its intervention counts are over every seat: not yet split between human and
        # automated ones, so it stays on strings of automated vehicles
        self.drives_mixed = False
        defaults = SafetyFilterConfig()
        self.options = {**self.inner.options, **{
            f"{OPTION_PREFIX}{k}": getattr(self.config, k)
            for k in SafetyFilterConfig.__dataclass_fields__
            if getattr(self.config, k) != getattr(defaults, k)}}
        self.interventions = np.zeros(0, dtype=np.int64)
        self.correction_sum_mps2 = np.zeros(0)
        self.params = PlatoonParams()

    @staticmethod
    def batch_invariant_probe(inner: str, **_: Any) -> bool:
        """Batch-invariant where the wrapped controller is (the filter is elementwise)."""
        from controllers.registry import batch_invariant

        return batch_invariant(inner)

    @staticmethod
    def options_of(inner: str) -> dict[str, Any]:
        """The options of ``safe:<inner>`` with their defaults: the wrapped controller's, then
        the filter's (``safe_*``)."""
        from controllers.registry import controller_options

        defaults = SafetyFilterConfig()
        return {**controller_options(inner), **{
            f"{OPTION_PREFIX}{k}": getattr(defaults, k)
            for k in SafetyFilterConfig.__dataclass_fields__}}

    @property
    def policy_sha256(self) -> str:
        """The wrapped controller's (the filter learns nothing)."""
        return self.inner.policy_sha256

    def preflight(self, scenario: Scenario, n_vehicles: int, params: PlatoonParams | None = None
                  ) -> None:
        """The wrapped controller's checks, then the filter's parameters against ``params``."""
        self.inner.preflight(scenario, n_vehicles, params)
        self.config.check(params or PlatoonParams())

    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """The wrapped controller's messages (the filter sends nothing)."""
        return self.inner.messages(ctx)

    def spacing_policy(self, target_gap_m: float, target_speed_mps: float
                       ) -> SpacingPolicy | None:
        """The wrapped controller's (the filter aims at no gap of its own)."""
        return self.inner.spacing_policy(target_gap_m, target_speed_mps)

    def reset(self, ctx: EpisodeContext) -> None:
        self.config.check(ctx.params)
        self.inner.reset(ctx)
        self.params = ctx.params
        #: a string of vehicle classes: per class, its physics (its lag and bounds), the filter's
        #: options with the predecessor's assumed braking of the run (no class brakes harder
        #: than the run's bound) and its seats; None: the homogeneous platoon
        self._groups: list[tuple[PlatoonParams, SafetyFilterConfig, np.ndarray]] | None = None
        groups = ctx.class_groups()
        if groups is not None:
            cfg = dataclasses.replace(self.config, pred_brake_mps2=self.config.brake_mps2(
                ctx.params))
            self._groups = [(p_i, cfg, seats) for p_i, seats in groups]
        self.interventions = np.zeros(ctx.batch_size, dtype=np.int64)
        self.correction_sum_mps2 = np.zeros(ctx.batch_size)

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        given = self.inner.act(state, observation)
        self.solver_failures = int(getattr(self.inner, "solver_failures", 0))
        if self._groups is None:
            out, changed, correction = filter_commands(
                given, state.gap_m, state.speed_mps, state.pred_speed_mps,
                state.realised_accel_mps2, self.params, self.config)
        else:  # each class's seats by its own lag and bounds
            out = np.empty_like(given, dtype=np.float64)
            changed = np.zeros(given.shape, dtype=bool)
            correction = np.zeros(given.shape)
            pred = state.pred_speed_mps
            for p_i, cfg, cols in self._groups:
                o, c, k = filter_commands(
                    given[:, cols], state.gap_m[:, cols], state.speed_mps[:, cols], pred[:, cols],
                    state.realised_accel_mps2[:, cols], p_i, cfg)
                out[:, cols], changed[:, cols], correction[:, cols] = o, c, k
        running = ~state.done  # an ended episode is frozen: its commands are not applied
        if np.any(changed & running[:, None]):
            self.interventions += np.where(running, changed.sum(axis=1), 0)
            self.correction_sum_mps2 += np.where(
                running, np.ascontiguousarray(correction).sum(axis=1), 0.0)
        return out

    def intervention_totals(self) -> tuple[np.ndarray, np.ndarray]:
        """Per episode since the reset, ``(B,)`` each: follower-steps whose command the filter
        lowered, and the sum of the corrections (m/s^2)."""
        return self.interventions.copy(), self.correction_sum_mps2.copy()
