"""Scenarios with versioned ids: initial states, leader speed profiles, targets, seeding.

Published seeding: the perturbation of an episode is the first draw after seeding, ``U =
numpy.random.RandomState(seed).random_sample()``. Everything random in an episode comes from
streams derived from its own seed (see :func:`episode_stream`), never from a global RNG, so every
controller faces identical episodes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from envs.humans import (
    HUMAN_MODELS,
    PLACEMENTS,
    Arrangement,
    IDMParams,
    check_human_noise,
    check_reaction_delay,
    count_automated,
    idm_equilibrium_speed_mps,
    parse_positions,
    place_automated,
)
from envs.params import PlatoonParams
from envs.streams import episode_stream
from envs.vehicle_classes import (
    VehicleArrays,
    VehicleClass,
    canonical_classes,
    check_drag_saving,
    classes_for,
    parse_class_sequence,
    vehicle_arrays,
)
from infra.errors import CaccBenchError, ConfigError, UnknownNameError
from infra.limits import MAX_SEED, MAX_VEHICLES, MIN_VEHICLES
from infra.naming import coerce_option, format_label, is_reference, parse_label, parse_named_list
from infra.plugins import entry_points, first_line, load_plugin


def published_perturbation(seed: int) -> float:
    """``U = numpy.random.RandomState(seed).random_sample()``: seed 0 gives 0.5488135039273248."""
    return float(np.random.RandomState(int(seed)).random_sample())


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
    ring: bool = False
    #: Mixed-traffic metrics start this long after the start (s): the ring's first minute,
    #: when its waves are still forming, is left out; 0 elsewhere.
    settle_s: float = 0.0
    #: The ``package.module:NAME`` it was built from when it is a scenario of one's own
    #: (:attr:`base_name`); empty for a registered id.
    reference: str = field(default="", repr=False, compare=False)
    #: The options its label names (typed), which :meth:`derive` builds on.
    given: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def derive(self, **options: Any) -> Scenario:
        """This scenario with ``options`` set on top of those it was built with, checked as
        :func:`make_scenario` checks them (a training run's drawn arrangement or classes);
        built from the typed options, not from the label."""
        return make_scenario(self.base_name, **{**self.given, **options})

    @property
    def base_name(self) -> str:
        """The name :func:`make_scenario` builds it from, without options: its id, or the
        ``package.module:NAME`` reference of a scenario of one's own (whose id alone names
        nothing; the head of its :attr:`label`), as given when it was built."""
        return self.reference or self.id

    def arrangement(self, n_vehicles: int) -> Arrangement:
        """Which of the ``n_vehicles`` follower seats are automated, and how the human ones drive
        (the options ``humans``, ``cav_fraction``, ``cavs``, ``placement``, ``placement_seed``,
        ``human_model``, ``reaction_delay_s``, ``human_noise_mps2``; :mod:`envs.humans`).

        Raises
        ------
        ConfigError
            For human positions beyond ``n_vehicles`` or more automated vehicles than seats.
        """
        return arrangement_of(self.options, n_vehicles, self.label or self.id)

    def vehicle_classes(self, n_vehicles: int) -> tuple[VehicleClass, ...] | None:
        """The classes of the ``n_vehicles`` followers (options ``classes``, ``class_mix``,
        ``class_seed``; :mod:`envs.vehicle_classes`), or None for the homogeneous platoon.

        Raises
        ------
        ConfigError
            When the classes named are not exactly ``n_vehicles``.
        """
        o = self.options
        return classes_for(o.get("classes", ""), o.get("class_mix", ""),
                           int(o.get("class_seed", 0)), n_vehicles, self.label or self.id)

    def vehicle_arrays(self, n_vehicles: int, params: PlatoonParams) -> VehicleArrays | None:
        """The per-vehicle lags and bounds of the followers' classes in a run with ``params``
        (:func:`envs.vehicle_classes.vehicle_arrays`), or None without classes."""
        classes = self.vehicle_classes(n_vehicles)
        return None if classes is None else vehicle_arrays(classes, params,
                                                           self.label or self.id)

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
        check_size_fits(self, n_vehicles)
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


def check_size_fits(scenario: Scenario, n_vehicles: int) -> None:
    """Refuse a platoon size the scenario's arrangement or ring cannot take
    (:class:`ConfigError` naming what works)."""
    if scenario.ring and n_vehicles != scenario.options["vehicles"]:
        raise ConfigError(
            f"{scenario.label or scenario.id} has {scenario.options['vehicles']} vehicles on its "
            f"ring (its option vehicles), not {n_vehicles}: set the count on the scenario "
            f"({scenario.id}:vehicles={n_vehicles}) and leave --vehicles out")
    scenario.arrangement(n_vehicles)
    scenario.vehicle_classes(n_vehicles)


# --------------------------------------------------------------------------- arrangements

#: The arrangement options every scenario takes, with their defaults (every follower
#: automated: the published platoon). ``cavs`` -1 and ``humans`` "" mean "not set".
ARRANGEMENT_DEFAULTS: dict[str, Any] = {
    "humans": "",
    "cav_fraction": 1.0,
    "cavs": -1,
    "placement": "random",
    "placement_seed": 0,
    "human_model": "idm",
    "reaction_delay_s": 0.0,
    "human_noise_mps2": 0.2,
    "classes": "",
    "class_mix": "",
    "class_seed": 0,
    "drag_saving": "none",
}


#: The options that say which seats are automated (one of them at a time), and where a share or
#: a count puts them.
SEAT_OPTIONS: tuple[str, ...] = ("humans", "cav_fraction", "cavs")
PLACEMENT_OPTIONS: tuple[str, ...] = ("placement", "placement_seed")


def _check_arrangement(scenario_id: str, opts: dict[str, Any], given: dict[str, Any]) -> None:
    """The arrangement options' rules (one place): ranges, names, no option given (``given``)
    that does not act; writes the human positions in one spelling (``5+02`` is ``2+5``)."""
    share = opts["cav_fraction"]
    if not (math.isfinite(share) and 0.0 <= share <= 1.0):
        raise ConfigError(f"{scenario_id}: cav_fraction is the share of automated followers and "
                          f"must lie in [0, 1], got {share}")
    if "cavs" in given and opts["cavs"] < 0:
        raise ConfigError(f"{scenario_id}: cavs is a number of automated followers (>= 0), "
                          f"got {opts['cavs']}")
    if "humans" in given:
        if not opts["humans"].strip():
            raise ConfigError(f"{scenario_id}: humans= names no position; give the human "
                              "followers' numbers (humans=2+5), or leave the option out")
        opts["humans"] = "+".join(map(str, parse_positions(opts["humans"])))
        if any(k in given for k in PLACEMENT_OPTIONS):
            raise ConfigError(f"{scenario_id}: humans places the human followers itself; "
                              "placement and placement_seed place a share or a count "
                              "(cav_fraction, cavs): leave them out")
    if opts["placement"] not in PLACEMENTS:
        raise ConfigError(f"{scenario_id}: placement must be one of {', '.join(PLACEMENTS)}, "
                          f"got {opts['placement']!r}")
    if "placement_seed" in given and opts["placement"] != "random":
        raise ConfigError(f"{scenario_id}: placement_seed draws a random placement, but the "
                          f"placement is {opts['placement']}; add placement=random, or leave "
                          "placement_seed out")
    if opts["human_model"] not in HUMAN_MODELS:
        raise ConfigError(f"{scenario_id}: human_model must be one of {', '.join(HUMAN_MODELS)}, "
                          f"got {opts['human_model']!r}")
    check_reaction_delay(opts["reaction_delay_s"], scenario_id)
    _check_classes(scenario_id, opts, given)
    check_drag_saving(opts["drag_saving"], scenario_id)
    check_human_noise(opts["human_noise_mps2"], scenario_id)
    if not 0 <= opts["placement_seed"] <= MAX_SEED:
        raise ConfigError(f"{scenario_id}: placement_seed must lie in 0..{MAX_SEED}, got "
                          f"{opts['placement_seed']}")


def _check_classes(scenario_id: str, opts: dict[str, Any], given: dict[str, Any]) -> None:
    """The vehicle-class options' rules: known names in the grammar of
    :func:`envs.vehicle_classes.parse_class_sequence`, one of ``classes`` and ``class_mix``,
    ``class_seed`` only with a mix; writes the sequence in one spelling (``car+car`` is
    ``car*2``)."""
    for key in ("classes", "class_mix"):
        if key in given:
            if not opts[key].strip():
                raise ConfigError(f"{scenario_id}: {key}= names no class; give the followers' "
                                  "classes (classes=bus+van+car*6), or leave the option out")
            opts[key] = canonical_classes(parse_class_sequence(opts[key], f"{scenario_id}: {key}"))
    if opts["classes"] and opts["class_mix"]:
        raise ConfigError(f"{scenario_id}: classes and class_mix both say the followers' "
                          "classes; give classes for an order or class_mix for a seeded mix")
    if "class_seed" in given and not opts["class_mix"]:
        raise ConfigError(f"{scenario_id}: class_seed shuffles a class_mix; add class_mix, or "
                          "leave class_seed out")
    if not 0 <= opts["class_seed"] <= MAX_SEED:
        raise ConfigError(f"{scenario_id}: class_seed must lie in 0..{MAX_SEED}, got "
                          f"{opts['class_seed']}")


def arrangement_of(opts: dict[str, Any], n_vehicles: int, who: str) -> Arrangement:
    """The :class:`envs.humans.Arrangement` of a scenario's options for N followers."""
    if opts.get("humans"):
        human = parse_positions(opts["humans"], n_vehicles)
        automated = tuple(i + 1 not in human for i in range(n_vehicles))
    else:
        if opts.get("cavs", -1) >= 0:
            k = int(opts["cavs"])
            if k > n_vehicles:
                raise ConfigError(f"{who}: cavs={k} automated followers but only {n_vehicles} "
                                  f"followers; cavs runs from 0 to {n_vehicles}")
        else:
            k = count_automated(float(opts.get("cav_fraction", 1.0)), n_vehicles)
        seats = set(place_automated(k, n_vehicles, opts.get("placement", "random"),
                                    int(opts.get("placement_seed", 0))).tolist())
        automated = tuple(i in seats for i in range(n_vehicles))
    return Arrangement(automated, str(opts.get("human_model", "idm")),
                       float(opts.get("reaction_delay_s", 0.0)),
                       float(opts.get("human_noise_mps2", 0.2)))


