"""Scenarios with versioned ids: initial states, leader speed profiles, targets, seeding.

Published seeding: the perturbation of an episode is the first draw after seeding, ``U =
numpy.random.RandomState(seed).random_sample()``. Everything random in an episode comes from
streams derived from its own seed (see :func:`episode_stream`), never from a global RNG, so every
controller faces identical episodes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from envs.errors import ConfigError, UnknownNameError
from envs.naming import coerce_option, format_label, parse_label, parse_named_list
from envs.params import PlatoonParams

MIN_VEHICLES = 2
MAX_VEHICLES = 64


def published_perturbation(seed: int) -> float:
    """``U = numpy.random.RandomState(seed).random_sample()``: seed 0 gives 0.5488135039273248."""
    return float(np.random.RandomState(int(seed)).random_sample())


def episode_stream(seed: int, stream: str) -> np.random.Generator:
    """An independent random stream of one episode, named (e.g. ``"loss"``, ``"noise"``).

    Depends only on the episode seed and the stream's name, never on a global state.
    """
    key = [int(b) for b in stream.encode()]
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), *key])))


@dataclass(frozen=True)
class EpisodeBatch:
    """Initial conditions of ``B`` episodes of one scenario.

    Attributes
    ----------
    seeds : (B,) int
        Episode seeds.
    perturbation : (B,) float
        The uniform draw ``U`` of each episode (published seeding), or the value passed in.
    gap_m, speed_mps : (B, N)
        Followers' initial gaps and speeds (speeds may exceed the bound: slowdown-v1 quirk).
    leader_speed_mps : (B, n_steps + 1)
        Leader speed at steps 0..n_steps.
    """

    seeds: np.ndarray
    perturbation: np.ndarray
    gap_m: np.ndarray
    speed_mps: np.ndarray
    leader_speed_mps: np.ndarray


@dataclass(frozen=True)
class Scenario:
    """A scenario: targets, length, and a generator of initial conditions and leader profiles.

    Use :func:`make_scenario` to build one from its id and options (it alone checks them). It
    pickles (its builder is a module-level function), so executors hand it to workers as is.

    Attributes
    ----------
    label : str
        The canonical label (``sine-v1[amplitude_mps=2.0]``): the id and the options set away
        from their defaults; the name of its runs in the store and in ``runs.csv``.
    """

    id: str
    description: str
    target_gap_m: float
    target_speed_mps: float
    n_steps: int
    options: dict[str, Any] = field(default_factory=dict)
    default_vehicles: int = 8
    note: str = ""
    _builder: Callable[[Scenario, np.ndarray, np.ndarray, int], EpisodeBatch] | None = field(
        default=None, repr=False, compare=False
    )
    label: str = field(default="", repr=False, compare=False)

    def episodes(
        self,
        seeds: Sequence[int] | np.ndarray,
        n_vehicles: int,
        perturbation: float | Sequence[float] | np.ndarray | None = None,
    ) -> EpisodeBatch:
        """Initial conditions and leader profiles of one episode per seed.

        Parameters
        ----------
        seeds : sequence of int, length B
            Episode seeds.
        n_vehicles : int
            Number of followers N.
        perturbation : float or (B,) floats in [0, 1), optional
            Overrides the published draw ``U`` of each episode.
        """
        check_vehicles(n_vehicles)
        seeds_arr = np.asarray(seeds, dtype=np.int64).reshape(-1)
        if perturbation is None:
            u = np.array([published_perturbation(int(s)) for s in seeds_arr], dtype=np.float64)
        else:
            u = np.broadcast_to(np.asarray(perturbation, dtype=np.float64), seeds_arr.shape).copy()
            if np.any(~np.isfinite(u)) or np.any(u < 0) or np.any(u > 1):
                raise ConfigError("perturbation must lie in [0, 1]")
        assert self._builder is not None
        return self._builder(self, seeds_arr, u, n_vehicles)


def check_vehicles(n_vehicles: int) -> int:
    """Validate the platoon size N (followers), return it."""
    if not isinstance(n_vehicles, int | np.integer) or not (
        MIN_VEHICLES <= n_vehicles <= MAX_VEHICLES
    ):
        raise ConfigError(
            f"the number of followers must be an integer from {MIN_VEHICLES} to {MAX_VEHICLES}, "
            f"got {n_vehicles!r}"
        )
    return int(n_vehicles)


# --------------------------------------------------------------------------- builders


def _equilibrium(
    sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int, leader: np.ndarray
) -> EpisodeBatch:
    b = len(seeds)
    return EpisodeBatch(
        seeds=seeds,
        perturbation=u,
        gap_m=np.full((b, n), sc.target_gap_m),
        speed_mps=np.full((b, n), sc.target_speed_mps),
        leader_speed_mps=np.broadcast_to(leader, (b, sc.n_steps + 1)).copy(),
    )


def _catchup(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    b = len(seeds)
    gap = np.full((b, n), 20.0)
    gap[:, 0] = 20.0 * (1.5 + u)
    return EpisodeBatch(
        seeds=seeds,
        perturbation=u,
        gap_m=gap,
        speed_mps=np.full((b, n), 15.0),
        leader_speed_mps=np.full((b, sc.n_steps + 1), 15.0),
    )


def _slowdown(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    b = len(seeds)
    v0 = 15.0 * (1.5 + u)
    if sc.options.get("cap_initial_speed", False):
        v0 = np.minimum(v0, 30.0)
    leader = np.full((b, sc.n_steps + 1), 15.0)
    ramp = min(300, sc.n_steps + 1)
    for k in range(b):
        leader[k, :ramp] = np.linspace(v0[k], 15.0, 300)[:ramp]
    return EpisodeBatch(
        seeds=seeds,
        perturbation=u,
        gap_m=np.full((b, n), 20.0),
        speed_mps=np.repeat(v0[:, None], n, axis=1),
        leader_speed_mps=leader,
    )


def _sine(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    amp = float(sc.options["amplitude_mps"])
    freq = float(sc.options["frequency_hz"])
    t = np.arange(sc.n_steps + 1) * PlatoonParams().dt_s
    leader = sc.target_speed_mps + amp * np.sin(2 * np.pi * freq * t)
    return _equilibrium(sc, seeds, u, n, leader)


def brake_profile_mps(n_steps: int, dt_s: float = 0.1) -> np.ndarray:
    """Leader of ``brake-v1``: 15 m/s; from 10 s brakes at 2.5 m/s^2 to 5 m/s, holds 10 s,
    returns to 15 m/s at 1.5 m/s^2. Speeds at steps 0..n_steps (exact piecewise-linear)."""
    t = np.arange(n_steps + 1) * dt_s
    t1 = 10.0
    t2 = t1 + (15.0 - 5.0) / 2.5
    t3 = t2 + 10.0
    t4 = t3 + (15.0 - 5.0) / 1.5
    v = np.full_like(t, 15.0)
    v = np.where((t >= t1) & (t < t2), 15.0 - 2.5 * (t - t1), v)
    v = np.where((t >= t2) & (t < t3), 5.0, v)
    v = np.where((t >= t3) & (t < t4), 5.0 + 1.5 * (t - t3), v)
    return v


def _brake(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    return _equilibrium(sc, seeds, u, n, brake_profile_mps(sc.n_steps))


def _openacc(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    from envs.openacc import load_window

    window = load_window(sc.options["window"])
    lead = np.asarray(window.leader_speed_mps, dtype=np.float64)
    if len(lead) < sc.n_steps + 1:
        raise ConfigError(f"OpenACC window {window.name} has only {len(lead)} samples")
    k = window.follower_speed_mps.shape[1]
    speed0 = np.empty(n)
    gap0 = np.empty(n)
    m = min(n, k)
    speed0[:m] = window.follower_speed_mps[0, :m]
    gap0[:m] = window.follower_gap_m[0, :m]
    # Followers beyond the real platoon start as the last real follower (speed and gap).
    speed0[m:] = speed0[m - 1]
    gap0[m:] = gap0[m - 1]
    b = len(seeds)
    return EpisodeBatch(
        seeds=seeds,
        perturbation=u,
        gap_m=np.tile(gap0, (b, 1)),
        speed_mps=np.tile(speed0, (b, 1)),
        leader_speed_mps=np.tile(lead[: sc.n_steps + 1], (b, 1)),
    )


def dynamic_platform_profile_mps(
    uniforms: np.ndarray, n_steps: int, dt_s: float = 0.1
) -> np.ndarray:
    """A leader speed profile shaped like the OpenACC Dynamic Platform's perturbation.

    Cruise at ``v0``, brake at a constant rate down to ``v_min``, hold, accelerate back to
    ``v0`` and cruise. Six uniforms in [0, 1) set, in order: ``v0`` in [7.5, 12] m/s, the braking
    start in [3, 15] s, the braking rate in [1.5, 3.5] m/s^2, ``v_min`` in [3, 7] m/s (at most
    ``v0 - 1``), the hold in [0, 4] s and the recovery rate in [0.8, 2.8] m/s^2. The three real
    test windows lie inside these ranges (cruise 8.2-11.1 m/s, minimum 4.4-5.8 m/s, braking up to
    2.7-3.4 m/s^2 and recovery up to 1.2-2.7 m/s^2, about 10-13 s in).
    """
    u = np.asarray(uniforms, dtype=np.float64)
    v0 = 7.5 + 4.5 * u[0]
    t_brake = 3.0 + 12.0 * u[1]
    a_brake = 1.5 + 2.0 * u[2]
    v_min = min(3.0 + 4.0 * u[3], v0 - 1.0)
    hold = 4.0 * u[4]
    a_up = 0.8 + 2.0 * u[5]
    t = np.arange(n_steps + 1) * dt_s
    return braking_profile_mps(t, v0, t_brake, a_brake, v_min, hold, a_up)


def _openacc_train(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    """Randomised training episodes for the OpenACC setting (never the test windows)."""
    b = len(seeds)
    leader = np.empty((b, sc.n_steps + 1))
    gap0 = np.empty((b, n))
    speed0 = np.empty((b, n))
    for i, seed in enumerate(seeds):
        rng = episode_stream(int(seed), "openacc-train")
        draws = rng.random(6)
        draws[0] = u[i]  # the episode's perturbation sets the cruise speed
        leader[i] = dynamic_platform_profile_mps(draws, sc.n_steps)
        gap0[i] = sc.target_gap_m * (0.8 + 0.6 * rng.random(n))
        speed0[i] = np.clip(leader[i, 0] + rng.normal(0.0, 0.2, n), 0.0, None)
    return EpisodeBatch(seeds=seeds, perturbation=u, gap_m=gap0, speed_mps=speed0,
                        leader_speed_mps=leader)


#: The disturbances the ``mixed`` families draw from (their ``kinds`` option joins a subset with
#: ``+``). ``mixed-v1`` stays as first published, with the first four; ``mixed-v2`` adds the
#: randomised OpenACC-like leader of the ``openacc-train`` families.
MIXED_KINDS: tuple[str, ...] = ("catchup", "slowdown", "brake", "sine", "openacc")
MIXED_V1_KINDS: tuple[str, ...] = MIXED_KINDS[:4]


def _mixed(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    """A distribution of episodes (domain randomisation): per episode, its own stream draws the
    kind of disturbance and its parameters, then the followers' initial gaps and speeds are
    spread around the kind's own. ``catchup`` and ``slowdown`` are the published builders (the
    episode's ``U`` sets them); ``brake`` is a leader braking from ``v*`` at a random rate to a
    random speed, holding, and recovering (``brake-v1`` and the OpenACC Dynamic Platform's
    manoeuvre are members); ``sine`` has a random amplitude and frequency; ``openacc`` is the
    randomised Dynamic-Platform-like leader of the ``openacc-train`` families (cruise at 7.5-12
    m/s, braking at up to 3.5 m/s^2 as in the three real windows) with the followers starting at
    ``d*`` and the leader's initial speed."""
    o = sc.options
    kinds = o["kinds"].split("+")
    b = len(seeds)
    leader = np.empty((b, sc.n_steps + 1))
    gap0 = np.empty((b, n))
    speed0 = np.empty((b, n))
    t = np.arange(sc.n_steps + 1) * PlatoonParams().dt_s
    for i, seed in enumerate(seeds):
        rng = episode_stream(int(seed), "mixed")
        kind = kinds[int(rng.integers(len(kinds)))]
        one = (sc, seeds[i:i + 1], u[i:i + 1], n)
        if kind == "catchup":
            ep = _catchup(*one)
        elif kind == "slowdown":
            ep = _slowdown(*one)
        elif kind == "brake":
            v0 = sc.target_speed_mps
            a_brake = 1.5 + (o["brake_rate_max_mps2"] - 1.5) * rng.random()
            v_min = 3.0 + (v0 - 5.0) * rng.random()
            profile = braking_profile_mps(t, v0, 3.0 + 12.0 * rng.random(), a_brake, v_min,
                                          10.0 * rng.random(), 0.8 + 2.0 * rng.random())
            ep = _equilibrium(sc, *one[1:], profile)
        elif kind == "openacc":
            profile = dynamic_platform_profile_mps(rng.random(6), sc.n_steps)
            ep = _equilibrium(sc, *one[1:], profile)
            ep.speed_mps[:] = profile[0]
        else:
            amp = o["sine_amplitude_max_mps"] * rng.random()
            freq = 0.02 + (o["sine_frequency_max_hz"] - 0.02) * rng.random()
            profile = sc.target_speed_mps + amp * np.sin(2 * np.pi * freq * t)
            ep = _equilibrium(sc, *one[1:], profile)
        leader[i] = ep.leader_speed_mps[0]
        spread = 1.0 + o["gap_spread"] * (2.0 * rng.random(n) - 1.0)
        if kind == "catchup":
            spread[0] = 1.0  # follower 1's gap is the disturbance
        gap0[i] = ep.gap_m[0] * spread
        speed0[i] = np.clip(ep.speed_mps[0] + o["speed_spread_mps"] * (2.0 * rng.random(n) - 1.0),
                            0.0, None)
    return EpisodeBatch(seeds=seeds, perturbation=u, gap_m=gap0, speed_mps=speed0,
                        leader_speed_mps=leader)


