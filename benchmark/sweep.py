"""The measured frequency sweep: every controller's string stability, the same way for all.

A sweep drives the leader with a sinusoid at each frequency of a grid (the ``sine-v1`` leader
profile, all frequencies in one batched closed loop through :func:`benchmark.rollout.rollout_batch`),
drops the transient and fits a sinusoid at the driving frequency to every vehicle's
acceleration (least squares, :func:`fit_sinusoid`): the amplitude ratio of consecutive
followers is the measured ``|Gamma(j w)|``, for any controller (linear laws, MPC, learned
policies) through the one controller interface.

- :func:`measure_gains` is the measurement itself (any grid, amplitudes and lengths);
  :func:`analysis.stability.empirical_gain` (``cacc-bench stability --empirical``) and the
  standard sweep both call it.
- :func:`sweep_peak` is the **standard sweep** every leaderboard row carries: the grid
  :data:`SWEEP_OMEGAS_RAD_S`, the leader's acceleration amplitude
  :data:`SWEEP_LEADER_ACCEL_MPS2`, :data:`SWEEP_TRANSIENT_S` and :data:`SWEEP_WINDOW_S`,
  :data:`SWEEP_REPLICAS` episodes per frequency for a stochastic controller, at the row's N,
  V2V channel and actuator lag. A configuration is string stable when the peak is at most
  ``1 + SWEEP_TOL`` (:attr:`SweepResult.string_stable`).
- :class:`SweepCache` keeps the results of a results folder in ``string_sweeps.json``
  (:data:`CACHE_NAME`), keyed by the configuration (label, N, channel, lag, the policy's hash
  and :data:`SWEEP_VERSION`), written atomically and checked when read.
- :func:`row_sweeps` measures (or reads) the sweep of every leaderboard row of a store's
  records: the export calls it when it builds the leaderboard.

Controllers that adapt to the scenario they run on act in the sweep as they did on the row's
scenario (:func:`as_on_scenario`): a learned policy with the checkpoint of that scenario, ``duty``
with the period it chose there.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmark.string_gain import STRING_GAIN_TOL, is_string_stable
from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.scenarios import EpisodeBatch, Scenario, make_scenario, scenario_spec
from infra.errors import CaccBenchError, ConfigError
from infra.interrupt import raise_if_interrupted
from infra.limits import check_nonnegative

# ------------------------------------------------------------------------- the standard sweep

#: Driving frequencies of the standard sweep (Hz): octaves from 0.05 Hz (a 20 s period) to
#: 0.4 Hz, ``sine-v1``'s default 0.2 Hz among them. They hold the peaks of ``cacc`` with a
#: 0.2 s delay (the analytic peak 1.063 at 0.665 rad/s; 1.062 at 0.628 rad/s, on the grid) and
#: of ``acc`` (1.211 at 0.328 rad/s; 1.210 at 0.314 rad/s); below the grid every law that holds
#: its time gap tends to the gain 1 (``Gamma(0) = 1``). Four frequencies keep the sweep cheap:
#: it costs the closed loops of 4 episodes of 60 s (16 for a sampled policy), one batch.
SWEEP_FREQUENCIES_HZ: tuple[float, ...] = (0.05, 0.1, 0.2, 0.4)
#: The same grid in rad/s (0.314 to 2.51).
SWEEP_OMEGAS_RAD_S: tuple[float, ...] = tuple(2.0 * math.pi * f for f in SWEEP_FREQUENCIES_HZ)
#: Amplitude of the leader's acceleration at every frequency (m/s^2): its speed amplitude is
#: ``SWEEP_LEADER_ACCEL_MPS2 / w`` (1.6 m/s at the lowest frequency, 0.2 m/s at the highest),
#: so every frequency excites the platoon equally in the quantity the gain is a ratio of.
SWEEP_LEADER_ACCEL_MPS2 = 0.5
#: Start of each episode left out of the fit (s). What is left of the start's transient then
#: moves the measured gain of ``acc`` at N = 8, the string-unstable law whose transient grows
#: down the platoon, by at most 2.2e-3 of the analytic value on the grid (``cacc``: 2.4e-7).
SWEEP_TRANSIENT_S = 30.0
#: Fit window after the transient (s): 1.5 periods of the lowest frequency. An episode lasts
#: ``SWEEP_TRANSIENT_S + SWEEP_WINDOW_S`` = 60 s, the length of a ``sine-v1`` episode.
SWEEP_WINDOW_S = 30.0
#: A follower pair counts only where the predecessor's fitted amplitude is at least this share
#: of the leader's: once the disturbance has died down to 5 % of the leader's, what is left at
#: the driving frequency is the transient's and the controller's own motion, and a ratio of
#: such remainders says nothing about amplification (``acc`` at 2.5 rad/s, N = 8: 0.18 per
#: vehicle, follower 8 at 6e-6 of the leader). A frequency where no pair counts has gain NaN.
SWEEP_MIN_FRACTION = 0.05
#: Episodes per frequency for a controller that is not deterministic (a sampled policy): the
#: fitted complex amplitudes are averaged over them, which leaves the response to the leader
#: and averages out the sampling noise. A deterministic controller runs one.
SWEEP_REPLICAS = 4
#: Seed of the first episode (episode k of the batch gets ``SWEEP_SEED + 10 k``).
SWEEP_SEED = 2000
#: A configuration is string stable when its peak gain is at most ``1 + SWEEP_TOL``: the one
#: tolerance of the measured string gains (:data:`benchmark.string_gain.STRING_GAIN_TOL`).
SWEEP_TOL = STRING_GAIN_TOL
#: Version of the standard sweep's definition (grid, amplitude, lengths, replicas, fit): part
#: of every cache key, so a changed definition never reads an old result.
SWEEP_VERSION = 1
#: The cache file in a results folder, beside the store.
CACHE_NAME = "string_sweeps.json"
#: Fewer configurations to measure than this run in this process, whatever the executor: a
#: pool's start and stop (spawned workers that import the controllers again, torch for a
#: policy) cost more than they save (the 8 sweeps of the default ``run``: 8.4 s here against
#: 13.6 s in a pool of 2, on the 2-core machine beside other jobs).
MIN_POOL_SWEEPS = 16


def fit_sinusoid(x: np.ndarray, omega_rad_s: float, t_s: np.ndarray) -> np.ndarray:
    """Complex amplitude ``c + j s`` of ``x(t) ~ c cos(w t) + s sin(w t) + offset`` (least squares).

    Parameters
    ----------
    x : (T, ...)
        Samples; every trailing column is fitted separately.
    omega_rad_s : float
        The frequency fitted.
    t_s : (T,)
        Sample times.
    """
    basis = np.stack(
        [np.cos(omega_rad_s * t_s), np.sin(omega_rad_s * t_s), np.ones_like(t_s)], axis=1
    )
    flat = np.asarray(x, dtype=np.float64).reshape(len(t_s), -1)
    coef, *_ = np.linalg.lstsq(basis, flat, rcond=None)
    out = coef[0] + 1j * coef[1]
    return out.reshape(np.shape(x)[1:])


@dataclass(frozen=True)
class Measured:
    """What :func:`measure_gains` measured (W frequencies, N followers).

    Attributes
    ----------
    omegas_rad_s : (W,)
        Driving frequencies.
    amplitudes_mps : (W,)
        The leader's speed amplitude at each.
    pair_gain : (W, N)
        Amplitude ratio of follower i's acceleration over its predecessor's at the driving
        frequency; column 0 is follower 1 over the leader. NaN where an episode collided.
    gain : (W,)
        Max over the follower pairs (columns 1..N-1) whose predecessor moves enough
        (``min_fraction``): the measured ``|Gamma(jw)|``; NaN where none does or it collided.
    collided, saturated : (W,) bool
        An episode of the frequency collided; a command reached its bound or a speed 0 or the
        speed bound (the run left the linear regime).
    duration_s : float
        Simulated time of each episode.
    replicas : int
        Episodes per frequency.
    """

    omegas_rad_s: np.ndarray
    amplitudes_mps: np.ndarray
    pair_gain: np.ndarray
    gain: np.ndarray
    collided: np.ndarray
    saturated: np.ndarray
    duration_s: float
    replicas: int


@functools.cache
def _sine_base(scenario_options: tuple[tuple[str, Any], ...] = ()) -> Scenario:
    """``sine-v1`` (with an arrangement's options), built once per process: the sweep derives
    each frequency's episodes from it without parsing a label again."""
    return make_scenario("sine-v1", **dict(scenario_options))


def _sine_episodes(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int, *,
                   table: tuple[tuple[int, float, float], ...], base: Scenario) -> EpisodeBatch:
    """Episodes of the sweep's scenario: the ``sine-v1`` episode of each seed's frequency and
    amplitude (``table`` rows ``(seed, frequency_hz, amplitude_mps)``, checked by
    :func:`measure_gains`), built by ``sine-v1``'s own builder (``base``) at the sweep's
    length."""
    by_seed = {s: (f, a) for s, f, a in table}
    parts = []
    for seed, uk in zip(seeds.tolist(), u.tolist(), strict=True):
        if seed not in by_seed:
            raise ConfigError(f"the frequency sweep has no episode with seed {seed}")
        f_hz, amp = by_seed[seed]
        one = dataclasses.replace(
            base, options={**base.options, "amplitude_mps": amp, "frequency_hz": f_hz},
            n_steps=sc.n_steps)
        parts.append(one.episodes([seed], n, uk))
    return EpisodeBatch(seeds, u, *(np.concatenate([getattr(p, name) for p in parts])
                                    for name in ("gap_m", "speed_mps", "leader_speed_mps")))


def measure_gains(
    controller: Any,
    omegas_rad_s: Sequence[float] | np.ndarray,
    amplitudes_mps: Sequence[float] | np.ndarray | float,
    *,
    n_vehicles: int,
    params: PlatoonParams = PlatoonParams(),
    channel: ChannelConfig = ChannelConfig(),
    transient_s: float = SWEEP_TRANSIENT_S,
    periods: float = 1.0,
    min_window_s: float = SWEEP_WINDOW_S,
    seed: int = SWEEP_SEED,
    replicas: int = 1,
    min_fraction: float = 0.0,
    scenario_options: Mapping[str, Any] | None = None,
) -> Measured:
    """Measure ``|Gamma(jw)|`` of a built controller with sinusoidal leaders, in one batch.

    Episode ``(k, r)`` (frequency k, replica r) follows the ``sine-v1`` leader at
    ``f = w_k / 2 pi`` with speed amplitude ``amplitudes_mps[k]`` and seed
    ``seed + 10 (k replicas + r)``; all run together, as long as the longest needs: after
    ``transient_s``, at least ``max(periods / f, min_window_s)`` remain for the fit.

    Parameters
    ----------
    controller : controllers.base.Controller
        A built controller (``controllers.registry.make_controller``).
    omegas_rad_s : (W,) floats
        Driving frequencies, in (0, pi/dt).
    amplitudes_mps : float or (W,) floats
        The leader's speed amplitude at each frequency (> 0; small enough not to saturate).
    n_vehicles : int
        Followers N (>= 2; the gain is taken over follower pairs).
    params, channel
        Physics (the actuator lag) and the V2V channel of the episodes.
    transient_s, periods, min_window_s : float
        Start left out of the fit; the fit window's length in periods and in seconds.
    seed : int
        Seed of the first episode.
    replicas : int
        Episodes per frequency (>= 1); their fitted complex amplitudes are averaged.
    min_fraction : float
        A follower pair counts in ``gain`` only where its predecessor's amplitude is at least
        this share of the leader's (:data:`SWEEP_MIN_FRACTION` in the standard sweep; 0: every
        pair). ``pair_gain`` holds every pair.
    scenario_options : mapping, optional
        Arrangement options of the ``sine-v1`` episodes (``classes``, ``humans``, ...: the
        head-to-tail measurement of :mod:`analysis.head_to_tail`); none by default.
    """
    from benchmark.rollout import rollout_batch
    from envs.scenarios import check_vehicles

    n = check_vehicles(n_vehicles)
    dt = params.dt_s
    omegas = np.atleast_1d(np.asarray(omegas_rad_s, dtype=np.float64))
    if omegas.size == 0 or np.any(~np.isfinite(omegas)) or np.any(omegas <= 0):
        raise ConfigError("frequencies must be finite and > 0 rad/s")
    if np.any(omegas >= math.pi / dt):
        raise ConfigError(
            f"frequencies must lie below the Nyquist frequency {math.pi / dt:.3g} rad/s")
    amps = np.broadcast_to(np.asarray(amplitudes_mps, dtype=np.float64), omegas.shape).copy()
    for a in amps:
        check_nonnegative(float(a), "amplitude_mps", positive=True)
    check_nonnegative(transient_s, "transient_s")
    check_nonnegative(periods, "periods", positive=True)
    check_nonnegative(min_window_s, "min_window_s", positive=True)
    if isinstance(replicas, bool) or not isinstance(replicas, int) or replicas < 1:
        raise ConfigError(f"replicas must be an integer >= 1, got {replicas!r}")
    if not 0.0 <= check_nonnegative(min_fraction, "min_fraction") < 1.0:
        raise ConfigError(f"min_fraction must lie in [0, 1), got {min_fraction!r}")

    window_s = np.maximum(periods * 2 * np.pi / omegas, min_window_s)
    duration_s = transient_s + float(window_s.max())
    base = _sine_base(tuple(sorted(dict(scenario_options or {}).items())))
    check_sine = scenario_spec("sine-v1").check  # sine-v1's own rule for every episode
    for a, w_rad_s in zip(amps.tolist(), omegas.tolist(), strict=True):
        if check_sine is not None:
            check_sine({**base.options, "amplitude_mps": a, "frequency_hz": w_rad_s / (2 * np.pi)})
    n_steps = max(base.n_steps, int(math.ceil(duration_s / dt)))
    w, r = len(omegas), replicas
    seeds = [seed + 10 * i for i in range(w * r)]
    table = tuple((s, float(omegas[i // r] / (2 * np.pi)), float(amps[i // r]))
                  for i, s in enumerate(seeds))
    sweep_sc = dataclasses.replace(
        base, n_steps=n_steps, label="sine-v1[frequency sweep]",
        _builder=functools.partial(_sine_episodes, table=table, base=base))
    trajs = rollout_batch(controller, sweep_sc, n, seeds, params, channel)
    leader = sweep_sc.episodes(seeds, n).leader_speed_mps  # (B, n_steps + 1)

    a_bound = min(-params.accel_min_mps2, params.accel_max_mps2) - 1e-9
    k0 = int(math.ceil(transient_s / dt))
    t_s = np.arange(n_steps) * dt
    amp_c = np.zeros((w, r, n + 1), dtype=np.complex128)
    collided = np.zeros(w, dtype=bool)
    saturated = np.zeros(w, dtype=bool)
    for i, traj in enumerate(trajs):
        raise_if_interrupted()
        k, j = divmod(i, r)
        accel = np.zeros((n_steps, n + 1))
        accel[:, 0] = np.diff(leader[i]) / dt
        accel[: traj.steps, 1:] = traj.accel_mps2[1:]
        saturated[k] |= bool(
            np.any(np.abs(traj.command_mps2) >= a_bound)
            or np.any((traj.speed_mps[1:] <= 0.0) | (traj.speed_mps[1:] >= params.speed_max_mps)))
        collided[k] |= traj.collided
        amp_c[k, j] = fit_sinusoid(accel[k0:], float(omegas[k]), t_s[k0:])
    amp = np.abs(amp_c.mean(axis=1))  # (W, N+1)
    with np.errstate(divide="ignore", invalid="ignore"):
        pair_gain = amp[:, 1:] / amp[:, :-1]
    pair_gain[collided] = np.nan
    counted = np.where(amp[:, 1:-1] >= min_fraction * amp[:, :1], pair_gain[:, 1:], -np.inf)
    gain = np.max(counted, axis=1)  # N >= 2 (check_vehicles): at least one pair
    return Measured(
        omegas_rad_s=omegas, amplitudes_mps=amps, pair_gain=pair_gain,
        gain=np.where(np.isneginf(gain), np.nan, gain), collided=collided, saturated=saturated,
        duration_s=n_steps * dt, replicas=r,
    )


@dataclass(frozen=True)
class SweepResult:
    """The standard sweep of one controller configuration.

    Attributes
    ----------
    controller : str
        The configuration's label (:func:`controllers.registry.controller_label`), as its runs
        carry it.
    scenario : str
        The scenario id it acted as on (:func:`adapts_to_scenario`; empty when its behaviour
        does not depend on the scenario).
    n_vehicles : int
    comm_delay_s, packet_loss, lag_s : float
        The V2V channel and the actuator lag of the sweep.
    policy_sha256 : str
        The learned policy's hash (empty without learned weights).
    omegas_rad_s : tuple of float
        The grid, :data:`SWEEP_OMEGAS_RAD_S`.
    gains_per_omega : tuple of float
        The measured ``|Gamma(jw)|`` at each (max over the follower pairs that count, see
        :data:`SWEEP_MIN_FRACTION`; NaN where none counts or an episode collided).
    peak_gain : float
        Max over the grid; ``inf`` when an episode collided (the disturbance grew into a
        collision); NaN when no follower pair moved enough to count at any frequency (shown
        as n/a, never string stable).
    omega_at_peak_rad_s : float
        Where the peak is.
    collided, saturated : bool
        Whether an episode collided or left the linear regime (a command at its bound, a speed
        at 0 or at the bound) at any frequency.
    version : int
        :data:`SWEEP_VERSION` of the definition it was measured with.
    """

    controller: str
    scenario: str
    n_vehicles: int
    comm_delay_s: float
    packet_loss: float
    lag_s: float
    policy_sha256: str
    omegas_rad_s: tuple[float, ...]
    gains_per_omega: tuple[float, ...]
    peak_gain: float
    omega_at_peak_rad_s: float
    collided: bool
    saturated: bool
    version: int = SWEEP_VERSION

    @property
    def string_stable(self) -> bool:
        """Whether the peak is at most ``1 + SWEEP_TOL`` (a collision never is)."""
        return is_string_stable(self.peak_gain)

    @property
    def key(self) -> str:
        """The cache key of the configuration (:func:`sweep_key`)."""
        return sweep_key(self.controller, self.scenario, self.n_vehicles, self.comm_delay_s,
                         self.packet_loss, self.lag_s, self.policy_sha256)


def sweep_key(label: str, scenario: str, n_vehicles: int, comm_delay_s: float,
              packet_loss: float, lag_s: float, policy_sha256: str = "") -> str:
    """The cache key of a configuration: sweep version, label, the scenario it acts as on, N,
    channel, lag and policy hash."""
    return (f"v{SWEEP_VERSION}|{label}|{scenario}|n{int(n_vehicles)}|d{float(comm_delay_s)!r}"
            f"|l{float(packet_loss)!r}|tau{float(lag_s)!r}|{policy_sha256}")


def adapts_to_scenario(name: str, options: Mapping[str, Any]) -> bool:
    """Whether controller ``name`` with ``options`` chooses what it does from the scenario it
    runs on: a learned policy without ``scenario`` or ``checkpoint`` (it loads the checkpoint of
    the run's scenario), ``duty`` without ``k`` (the best period on the run's scenario)."""
    from controllers.registry import controller_options

    if name == "duty":
        return options.get("k") is None
    known = controller_options(name)
    return ("scenario" in known and options.get("scenario") is None
            and options.get("checkpoint") is None)


def as_on_scenario(name: str, options: Mapping[str, Any], scenario: Scenario | str | None,
                   n_vehicles: int, params: PlatoonParams = PlatoonParams()) -> dict[str, Any]:
    """The options that make controller ``name`` act in the sweep as it acts on ``scenario``
    (:func:`adapts_to_scenario`): a learned policy gets ``scenario=<the scenario's id>``, the
    checkpoint it loads there; ``duty`` gets the period ``k`` it picks there
    (:func:`controllers.duty.best_k`). Others, or ``scenario`` None: the options as given."""
    opts = dict(options)
    if scenario is None or not adapts_to_scenario(name, opts):
        return opts
    from envs.scenarios import as_scenario

    sc = as_scenario(scenario)
    if name != "duty":
        opts["scenario"] = sc.id
        return opts
    from benchmark.rollout import rollout_batch
    from controllers.duty import DutyConfig, best_k
    from infra.naming import build_config

    cfg = build_config(DutyConfig, opts, "duty")
    opts["k"] = best_k(sc, n_vehicles, cfg.k_max, params, rollout_batch)
    return opts


def _configuration(
    name: str, options: Mapping[str, Any] | None, n_vehicles: int, comm_delay_s: float,
    packet_loss: float, lag_s: float, scenario: Scenario | str | None,
) -> tuple[int, PlatoonParams, ChannelConfig, dict[str, Any], str, str]:
    """Checked settings of a sweep: N, physics, channel, canonical options, label and the
    scenario id it acts as on (empty when it does not adapt to one)."""
    from controllers.registry import canonical_options, controller_label
    from envs.scenarios import as_scenario, check_vehicles
    from infra.limits import check_delay, check_packet_loss, check_whole_steps

    n = check_vehicles(n_vehicles)
    params = PlatoonParams(lag_s=check_nonnegative(lag_s, "lag_s"))
    check_delay(comm_delay_s, "comm_delay_s")
    check_whole_steps(comm_delay_s, "comm_delay_s", params.dt_s)
    check_packet_loss(packet_loss, "packet_loss")
    channel = ChannelConfig(float(comm_delay_s), float(packet_loss), params.dt_s)
    opts = canonical_options(name, dict(options or {}))
    label = controller_label(name, opts)
    pinned = (as_scenario(scenario).id
              if scenario is not None and adapts_to_scenario(name, opts) else "")
    return n, params, channel, opts, label, pinned


def cached_sweep(cache: SweepCache, controller_name: str, options: Mapping[str, Any] | None,
                 *, n_vehicles: int, comm_delay_s: float, packet_loss: float, lag_s: float,
                 scenario: Scenario | str | None, policy_sha256: str) -> SweepResult | None:
    """The cached sweep of a configuration whose policy hash is known (None if not cached),
    without building the controller."""
    n, _, _, _, label, pinned = _configuration(controller_name, options, n_vehicles,
                                               comm_delay_s, packet_loss, lag_s, scenario)
    key = sweep_key(label, pinned, n, comm_delay_s, packet_loss, lag_s, policy_sha256)
    return cache[key] if key in cache else None


def sweep_peak(
    controller_name: str,
    options: Mapping[str, Any] | None = None,
    *,
    n_vehicles: int = 8,
    comm_delay_s: float = 0.0,
    packet_loss: float = 0.0,
    lag_s: float = 0.0,
    scenario: Scenario | str | None = None,
    policy_sha256: str | None = None,
    cache: SweepCache | None = None,
) -> SweepResult:
    """The standard sweep of a controller configuration (measured, or read from ``cache``).

    Parameters
    ----------
    controller_name : str
        Registered controller name (``safe:`` filtered ones too).
    options : mapping, optional
        Its options, as on the command line or typed.
    n_vehicles : int
        Followers N.
    comm_delay_s, packet_loss : float
        The V2V channel (delay in whole steps, loss in [0, 1]).
    lag_s : float
        Actuator lag.
    scenario : Scenario or str, optional
        The scenario the configuration runs on, for the controllers that adapt to it
        (:func:`as_on_scenario`); ignored for the others.
    policy_sha256 : str, optional
        The policy hash the configuration's runs acted with: a cached result is then found
        without loading the controller, and a policy that has changed is refused.
    cache : SweepCache, optional
        Looked up first; a measured result is added to it (the caller saves it).

    Returns
    -------
    SweepResult
        With :attr:`SweepResult.peak_gain` and :attr:`SweepResult.string_stable`.

    Raises
    ------
    ConfigError
        For bad settings, an unknown controller or bad options, a controller that cannot run
        the sweep (a recorded platoon; a policy without its checkpoint), or a policy other than
        ``policy_sha256``.
    """
    from controllers.registry import check_fits, make_controller

    n, params, channel, opts, label, pinned = _configuration(
        controller_name, options, n_vehicles, comm_delay_s, packet_loss, lag_s, scenario)

    def key_of(policy: str) -> str:
        return sweep_key(label, pinned, n, comm_delay_s, packet_loss, lag_s, policy)

    if cache is not None and policy_sha256 is not None and key_of(policy_sha256) in cache:
        return cache[key_of(policy_sha256)]
    ctrl = make_controller(controller_name,
                           **as_on_scenario(controller_name, opts, pinned or None, n, params))
    if getattr(ctrl, "recorded", None) is not None:
        raise ConfigError(f"{label} is a recorded platoon: it has no response to the sweep's "
                          "leader, so no frequency sweep")
    check_fits(ctrl, _sine_base(()), n, params)  # loads a policy: its hash is known
    policy = str(getattr(ctrl, "policy_sha256", ""))
    if policy_sha256 is not None and policy != policy_sha256:
        raise ConfigError(f"{label}: its policy has changed since its runs (policy "
                          f"{policy_sha256[:12]} then, {policy[:12] or 'none'} now)")
    if cache is not None and key_of(policy) in cache:
        return cache[key_of(policy)]
    omegas = np.asarray(SWEEP_OMEGAS_RAD_S)
    deterministic = bool(getattr(ctrl, "deterministic", True))
    m = measure_gains(ctrl, omegas, SWEEP_LEADER_ACCEL_MPS2 / omegas, n_vehicles=n,
                      params=params, channel=channel,  # the standard transient, window, seed
                      replicas=1 if deterministic else SWEEP_REPLICAS,
                      min_fraction=SWEEP_MIN_FRACTION)
    if m.collided.any():
        i = int(np.argmax(m.collided))
        peak = math.inf
    else:
        measured = bool(np.isfinite(m.gain).any())  # else no pair moved enough to count
        i = int(np.nanargmax(m.gain)) if measured else 0
        peak = float(m.gain[i]) if measured else math.nan
    result = SweepResult(
        controller=label, scenario=pinned, n_vehicles=n, comm_delay_s=float(comm_delay_s),
        packet_loss=float(packet_loss), lag_s=float(lag_s), policy_sha256=policy,
        omegas_rad_s=tuple(float(x) for x in omegas),
        gains_per_omega=tuple(float(x) for x in m.gain), peak_gain=peak,
        omega_at_peak_rad_s=float(omegas[i]), collided=bool(m.collided.any()),
        saturated=bool(m.saturated.any()),
    )
    if cache is not None:
        cache[result.key] = result
    return result


# ------------------------------------------------------------------------------------ cache


_FIELDS: dict[str, type | tuple[type, ...]] = {
    "controller": str, "scenario": str, "n_vehicles": int, "comm_delay_s": (int, float),
    "packet_loss": (int, float), "lag_s": (int, float), "policy_sha256": str,
    "omegas_rad_s": list, "gains_per_omega": list, "peak_gain": (int, float, type(None)),
    "omega_at_peak_rad_s": (int, float), "collided": bool, "saturated": bool, "version": int,
}


def _encode(res: SweepResult) -> dict[str, Any]:
    out = dataclasses.asdict(res)
    out["omegas_rad_s"] = list(res.omegas_rad_s)
    out["gains_per_omega"] = [None if math.isnan(g) else g for g in res.gains_per_omega]
    # JSON has neither inf (a collision) nor NaN (no follower pair moved enough to count)
    out["peak_gain"] = None if not math.isfinite(res.peak_gain) else res.peak_gain
    return out


def _decode(entry: Any) -> SweepResult:
    """A cached entry, checked field by field (ValueError saying what is wrong)."""
    if not isinstance(entry, dict) or set(entry) != set(_FIELDS):
        raise ValueError("not an entry with the sweep's fields")
    for name, kind in _FIELDS.items():
        value = entry[name]
        if (isinstance(value, bool) and kind is not bool) or not isinstance(value, kind):
            raise ValueError(f"{name} has the wrong type")
    omegas, gains = entry["omegas_rad_s"], entry["gains_per_omega"]
    if not omegas or len(omegas) != len(gains):
        raise ValueError("frequencies and gains of different lengths")
    for x in (*omegas, *(g for g in gains if g is not None)):
        if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
            raise ValueError("a frequency or gain is not a finite number")
    peak = entry["peak_gain"]
    if entry["omega_at_peak_rad_s"] not in omegas:
        raise ValueError("the frequency of its peak is not one of its frequencies")
    res = SweepResult(
        controller=entry["controller"], scenario=entry["scenario"],
        n_vehicles=entry["n_vehicles"], comm_delay_s=float(entry["comm_delay_s"]),
        packet_loss=float(entry["packet_loss"]), lag_s=float(entry["lag_s"]),
        policy_sha256=entry["policy_sha256"], omegas_rad_s=tuple(float(x) for x in omegas),
        gains_per_omega=tuple(math.nan if g is None else float(g) for g in gains),
        peak_gain=(math.inf if entry["collided"] else math.nan) if peak is None else float(peak),
        omega_at_peak_rad_s=float(entry["omega_at_peak_rad_s"]),
        collided=entry["collided"], saturated=entry["saturated"], version=entry["version"],
    )
    no_gain = all(g is None for g in gains)
    if (peak is None) != (res.collided or no_gain):
        raise ValueError("a peak that disagrees with the collision flag and the gains")
    if peak is not None:  # measured: the largest gain, at the first frequency that has it
        top = max(g for g in gains if g is not None)
        if peak != top or entry["omega_at_peak_rad_s"] != omegas[gains.index(top)]:
            raise ValueError(f"a peak gain of {peak!r} that is not the largest of its gains "
                             f"({top!r}) at its frequency")
    return res


class SweepCache:
    """The standard sweeps of a results folder, in ``<folder>/string_sweeps.json``.

    A mapping from :func:`sweep_key` to :class:`SweepResult`; :meth:`save` writes the file
    atomically when something was added. Reading checks every entry: a damaged file is refused
    (:class:`infra.errors.ConfigError`, one line) and never overwritten. Entries of another
    :data:`SWEEP_VERSION` are kept but never match a key of this one.
    """

    FORMAT = "cacc-bench string sweeps"

    def __init__(self, folder: str | Path) -> None:
        self.path = Path(folder) / CACHE_NAME
        self._entries: dict[str, SweepResult] = {}
        self._dirty = False
        if self.path.is_dir():
            raise ConfigError(f"{self.path} is a folder, so the string-sweep cache cannot be "
                              "written there; move that folder away")
        if self.path.exists():
            self._load()

    def _load(self) -> None:
        from infra.files import damaged, read_json

        what = "the string-sweep cache"
        fix = "remove it: the next `cacc-bench leaderboard` of that folder measures the sweeps again"
        data = read_json(self.path, what, fix)
        if data.get("format") != self.FORMAT or not isinstance(data.get("entries"), list):
            raise damaged(self.path, what, f"not a {self.FORMAT} file", fix)
        for i, raw in enumerate(data["entries"]):
            try:
                res = _decode(raw)
            except ValueError as exc:
                raise damaged(self.path, what, f"entry {i}: {exc}", fix) from None
            self._entries[res.key] = res

    def __contains__(self, key: object) -> bool:
        return key in self._entries

    def __getitem__(self, key: str) -> SweepResult:
        return self._entries[key]

    def __setitem__(self, key: str, value: SweepResult) -> None:
        if key != value.key:
            raise ValueError(f"a sweep of {value.key!r} stored under {key!r}")
        self._entries[key] = value
        self._dirty = True

    def __len__(self) -> int:
        return len(self._entries)

    def values(self) -> list[SweepResult]:
        """Every cached sweep, sorted by key (what ``cacc-bench plot`` draws)."""
        return [self._entries[k] for k in sorted(self._entries)]

    def save(self) -> None:
        """Write the file atomically if an entry was added (entries sorted by key)."""
        if not self._dirty:
            return
        from infra.atomic import write_text

        body = {"format": self.FORMAT,
                "entries": [_encode(self._entries[k]) for k in sorted(self._entries)]}
        write_text(self.path, json.dumps(body, indent=1, sort_keys=True, allow_nan=False) + "\n")
        self._dirty = False


# ----------------------------------------------------------------------------- leaderboard rows

#: A leaderboard setting of one run label: ``(controller, scenario, n_vehicles, comm_delay_s,
#: packet_loss, lag_s)`` as the records hold them.
RowKey = tuple[str, str, int, float, float, float]


def row_key(rec: Mapping[str, Any]) -> RowKey:
    """The setting of a record or a runs.csv row (:data:`RowKey`)."""
    return (str(rec["controller"]), str(rec["scenario"]), int(rec["n_vehicles"]),
            float(rec["comm_delay_s"]), float(rec["packet_loss"]), float(rec["lag_s"]))


def _sweep_job(job: tuple[Any, ...]) -> tuple[Any, SweepResult | str]:
    """One configuration's sweep in a worker: ``(its identity, result)``, or the one-line
    reason it has none (a missing checkpoint, a changed policy, a controller that fails: as a
    failed run is stored with its error, a failed sweep leaves the row without one)."""
    i, name, options, n, delay, loss, lag, scenario, policy = job
    try:
        return i, sweep_peak(name, options, n_vehicles=n, comm_delay_s=delay, packet_loss=loss,
                             lag_s=lag, scenario=scenario, policy_sha256=policy)
    except CaccBenchError as exc:
        return i, str(exc)
    except Exception as exc:  # noqa: BLE001 - a controller that fails: as a run's error, no sweep
        return i, f"the controller failed: {type(exc).__name__}: {exc}"


def row_sweeps(
    records: Iterable[Mapping[str, Any]],
    cache: SweepCache | None = None,
    notes: list[str] | None = None,
    executor: str = "serial",
    workers: int = 1,
    ray_address: str | None = None,
) -> dict[RowKey, SweepResult | None]:
    """The standard sweep of every setting (:data:`RowKey`) of ``records``.

    Found in ``cache`` when it holds the configuration with the policy the runs used, else
    measured (one job per configuration on ``executor``, however many settings share it: a
    controller that adapts to the scenario is measured as it acted on the setting's scenario,
    any other once for all scenarios) and added to it. A setting gets
    None, with a line in ``notes``, when it cannot be swept: a recorded platoon (no line), a
    policy whose checkpoint is gone or is no longer the one its finished runs used.

    Parameters
    ----------
    records : iterable of mappings
        Store records or runs.csv rows (``controller``, ``name`` or ``controller_name``,
        ``options`` as JSON, ``scenario``, the setting, ``status``; ``policy_sha256`` where
        known).
    cache : SweepCache, optional
        Read first, added to (the caller saves it).
    notes : list of str, optional
        Where the reasons go (one line each).
    executor, workers, ray_address
        Where the sweeps run (:func:`benchmark.executors.map_jobs`); in this process when fewer
        than :data:`MIN_POOL_SWEEPS` need measuring.
    """
    from benchmark.executors import map_jobs
    from controllers.registry import resolve, runs_inside_simulator
    from envs.scenarios import as_scenario

    settings: dict[RowKey, tuple[str, dict[str, Any], set[str]]] = {}
    for rec in records:
        key = row_key(rec)
        if key not in settings:
            name = str(rec.get("name") or rec.get("controller_name") or rec["controller"])
            settings[key] = (name, json.loads(str(rec.get("options") or "{}")), set())
        if rec.get("status") == "ok" and "policy_sha256" in rec:
            settings[key][2].add(str(rec["policy_sha256"] or ""))
    out: dict[RowKey, SweepResult | None] = {}
    results: dict[tuple[Any, ...], SweepResult | str] = {}  # one per configuration
    ident_of: dict[RowKey, tuple[Any, ...]] = {}
    jobs: dict[tuple[Any, ...], tuple[Any, ...]] = {}
    for key in sorted(settings):
        name, options, policies = settings[key]
        label, scenario, n, delay, loss, lag = key
        out[key] = None
        if resolve(name).family == "data":  # a recorded platoon: nothing to drive
            continue
        policy = next(iter(policies)) if len(policies) == 1 else None
        try:
            if runs_inside_simulator(resolve(name)):  # sumo:acc, plexe:ploeg: none to measure
                raise ConfigError(f"{name} is a model that runs inside SUMO only, and the "
                                  "standard frequency sweep runs in the built-in simulator, so "
                                  "it has none (its runs' string_gain is measured in SUMO)")
            pinned = as_scenario(scenario).id if adapts_to_scenario(name, options) else ""
        except CaccBenchError as exc:  # also a scenario or controller this version does not know
            ident_of[key] = (key,)
            results[(key,)] = str(exc)
            continue
        ident: tuple[Any, ...] = (label, pinned, n, delay, loss, lag, policy)
        ident_of[key] = ident
        if ident in results or ident in jobs:
            continue
        if cache is not None and policy is not None:
            hit = cached_sweep(cache, name, options, n_vehicles=n, comm_delay_s=delay,
                               packet_loss=loss, lag_s=lag, scenario=scenario,
                               policy_sha256=policy)
            if hit is not None:
                results[ident] = hit
                continue
        jobs[ident] = (ident, name, options, n, delay, loss, lag, scenario, policy)
    if len(jobs) < MIN_POOL_SWEEPS:
        executor = "serial"
    for ident, res in map_jobs(_sweep_job, list(jobs.values()), executor, workers, ray_address):
        results[ident] = res
    for key, ident in ident_of.items():
        res = results[ident]
        if isinstance(res, str):
            line = f"no frequency sweep for {key[0]} on {key[1]} (N = {key[2]}): {res}"
            if notes is None:
                print(line, file=sys.stderr)
            elif line not in notes:
                notes.append(line)
            continue
        out[key] = res
        if cache is not None and res.key not in cache:
            cache[res.key] = res
    return out