# --------------------------------------------------------------------------- builders


def _equilibrium(
    sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int, leader: np.ndarray
) -> EpisodeBatch:
    """Every follower at the targets behind the leader profile ``leader``."""
    b = len(seeds)
    return EpisodeBatch(seeds=seeds, perturbation=u, gap_m=np.full((b, n), sc.target_gap_m),
                        speed_mps=np.full((b, n), sc.target_speed_mps),
                        leader_speed_mps=np.broadcast_to(leader, (b, sc.n_steps + 1)).copy())


def _catchup(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    b = len(seeds)
    gap = np.full((b, n), 20.0)
    gap[:, 0] = 20.0 * (1.5 + u)
    return EpisodeBatch(seeds=seeds, perturbation=u, gap_m=gap, speed_mps=np.full((b, n), 15.0),
                        leader_speed_mps=np.full((b, sc.n_steps + 1), 15.0))


def _slowdown(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    b = len(seeds)
    v0 = 15.0 * (1.5 + u)
    if sc.options.get("cap_initial_speed", False):
        v0 = np.minimum(v0, 30.0)
    leader = np.full((b, sc.n_steps + 1), 15.0)
    ramp = min(300, sc.n_steps + 1)
    for k in range(b):
        leader[k, :ramp] = np.linspace(v0[k], 15.0, 300)[:ramp]
    return EpisodeBatch(seeds=seeds, perturbation=u, gap_m=np.full((b, n), 20.0),
                        speed_mps=np.repeat(v0[:, None], n, axis=1), leader_speed_mps=leader)


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
    # Followers beyond the real platoon start as the last real follower (speed and gap).
    real = np.minimum(np.arange(n), window.follower_speed_mps.shape[1] - 1)
    b = len(seeds)
    return EpisodeBatch(seeds=seeds, perturbation=u,
                        gap_m=np.tile(window.follower_gap_m[0, real], (b, 1)),
                        speed_mps=np.tile(window.follower_speed_mps[0, real], (b, 1)),
                        leader_speed_mps=np.tile(lead[: sc.n_steps + 1], (b, 1)))


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


#: Longest ring of ``ring-v1`` (m): 10 km, 40 times Flow's 260 m.
MAX_RING_LENGTH_M: float = 10_000.0
#: Vehicle length on the ring (m): Flow's and SUMO's passenger-car default. The followers of the
#: other scenarios are points with gaps; on a ring the length decides the density.
RING_VEHICLE_LENGTH_M: float = 5.0


def ring_target_gap_m(length_m: float, vehicles: int) -> float:
    """The ring's uniform gap (m): ``L / n - vehicle length``."""
    return length_m / vehicles - RING_VEHICLE_LENGTH_M


def _ring(sc: Scenario, seeds: np.ndarray, u: np.ndarray, n: int) -> EpisodeBatch:
    """``n`` vehicles near uniform spacing on the ring, every one at the IDM's equilibrium speed
    for the uniform gap; each vehicle's position is moved by a uniform draw in
    ``[-perturbation_m, perturbation_m]`` from the episode's stream ``ring`` (gaps change, their
    sum stays the ring's free length). There is no leader: the leader array is filled by the
    env as the episode runs (follower N's speed, follower 1's predecessor)."""
    b = len(seeds)
    d = ring_target_gap_m(sc.options["length_m"], n)
    shift = np.empty((b, n))
    for i, seed in enumerate(seeds):
        shift[i] = sc.options["perturbation_m"] * (2.0 * episode_stream(int(seed), "ring")
                                                   .random(n) - 1.0)
    # gap_i (follower i behind i-1; follower 1 behind follower N) = d + x_{i-1} - x_i
    ahead = np.roll(shift, 1, axis=1)
    gap = d + ahead - shift
    return EpisodeBatch(seeds=seeds, perturbation=u, gap_m=gap,
                        speed_mps=np.full((b, n), sc.target_speed_mps),
                        leader_speed_mps=np.zeros((b, sc.n_steps + 1)))


def _check_ring(opts: dict[str, Any]) -> None:
    n = opts["vehicles"]
    if not MIN_VEHICLES <= n <= MAX_VEHICLES:
        raise ConfigError(f"ring-v1 vehicles must be an integer from {MIN_VEHICLES} to "
                          f"{MAX_VEHICLES}, got {n}")
    gap = ring_target_gap_m(opts["length_m"], n)
    if opts["length_m"] > MAX_RING_LENGTH_M:
        raise ConfigError(f"ring-v1 length_m must be at most {MAX_RING_LENGTH_M:g} m (a ring is "
                          f"dense traffic; a longer road is a string), got {opts['length_m']:g}")
    if not (math.isfinite(opts["length_m"]) and gap >= 2 * IDMParams().standstill_m):
        raise ConfigError(
            f"ring-v1 length_m={opts['length_m']} leaves {gap:.2f} m between {n} vehicles of "
            f"{RING_VEHICLE_LENGTH_M:g} m; give at least "
            f"{n * (RING_VEHICLE_LENGTH_M + 2 * IDMParams().standstill_m):g} m")
    if not 0.0 <= opts["perturbation_m"] < gap / 2:
        raise ConfigError(f"ring-v1 perturbation_m must lie in [0, {gap / 2:.2f}) m (half the "
                          f"uniform gap), got {opts['perturbation_m']}")


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
        Raises :class:`infra.errors.ConfigError` for impossible option values.
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
    ring: bool = False
    settle_s: float = 0.0

    @property
    def all_defaults(self) -> dict[str, Any]:
        """Its own options and the arrangement options every scenario takes
        (:data:`ARRANGEMENT_DEFAULTS`; its own defaults override them, as the ring's one
        automated vehicle)."""
        return {**self.defaults, **{k: v for k, v in ARRANGEMENT_DEFAULTS.items()
                                    if k not in self.defaults}}


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


def scenario_family(scenario_id: str) -> str:
    """The family of a versioned scenario id: the id without its ``-vN`` suffix
    (``slowdown-v2`` -> ``slowdown``, ``openacc-train-s-v1`` -> ``openacc-train-s``); the one
    grammar of ids, which :func:`register_scenario` enforces.

    Raises
    ------
    ValueError
        For an id without a version suffix.
    """
    family, sep, version = scenario_id.rpartition("-")
    if not (sep and family and version[:1] == "v" and version[1:].isdigit()):
        raise ValueError(f"scenario ids carry a version suffix -vN, got {scenario_id!r}")
    return family


def register_scenario(spec: ScenarioSpec) -> None:
    """Add a scenario to the registry (ids carry a version: ``name-vN``)."""
    scenario_family(spec.id)
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
    ScenarioSpec(
        "ring-v1",
        "single-lane ring road, no leader (Flow's replica of Sugiyama's and Stern's rings): 22 "
        "vehicles on 260 m, by default 21 IDM humans and one automated vehicle; stop-and-go "
        "waves form (options length_m, vehicles, perturbation_m; 300 s, metrics after 60 s)",
        ring_target_gap_m(260.0, 22), idm_equilibrium_speed_mps(ring_target_gap_m(260.0, 22)),
        3000, _ring, default_vehicles=22,
        defaults={"length_m": 260.0, "vehicles": 22, "perturbation_m": 1.0, "cavs": 1,
                  "placement": "front"},
        check=_check_ring, ring=True, settle_s=60.0,
    ),
):
    register_scenario(_spec)

#: Scenarios that `cacc-bench run` uses by default.
DEFAULT_SCENARIOS: tuple[str, ...] = ("catchup-v1", "slowdown-v1")

#: The entry-point group through which an installed package adds scenarios: in its
#: ``pyproject.toml``, ``[project.entry-points."cacc_bench.scenarios"]`` then
#: ``hill-v1 = "my_scenarios:HILL"``, a :class:`ScenarioSpec` whose id is the entry point's name.
ENTRY_POINT_GROUP = "cacc_bench.scenarios"

_PLUGINS: dict[str, ScenarioSpec] = {}  # the specs of references and entry points, once loaded


def plugin_targets() -> dict[str, str]:
    """``id -> "package.module:NAME"`` of the installed packages' scenarios
    (:data:`ENTRY_POINT_GROUP`), read without importing them; an id a built-in holds is left
    out."""
    return {name: target for name, target in entry_points(ENTRY_POINT_GROUP).items()
            if name not in SCENARIOS}


def _plugin_spec(name: str, target: str) -> ScenarioSpec:
    """The :class:`ScenarioSpec` at ``target`` in the user's code (``name``: the reference
    itself, or an entry point's name, which must be the spec's id). Its id must be versioned
    and not a built-in's; a reference's runs are labelled by the reference
    (``my_scenarios:HILL[grade=0.02]``), so any process can build it again.

    Raises
    ------
    ConfigError
        One line for each way it fails (:func:`infra.plugins.import_reference`,
        :func:`_check_plugin_spec`).
    """
    return load_plugin(_PLUGINS, "scenario", name, target,
                       lambda obj, who: _check_plugin_spec(obj, who, name, target))


def _kind_of(obj: Any) -> str:
    """What a reference found, for messages: ``a class``, ``a function``, ``a module`` or ``an
    object of type X``."""
    import inspect

    if inspect.isclass(obj):
        return "a class"
    if inspect.isroutine(obj):
        return "a function"
    if inspect.ismodule(obj):
        return "a module"
    return f"an object of type {type(obj).__name__}"


#: The types an option's default may have (those :func:`infra.naming.coerce_option` reads a
#: command-line value as).
OPTION_TYPES: tuple[type, ...] = (bool, int, float, str)


def _is_number(value: Any) -> bool:
    return (not isinstance(value, bool) and isinstance(value, int | float | np.integer | np.floating)
            and math.isfinite(value))


def _is_whole(value: Any, lo: int, hi: int) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | np.integer) and lo <= int(value) <= hi