def braking_profile_mps(t_s: np.ndarray, v0_mps: float, t_brake_s: float, a_brake_mps2: float,
                        v_min_mps: float, hold_s: float, a_up_mps2: float) -> np.ndarray:
    """Cruise at ``v0``, from ``t_brake`` brake at ``a_brake`` to ``v_min``, hold ``hold``,
    accelerate back to ``v0`` at ``a_up`` (speeds at the times ``t_s``)."""
    t_low = t_brake_s + (v0_mps - v_min_mps) / a_brake_mps2
    t_up = t_low + hold_s
    v = np.full_like(t_s, v0_mps)
    braking = (t_s > t_brake_s) & (t_s <= t_low)
    v[braking] = v0_mps - a_brake_mps2 * (t_s[braking] - t_brake_s)
    v[(t_s > t_low) & (t_s <= t_up)] = v_min_mps
    rising = t_s > t_up
    v[rising] = np.minimum(v_min_mps + a_up_mps2 * (t_s[rising] - t_up), v0_mps)
    return v


def _mixed_check(scenario_id: str, allowed: tuple[str, ...]) -> Callable[[dict[str, Any]], None]:
    """The option check of one ``mixed`` family (its id in the messages, its own kinds)."""

    def check(opts: dict[str, Any]) -> None:
        kinds = opts["kinds"].split("+")
        if not kinds or any(k not in allowed for k in kinds) or len(set(kinds)) != len(kinds):
            raise ConfigError(f"{scenario_id} kinds must join distinct names of "
                              f"{', '.join(allowed)} with '+', got {opts['kinds']!r}")
        if not 1.5 <= opts["brake_rate_max_mps2"] <= 2.5:
            raise ConfigError(f"{scenario_id} brake_rate_max_mps2 must lie in [1.5, 2.5] m/s^2 "
                              "(a leader braking harder than the followers can is not "
                              "survivable)")
        if not 0 <= opts["sine_amplitude_max_mps"] <= 10:
            raise ConfigError(f"{scenario_id} sine_amplitude_max_mps must lie in [0, 10] m/s")
        if not 0.02 < opts["sine_frequency_max_hz"] < 5:
            raise ConfigError(f"{scenario_id} sine_frequency_max_hz must lie in (0.02, 5) Hz")
        if not (0 <= opts["gap_spread"] < 0.5 and 0 <= opts["speed_spread_mps"] <= 3):
            raise ConfigError(f"{scenario_id} gap_spread must lie in [0, 0.5) and "
                              "speed_spread_mps in [0, 3] m/s")

    return check


def _mixed_spec(scenario_id: str, kinds: tuple[str, ...], description: str) -> ScenarioSpec:
    return ScenarioSpec(
        scenario_id, description, 20.0, 15.0, 600, _mixed,
        defaults={"kinds": "+".join(kinds), "brake_rate_max_mps2": 2.5,
                  "sine_amplitude_max_mps": 3.0, "sine_frequency_max_hz": 0.5,
                  "gap_spread": 0.2, "speed_spread_mps": 0.5},
        check=_mixed_check(scenario_id, kinds),
    )


def _openacc_train_spec(size: str, gap_m: float) -> ScenarioSpec:
    return ScenarioSpec(
        f"openacc-train-{size}-v1",
        f"training family for openacc-{size}-v1 (d* = {gap_m:g} m, v* = 11 m/s): randomised "
        "Dynamic-Platform-like braking and recovery of the leader, followers 0.8-1.4 d* apart",
        gap_m, 11.0, 600, _openacc_train, default_vehicles=4,
    )


# --------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class ScenarioSpec:
    """A registered scenario id: its options (with defaults, and a check of their values) and
    the fixed settings its builder reads.

    Attributes
    ----------
    defaults : dict
        Options a user may set (``sine-v1:amplitude_mps=2``), with their defaults; a value takes
        the type of its default.
    fixed : dict
        Settings of the id itself (an OpenACC window, a speed cap), not user options.
    check : callable, optional
        Raises :class:`envs.errors.ConfigError` for impossible option values.
    """

    id: str
    description: str
    target_gap_m: float
    target_speed_mps: float
    n_steps: int
    builder: Callable[[Scenario, np.ndarray, np.ndarray, int], EpisodeBatch]
    defaults: dict[str, Any] = field(default_factory=dict)
    default_vehicles: int = 8
    note: str = ""
    published: bool = False
    fixed: dict[str, Any] = field(default_factory=dict)
    check: Callable[[dict[str, Any]], None] | None = None