def _check_plugin_spec(spec: Any, who: str, name: str, target: str) -> ScenarioSpec:
    """``spec``, the object at ``target`` for the scenario ``name`` (:func:`_plugin_spec`),
    checked once, when it is loaded, so that a mistake in it is one line before any work rather
    than a traceback or a failed run: a :class:`ScenarioSpec` with a versioned id of its own
    (an entry point's name is that id), text fields are text, the targets finite and in range
    (``0 < target_gap_m <=`` :data:`infra.limits.MAX_SPACING_M`, ``0 < target_speed_mps <=``
    the speed bound), ``n_steps`` a whole number in 1..:data:`infra.limits.MAX_EPISODE_STEPS`,
    ``default_vehicles`` a platoon size (:func:`check_vehicles`), ``settle_s`` within the
    episode, ``builder`` and ``check`` callables, and the options in ``defaults`` and ``fixed``
    named as identifiers, typed as :data:`OPTION_TYPES` and not shadowing an option every
    scenario takes (:data:`ARRANGEMENT_DEFAULTS`) or each other.

    Raises
    ------
    ConfigError
        ``<who>: <what is wrong>`` (a field's, with ``(envs.scenarios.ScenarioSpec; ...)``).
    """
    from infra.limits import MAX_EPISODE_STEPS, MAX_SPACING_M

    def bad(what: str) -> ConfigError:
        return ConfigError(f"{who}: {what} (envs.scenarios.ScenarioSpec; docs/contributing.md, "
                           "Add a scenario)")

    if not isinstance(spec, ScenarioSpec):
        raise bad(f"{target.split(':', 1)[1]} is {_kind_of(spec)}, not a ScenarioSpec")
    try:
        scenario_family(spec.id)
    except ValueError as exc:
        raise ConfigError(f"{who}: {exc}") from None
    if spec.id in SCENARIOS:
        raise ConfigError(f"{who}: its id {spec.id} is a built-in scenario's; give it an id of "
                          "its own")
    if target != name and spec.id != name:
        raise ConfigError(f"{who}: the entry point {name} names a scenario with id {spec.id}; "
                          "give the entry point the scenario's id")
    params = PlatoonParams()
    for attr in ("description", "note"):
        if not isinstance(getattr(spec, attr), str):
            raise bad(f"its {attr} must be text, got {_kind_of(getattr(spec, attr))}")
    for attr in ("published", "ring"):
        if not isinstance(getattr(spec, attr), bool):
            raise bad(f"its {attr} must be True or False, got {getattr(spec, attr)!r}")
    if not (_is_number(spec.target_gap_m) and 0 < spec.target_gap_m <= MAX_SPACING_M):
        raise bad(f"its target_gap_m must be a finite number in (0, {MAX_SPACING_M:g}] m, got "
                  f"{spec.target_gap_m!r}")
    if not (_is_number(spec.target_speed_mps)
            and 0 < spec.target_speed_mps <= params.speed_max_mps):
        raise bad(f"its target_speed_mps must be a finite number in (0, "
                  f"{params.speed_max_mps:g}] m/s, got {spec.target_speed_mps!r}")
    if not _is_whole(spec.n_steps, 1, MAX_EPISODE_STEPS):
        raise bad(f"its n_steps must be a whole number of {params.dt_s:g} s steps in "
                  f"1..{MAX_EPISODE_STEPS}, got {spec.n_steps!r}")
    length_s = spec.n_steps * params.dt_s
    if not (_is_number(spec.settle_s) and 0 <= spec.settle_s < length_s):
        raise bad(f"its settle_s must be a finite number in [0, {length_s:g}) s (the episode's "
                  f"length), got {spec.settle_s!r}")
    if not _is_whole(spec.default_vehicles, MIN_VEHICLES, MAX_VEHICLES):
        raise bad(f"its default_vehicles must be a whole number from {MIN_VEHICLES} to "
                  f"{MAX_VEHICLES}, got {spec.default_vehicles!r}")
    if not callable(spec.builder):
        raise bad(f"its builder must be a function (scenario, seeds, perturbation, n_vehicles) "
                  f"-> EpisodeBatch, got {_kind_of(spec.builder)}")
    if spec.check is not None and not callable(spec.check):
        raise bad(f"its check must be a function of the options dict, or None; got "
                  f"{_kind_of(spec.check)}")
    for field_name in ("defaults", "fixed"):
        table = getattr(spec, field_name)
        if not isinstance(table, dict):
            raise bad(f"its {field_name} must be a dict, got {_kind_of(table)}")
        named = [k for k in table if not (isinstance(k, str) and k.isidentifier())]
        if named:
            raise bad(f"its {field_name} name an option {named[0]!r}; an option's name is an "
                      "identifier (letters, digits, _)")
        shadowed = [k for k in table if k in ARRANGEMENT_DEFAULTS]
        if shadowed:
            raise bad(f"its {field_name} name {shadowed[0]}, an option every scenario takes "
                      f"(the arrangement: {', '.join(ARRANGEMENT_DEFAULTS)}); give its own "
                      "option another name")
    for key, value in spec.defaults.items():
        if not isinstance(value, OPTION_TYPES) or (isinstance(value, float)
                                                   and not math.isfinite(value)):
            raise bad(f"the default of its option {key} must be a bool, a whole number, a "
                      f"finite number or text, got {value!r}")
    both = [k for k in spec.fixed if k in spec.defaults]
    if both:
        raise bad(f"{both[0]} is both an option (defaults) and a fixed setting (fixed); keep "
                  "it in one of them")
    return spec