def _openacc_spec(window: str, description: str) -> ScenarioSpec:
    """An OpenACC replay scenario; targets and notes come from :data:`envs.openacc.WINDOWS`."""
    from envs.openacc import WINDOWS

    w = WINDOWS[window]
    return ScenarioSpec(
        w.scenario_id, description, w.target_gap_m, w.target_speed_mps, 600, _openacc,
        fixed={"window": window}, default_vehicles=4, note=w.note,
    )


def _check_sine(opts: dict[str, Any]) -> None:
    if not 0 <= opts["amplitude_mps"] <= 10:
        raise ConfigError("sine-v1 amplitude_mps must lie in [0, 10] m/s")
    if not 0 < opts["frequency_hz"] < 5:
        raise ConfigError("sine-v1 frequency_hz must lie in (0, 5) Hz (Nyquist at dt = 0.1 s)")


SCENARIOS: dict[str, ScenarioSpec] = {}


def register_scenario(spec: ScenarioSpec) -> None:
    """Add a scenario to the registry (ids carry a version: ``name-vN``)."""
    if not spec.id.rsplit("-", 1)[-1].startswith("v"):
        raise ValueError(f"scenario ids carry a version suffix -vN, got {spec.id!r}")
    SCENARIOS[spec.id] = spec


for _spec in (
    ScenarioSpec(
        "catchup-v1",
        "published: leader at 15 m/s, follower 1 starts 20(1.5+U) m behind",
        20.0, 15.0, 600, _catchup, published=True,
    ),
    ScenarioSpec(
        "slowdown-v1",
        "published: leader slows linearly from 15(1.5+U) m/s to 15 m/s over 30 s "
        "(initial speeds above 30 m/s are clipped at step 1, a published quirk)",
        20.0, 15.0, 600, _slowdown, published=True,
    ),
    ScenarioSpec(
        "slowdown-v2",
        "as slowdown-v1 with the initial speed capped at 30 m/s",
        20.0, 15.0, 600, _slowdown, fixed={"cap_initial_speed": True},
    ),
    ScenarioSpec(
        "sine-v1",
        "leader speed 15 + A sin(2 pi f t) from equilibrium (options amplitude_mps, frequency_hz)",
        20.0, 15.0, 600, _sine, defaults={"amplitude_mps": 1.0, "frequency_hz": 0.2},
        check=_check_sine,
    ),
    ScenarioSpec(
        "brake-v1",
        "leader brakes at 2.5 m/s^2 from 15 to 5 m/s at t = 10 s, holds 10 s, back at 1.5 m/s^2",
        20.0, 15.0, 600, _brake,
    ),
    _openacc_spec("S", "real OpenACC leader (ZalaZONE dynamic_part1, 316..376 s, short ACC setting)"),
    _openacc_spec(
        "M",
        "real OpenACC leader (ZalaZONE dynamic_part8, 1250..1310 s, medium setting; "
        "stands in for the paper's dynamic_part9)",
    ),
    _openacc_spec("L", "real OpenACC leader (ZalaZONE dynamic_part2, 450..510 s, long ACC setting)"),
    _mixed_spec(
        "mixed-v1", MIXED_V1_KINDS,
        "a training distribution: per episode catchup, slowdown, a random braking manoeuvre or "
        "a random sine (options kinds, brake_rate_max_mps2, sine_amplitude_max_mps, "
        "sine_frequency_max_hz, gap_spread, speed_spread_mps)",
    ),
    _mixed_spec(
        "mixed-v2", MIXED_KINDS,
        "mixed-v1 plus the randomised OpenACC-like leader (kind openacc, as openacc-train-*-v1 "
        "draws it); the same options",
    ),
    _openacc_train_spec("s", 12.0),
    _openacc_train_spec("m", 16.0),
    _openacc_train_spec("l", 20.0),
):
    register_scenario(_spec)