def _run_check(spec: ScenarioSpec, opts: dict[str, Any], name: str) -> None:
    """``spec.check(opts)``; a scenario of one's own whose check raises anything but a
    :class:`ConfigError` (its way of refusing a value) is one line naming it."""
    assert spec.check is not None
    try:
        spec.check(opts)
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - the user's code: one line
        if isinstance(exc, CaccBenchError) or SCENARIOS.get(spec.id) is spec:
            raise  # ours, or a built-in's check: its own errors are ours
        raise ConfigError(f"scenario {name}: its check of the options failed ({first_line(exc)}); "
                          "a check refuses a value by raising infra.errors.ConfigError") from None


def check_episode(scenario: Scenario, n_vehicles: int) -> None:
    """Refuse, before any run, a scenario of one's own whose builder fails or builds what the
    env cannot run: build the episode of seed 0 with ``n_vehicles`` followers and check its
    arrays (``gap_m`` and ``speed_mps`` ``(1, N)``, ``leader_speed_mps`` ``(1, n_steps + 1)``,
    finite numbers). The built-in scenarios pass at once (their builders are tested); a
    command's preflight calls this for every setting (:func:`commands.run.preflight`).

    Raises
    ------
    ConfigError
        One line naming the scenario and what its builder did.
    """
    if SCENARIOS.get(scenario.id) is not None:
        return
    who = f"scenario {scenario.label or scenario.id}"
    try:
        batch = scenario.episodes([0], n_vehicles)
    except CaccBenchError:
        raise
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - the user's builder: one line
        raise ConfigError(f"{who}: building an episode with N = {n_vehicles} failed "
                          f"({first_line(exc)}); fix its builder") from None
    if not isinstance(batch, EpisodeBatch):
        raise ConfigError(f"{who}: its builder returned {_kind_of(batch)}, not an "
                          "envs.scenarios.EpisodeBatch")
    for field_name, shape in (("gap_m", (1, n_vehicles)), ("speed_mps", (1, n_vehicles)),
                              ("leader_speed_mps", (1, scenario.n_steps + 1))):
        values = np.asarray(getattr(batch, field_name))
        if values.shape != shape:
            raise ConfigError(f"{who}: its builder's {field_name} has shape {values.shape}, "
                              f"expected {shape} (B = 1 episode, N = {n_vehicles} followers, "
                              f"n_steps + 1 = {scenario.n_steps + 1} leader speeds)")
        if values.dtype.kind not in "fiu" or not np.isfinite(values).all():
            raise ConfigError(f"{who}: its builder's {field_name} holds values that are not "
                              "finite numbers")


def scenario_spec(name: str) -> ScenarioSpec:
    """The spec a scenario name stands for: a registered id, an installed package's scenario
    (:data:`ENTRY_POINT_GROUP`) or a :class:`ScenarioSpec` in the user's code named by
    ``package.module:NAME``.

    Raises
    ------
    UnknownNameError
        If it is none of these (the message lists the valid ids).
    ConfigError
        If the user's object cannot be loaded or is not a scenario (:func:`_plugin_spec`).
    """
    spec = SCENARIOS.get(name)
    if spec is not None:
        return spec
    if is_reference(name):
        return _plugin_spec(name, name)
    targets = plugin_targets()
    if name in targets:
        return _plugin_spec(name, targets[name])
    raise UnknownNameError("scenario", name, [*SCENARIOS, *targets],
                           hint="or a ScenarioSpec of your own as package.module:NAME "
                                "(docs/contributing.md, Add a scenario)")


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
    name, options = base, {**given, **options}
    spec = scenario_spec(name)
    scenario_id = spec.id  # a reference's id is its spec's; its label starts with the reference
    defaults = spec.all_defaults
    opts = dict(defaults)
    for key, value in options.items():
        if key not in defaults:
            own = [k for k in spec.defaults if k not in ARRANGEMENT_DEFAULTS]
            raise ConfigError(
                f"scenario {scenario_id} has no option {key!r}; "
                f"its options are: {', '.join(own) or 'none'}; and the arrangement of every "
                f"scenario: {', '.join(ARRANGEMENT_DEFAULTS)}"
            )
        kind = type(defaults[key])  # an option takes the type of its default
        opts[key] = coerce_option(value if isinstance(value, str) else str(value), kind, key,
                                  scenario_id)
    if spec.check is not None:
        _run_check(spec, opts, name)
    _check_arrangement(scenario_id, opts, options)
    # which seats are automated: one of three ways; the one given replaces the default's
    seat_given = [k for k in SEAT_OPTIONS if k in options]
    if len(seat_given) > 1:
        raise ConfigError(f"{scenario_id}: {' and '.join(seat_given)} both say which followers are "
                          "automated; give one of humans (positions, humans=2+5), cav_fraction "
                          "(a share, cav_fraction=0.25) or cavs (a count, cavs=1)")
    if seat_given:
        for k in SEAT_OPTIONS:
            if k != seat_given[0]:
                opts[k] = ARRANGEMENT_DEFAULTS[k]
    # options at their default value are left out, so they never make a second leaderboard row
    # (the seat option stays when it changes the default arrangement: ring-v1:cav_fraction=1.0)
    seats_changed = any(opts[k] != defaults[k] for k in SEAT_OPTIONS)
    changed = {k: repr(opts[k]) if isinstance(opts[k], float) else str(opts[k])
               for k in options
               if opts[k] != defaults[k] or (k in SEAT_OPTIONS and seats_changed)}
    given = {k: opts[k] for k in changed}  # the label's options, typed
    opts.update(spec.fixed)
    target_gap_m, target_speed_mps, vehicles = (spec.target_gap_m, spec.target_speed_mps,
                                                spec.default_vehicles)
    if spec.ring:
        vehicles = int(opts["vehicles"])
        target_gap_m = ring_target_gap_m(opts["length_m"], vehicles)
        target_speed_mps = idm_equilibrium_speed_mps(target_gap_m)
    return Scenario(
        id=scenario_id,
        description=spec.description,
        target_gap_m=target_gap_m,
        target_speed_mps=target_speed_mps,
        n_steps=spec.n_steps,
        options=opts,
        default_vehicles=vehicles,
        note=spec.note,
        _builder=spec.builder,
        label=format_label(name, changed),
        ring=spec.ring,
        settle_s=spec.settle_s,
        reference=name if name != scenario_id else "",
        given=given,
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
    """All registered scenarios, in registration order, then the installed packages'
    (:data:`ENTRY_POINT_GROUP`; one that fails to load is left out: naming it says why)."""
    out = list(SCENARIOS.values())
    for name, target in plugin_targets().items():
        try:
            out.append(_plugin_spec(name, target))
        except ConfigError:
            continue
    return out