#: Scenarios that `cacc-bench run` uses by default.
DEFAULT_SCENARIOS: tuple[str, ...] = ("catchup-v1", "slowdown-v1")


def make_scenario(scenario_id: str, /, **options: Any) -> Scenario:
    """Build a registered scenario by id, with options (e.g. ``frequency_hz`` of ``sine-v1``);
    the id may carry them as a label (``sine-v1[amplitude_mps=2]`` or ``sine-v1:amplitude_mps=2``).

    The one rule for scenario input: every other way in (:func:`as_scenario`,
    :func:`parse_scenarios`, :func:`scenario_label`) comes through here.

    Raises
    ------
    UnknownNameError
        If the id is not registered (the message lists the valid ids).
    ConfigError
        For an unknown option or an impossible value.
    """
    base, given = parse_label(scenario_id, "scenario")
    scenario_id, options = base, {**given, **options}
    try:
        spec = SCENARIOS[scenario_id]
    except KeyError:
        raise UnknownNameError("scenario", scenario_id, SCENARIOS) from None
    opts = dict(spec.defaults)
    for key, value in options.items():
        if key not in spec.defaults:
            raise ConfigError(
                f"scenario {scenario_id} has no option {key!r}; "
                f"its options are: {', '.join(spec.defaults) or 'none'}"
            )
        kind = type(spec.defaults[key])  # an option takes the type of its default
        opts[key] = coerce_option(value if isinstance(value, str) else str(value), kind, key,
                                  scenario_id)
    if spec.check is not None:
        spec.check(opts)
    # options at their default value are left out, so they never make a second leaderboard row
    changed = {k: repr(opts[k]) if isinstance(opts[k], float) else str(opts[k])
               for k in options if opts[k] != spec.defaults[k]}
    opts.update(spec.fixed)
    return Scenario(
        id=scenario_id,
        description=spec.description,
        target_gap_m=spec.target_gap_m,
        target_speed_mps=spec.target_speed_mps,
        n_steps=spec.n_steps,
        options=opts,
        default_vehicles=spec.default_vehicles,
        note=spec.note,
        _builder=spec.builder,
        label=format_label(scenario_id, changed),
    )


def as_scenario(scenario: str | Scenario) -> Scenario:
    """``scenario`` itself, or the scenario a label or id names (built by :func:`make_scenario`).

    For functions that also take a label: the command layer hands the layers below built
    :class:`Scenario` objects, which pass through unchanged.
    """
    return scenario if isinstance(scenario, Scenario) else make_scenario(scenario)


def scenario_label(text: str) -> str:
    """The canonical label of a scenario with options (``sine-v1:amplitude_mps=2.0`` ->
    ``sine-v1[amplitude_mps=2.0]``); options at their default value are left out, so they never
    make a second leaderboard row. Checks the id and the options."""
    return make_scenario(text).label


def parse_scenarios(text: str) -> list[Scenario]:
    """The scenarios of a ``--scenarios`` list (``catchup-v1,sine-v1:amplitude_mps=2``), one per
    item, in order, each built once by :func:`make_scenario`.

    Raises
    ------
    UnknownNameError, ConfigError
        As :func:`make_scenario`; ConfigError also for an empty list or a malformed item.
    """
    return [make_scenario(name, **opts) for name, opts in parse_named_list(text, "scenario")]


def parse_scenario_list(text: str) -> list[str]:
    """Canonical labels of a ``--scenarios`` list (``catchup-v1,sine-v1:amplitude_mps=2``)."""
    return [sc.label for sc in parse_scenarios(text)]


def list_scenarios() -> list[ScenarioSpec]:
    """All registered scenarios, in registration order."""
    return list(SCENARIOS.values())
