"""Human drivers in the string: the arrangement of seats, the human models, their noise.

A follower seat is *automated* (the controller under test commands it) or *human* (the
environment drives it with a human-driver model; it sends nothing over V2V and takes no command).
Which seats are human is the scenario's arrangement (:class:`Arrangement`, from the options
``humans``, ``cav_fraction``, ``cavs``, ``placement`` and ``placement_seed`` that every scenario
takes); it is the same for every episode of a scenario, so a leaderboard row is one arrangement.

Two human models (sources and parameters: ``docs/concepts/mixed-traffic.md``):

- ``idm``: the Intelligent Driver Model (Treiber, Hennecke, Helbing 2000) with the parameters of
  the open mixed-autonomy benchmarks (Flow's ``IDMController``: a = 1 m/s^2, b = 1.5 m/s^2,
  v0 = 30 m/s, T = 1 s, s0 = 2 m, delta = 4) and Gaussian acceleration noise (std 0.2 m/s^2
  every step, Flow's ring set-up);
- ``ovm``: the optimal velocity model of the published benchmark with per-vehicle parameters
  drawn as DeeP-LCC's heterogeneous humans (alpha in [0.4, 0.8], beta in [0.6, 1.0], s_go in
  [31, 39] m; the ranges of DeeP-LCC's ``data_hdvParameter``), with the same noise.

Both take an optional reaction delay (whole steps of ``dt``): a human acts on what it saw that
long ago. Every draw (parameters, noise) comes from the episode seed alone, through streams named
here, so every controller meets the same humans on the same seed, alone or in a batch.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from envs.params import PlatoonParams
from envs.streams import episode_stream
from infra.errors import ConfigError

#: The human-driver models a scenario's ``human_model`` option takes.
HUMAN_MODELS: tuple[str, ...] = ("idm", "ovm")
#: Where ``cav_fraction`` / ``cavs`` put the automated vehicles among the followers.
PLACEMENTS: tuple[str, ...] = ("random", "front", "rear", "spread")
#: The longest reaction delay a human may have (s): a limit, checked in one place.
MAX_REACTION_DELAY_S: float = 2.0
#: The largest standard deviation of the humans' acceleration noise (m/s^2).
MAX_HUMAN_NOISE_MPS2: float = 2.0
#: Stream name of a random placement (with the scenario's ``placement_seed``).
PLACEMENT_STREAM = "placement"


def check_reaction_delay(value: float, who: str) -> float:
    """``value`` if it is a reaction delay in [0, :data:`MAX_REACTION_DELAY_S`] s and a whole
    number of steps (0.05 s would act as 0.1 s and be labelled 0.05), else a ConfigError naming
    ``who`` (a scenario's option, the ``idm`` controller's)."""
    dt_s = PlatoonParams().dt_s
    if not 0.0 <= value <= MAX_REACTION_DELAY_S:
        raise ConfigError(f"{who}: reaction_delay_s must lie in [0, {MAX_REACTION_DELAY_S:g}] s, "
                          f"got {value}")
    if abs(value / dt_s - round(value / dt_s)) > 1e-6:
        raise ConfigError(f"{who}: reaction_delay_s={value:g}: a human reacts after whole "
                          f"simulation steps of {dt_s:g} s; give a multiple of {dt_s:g} s")
    return float(value)


def check_human_noise(value: float, who: str, name: str = "human_noise_mps2") -> float:
    """``value`` if it is a noise standard deviation in [0, :data:`MAX_HUMAN_NOISE_MPS2`]
    m/s^2, else a ConfigError naming ``who`` and the option ``name``."""
    if not 0.0 <= value <= MAX_HUMAN_NOISE_MPS2:
        raise ConfigError(f"{who}: {name} must lie in [0, {MAX_HUMAN_NOISE_MPS2:g}] m/s^2, "
                          f"got {value}")
    return float(value)


@dataclass(frozen=True)
class IDMParams:
    """Parameters of the Intelligent Driver Model (Flow's ``IDMController`` defaults).

    Attributes
    ----------
    accel_max_mps2 : float
        Maximum acceleration a (1 m/s^2).
    decel_comfort_mps2 : float
        Comfortable deceleration b (1.5 m/s^2).
    desired_speed_mps : float
        Desired speed v0 (30 m/s).
    time_gap_s : float
        Safe time headway T (1 s).
    standstill_m : float
        Jam distance s0 (2 m).
    delta : float
        Acceleration exponent (4).
    """

    accel_max_mps2: float = 1.0
    decel_comfort_mps2: float = 1.5
    desired_speed_mps: float = 30.0
    time_gap_s: float = 1.0
    standstill_m: float = 2.0
    delta: float = 4.0


#: Ranges of the heterogeneous OVM humans' per-vehicle draws (DeeP-LCC ``data_hdvParameter``):
#: alpha (1/s), beta (1/s), s_go (m); s_st stays the benchmark's 5 m and v_max 30 m/s.
OVM_ALPHA_RANGE: tuple[float, float] = (0.4, 0.8)
OVM_BETA_RANGE: tuple[float, float] = (0.6, 1.0)
OVM_GAP_GO_RANGE_M: tuple[float, float] = (31.0, 39.0)


def idm_accel_mps2(gap_m: np.ndarray, speed_mps: np.ndarray, pred_speed_mps: np.ndarray,
                   p: IDMParams = IDMParams()) -> np.ndarray:
    """IDM acceleration ``a [1 - (v/v0)^delta - (s*/s)^2]``, ``s* = s0 + v T + v dv/(2 sqrt(ab))``.

    Parameters
    ----------
    gap_m, speed_mps, pred_speed_mps : arrays of one shape
        Bumper-to-bumper gap ``s``, own speed ``v`` and the predecessor's speed.
    p : IDMParams

    Returns
    -------
    array
        The acceleration (m/s^2), unclipped; a gap at or below 0 is taken as 1 cm (the collision
        rule ends the episode long before).
    """
    v = np.asarray(speed_mps, dtype=np.float64)
    # s* = s0 + v (T + (v - v_pred) / (2 sqrt(a b)))
    s_star = v - pred_speed_mps
    s_star *= 1.0 / (2.0 * math.sqrt(p.accel_max_mps2 * p.decel_comfort_mps2))
    s_star += p.time_gap_s
    s_star *= v
    s_star += p.standstill_m
    s_star /= np.maximum(gap_m, 0.01)
    s_star *= s_star  # (s*/s)^2
    if p.delta == 4.0:  # the common exponent, without a general power (several times faster)
        free = v / p.desired_speed_mps
        free *= free
        free *= free
    else:
        free = (v / p.desired_speed_mps) ** p.delta
    free += s_star
    return p.accel_max_mps2 * (1.0 - free)


def idm_equilibrium_speed_mps(gap_m: float, p: IDMParams = IDMParams()) -> float:
    """The speed at which the IDM keeps ``gap_m`` behind a predecessor at the same speed (the
    root of ``1 - (v/v0)^delta = ((s0 + v T)/s)^2`` in ``[0, v0]``, by bisection)."""
    if gap_m <= p.standstill_m:
        return 0.0
    lo, hi = 0.0, p.desired_speed_mps
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if 1.0 - (mid / p.desired_speed_mps) ** p.delta - ((p.standstill_m + mid * p.time_gap_s)
                                                           / gap_m) ** 2 > 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


#: Integer keys of the humans' per-episode streams (``numpy.random.default_rng([seed, key])``:
#: a few microseconds to start, where a named :func:`envs.streams.episode_stream` takes tens).
NOISE_KEY: int = 0x6E6F697365  # "noise"
PARAMS_KEY: int = 0x706172616D  # "param"
#: Levels of the humans' Gaussian noise: a draw is the normal quantile of one of 2^16 equally
#: likely levels (inverse transform of 16 random bits), rescaled to unit variance; its tails end
#: at 4.32 standard deviations. Sixteen bits a draw instead of a float64 normal keep an env with
#: humans within reach of the homogeneous env's speed (``cacc-bench perf``).
NOISE_LEVELS: int = 1 << 16


@functools.cache
def _normal_levels() -> np.ndarray:
    """The :data:`NOISE_LEVELS` quantiles ``Phi^-1((k + 1/2) / 2^16)``, scaled to unit variance."""
    from scipy.special import ndtri

    q = ndtri((np.arange(NOISE_LEVELS) + 0.5) / NOISE_LEVELS)
    return q / np.sqrt(np.mean(q * q))


class HumanNoise:
    """The humans' acceleration noise of a batch of episodes: Gaussian, std ``std_mps2``, every
    step and seat.

    A pure function of (episode seed, seat, step): episode ``seed``'s stream
    ``default_rng([seed, NOISE_KEY])`` gives seat ``i`` the 16-bit draws ``i T .. (i+1) T - 1``
    (so a seat's noise does not depend on N), each mapped to a level of :func:`_normal_levels`.
    An episode's humans get the same noise alone or in a batch, with any controller, and an
    ``idm`` controller on a seat gets the noise a human on that seat would.

    Parameters
    ----------
    seeds : (B,) ints
    n_seats, n_steps : int
    std_mps2 : float
    """

    def __init__(self, seeds: np.ndarray, n_seats: int, n_steps: int, std_mps2: float) -> None:
        seeds = np.asarray(seeds, dtype=np.int64).reshape(-1)
        raw = np.empty((n_seats, n_steps, len(seeds)), dtype=np.uint16)
        for k, seed in enumerate(seeds):
            bits = np.random.default_rng([int(seed), NOISE_KEY]).bytes(2 * n_seats * n_steps)
            raw[:, :, k] = np.frombuffer(bits, dtype="<u2").reshape(n_seats, n_steps)
        self._raw = raw
        self._levels = _normal_levels() * std_mps2

    def at(self, step: int, seats: np.ndarray) -> np.ndarray:
        """The noise of ``seats`` (0-based) at ``step``, ``(B, len(seats))`` (a Fortran-ordered
        array, laid out as the env's follower arrays)."""
        step = min(step, self._raw.shape[1] - 1)
        return self._levels[self._raw[seats, step, :]].T


@dataclass(frozen=True)
class Arrangement:
    """Which follower seats are automated, and how the human ones drive.

    Attributes
    ----------
    automated : tuple of bool, length N
        Seat ``i`` (follower ``i + 1``) is automated.
    human_model : str
        ``idm`` or ``ovm`` (:data:`HUMAN_MODELS`).
    reaction_delay_s : float
        The humans' reaction delay (rounded to whole steps).
    noise_std_mps2 : float
        Standard deviation of the humans' Gaussian acceleration noise, every step.
    """

    automated: tuple[bool, ...]
    human_model: str = "idm"
    reaction_delay_s: float = 0.0
    noise_std_mps2: float = 0.2

    @property
    def mask(self) -> np.ndarray:
        """``(N,)`` booleans, True where the seat is automated."""
        return np.array(self.automated, dtype=bool)

    @property
    def n_automated(self) -> int:
        """Automated seats."""
        return int(sum(self.automated))

    @property
    def cav_share(self) -> float:
        """Share of the followers that are automated, in [0, 1]."""
        return self.n_automated / len(self.automated)

    @property
    def homogeneous(self) -> bool:
        """Every seat automated (the published platoon)."""
        return all(self.automated)

    def delay_steps(self, dt_s: float) -> int:
        """The reaction delay in whole steps."""
        return int(round(self.reaction_delay_s / dt_s + 1e-9))


def count_automated(cav_fraction: float, n_vehicles: int) -> int:
    """Automated seats for a share: ``floor(share N + 1/2)`` (half up), at least one for a
    positive share (0.05 of 8 is one vehicle, not none)."""
    k = int(math.floor(cav_fraction * n_vehicles + 0.5))
    return max(k, 1) if cav_fraction > 0 else 0


def place_automated(k: int, n_vehicles: int, placement: str, placement_seed: int) -> np.ndarray:
    """The seats (0-based, sorted) of ``k`` automated vehicles among ``n_vehicles``.

    ``front``: the first k; ``rear``: the last k; ``spread``: ``floor(j N / k)`` for
    ``j = 0..k-1`` (evenly, the first seat automated); ``random``: drawn without replacement from
    the stream ``placement`` of ``placement_seed`` (the same for every episode of the scenario).
    """
    if placement == "front":
        seats = np.arange(k)
    elif placement == "rear":
        seats = np.arange(n_vehicles - k, n_vehicles)
    elif placement == "spread":
        seats = np.array([(j * n_vehicles) // k for j in range(k)], dtype=np.int64)
    else:
        seats = np.sort(episode_stream(int(placement_seed), PLACEMENT_STREAM)
                        .choice(n_vehicles, size=k, replace=False))
    return np.asarray(seats, dtype=np.int64)


def parse_positions(text: str, n_vehicles: int | None = None) -> tuple[int, ...]:
    """Human follower positions of the ``humans`` option: ``"2+5"`` -> ``(2, 5)`` (1-based).

    Raises
    ------
    ConfigError
        For an item that is not a positive integer, a repeated one, or (with ``n_vehicles``) a
        position beyond N.
    """
    out: list[int] = []
    for s in (item.strip() for item in text.split("+")):
        if not s.isdigit() or int(s) < 1:
            raise ConfigError(f"humans={text!r}: positions are follower numbers 1..N joined with "
                              f"'+' (humans=2+5), got {s!r}")
        out.append(int(s))
    if len(set(out)) != len(out):
        raise ConfigError(f"humans={text!r} names a position twice")
    if n_vehicles is not None and max(out) > n_vehicles:
        raise ConfigError(f"humans={text!r}: position {max(out)} is beyond the {n_vehicles} "
                          f"followers of this run; positions run from 1 to {n_vehicles}")
    return tuple(sorted(out))


class HumanDrivers:
    """The human seats of a batch of episodes: their parameters, delay buffer and noise.

    Built by the environment at reset; :meth:`commands` returns the commands of every seat with
    the human ones replaced by the human model's (automated seats keep the controller's).

    Parameters
    ----------
    arrangement : Arrangement
    seeds : (B,) ints
        Episode seeds (the parameter draws and the noise come from them).
    n_steps : int
        Steps of the episode.
    params : PlatoonParams
        Physics (``dt_s``, the OVM's gaps).
    ring : bool
        A ring road (follower 1's predecessor is follower N).
    idm : IDMParams
        The IDM humans' parameters (Flow's by default).
    """

    def __init__(self, arrangement: Arrangement, seeds: np.ndarray, n_steps: int,
                 params: PlatoonParams, ring: bool = False, idm: IDMParams = IDMParams()
                 ) -> None:
        self.arrangement = arrangement
        self.params = params
        n = len(arrangement.automated)
        self.human = ~arrangement.mask  # (N,)
        #: the human seats (0-based) and the seats ahead of them (-1: the leader, or N-1 on a ring)
        self.seats = np.flatnonzero(self.human)
        self._ahead = self.seats - 1
        self._behind_leader = (not ring) and bool(self.seats.size) and self.seats[0] == 0
        self.model = arrangement.human_model
        self.delay = arrangement.delay_steps(params.dt_s)
        self.idm = idm
        if self.model == "ovm":
            draws = np.stack([_ovm_draws(int(s), n) for s in seeds])  # (B, 3, N)
            self.alpha, self.beta, self.gap_go_m = draws[:, 0], draws[:, 1], draws[:, 2]
            self._own = (self.alpha[:, self.seats], self.beta[:, self.seats],
                         self.gap_go_m[:, self.seats])
        std = arrangement.noise_std_mps2
        self.noise = HumanNoise(seeds, n, n_steps, std) if std > 0 else None
        self._history: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def model_accel_mps2(self, gap_m: np.ndarray, speed_mps: np.ndarray,
                         pred_speed_mps: np.ndarray) -> np.ndarray:
        """The human model's acceleration of the human seats, ``(B, H)``, from their gaps,
        speeds and predecessors' speeds ``(B, H)``, without noise or delay."""
        if self.model == "idm":
            return idm_accel_mps2(gap_m, speed_mps, pred_speed_mps, self.idm)
        alpha, beta, gap_go = self._own
        return ovm_hetero_accel_mps2(gap_m, speed_mps, pred_speed_mps, alpha, beta, gap_go,
                                     self.params)

    def commands(self, step: int, command_mps2: np.ndarray, gap_m: np.ndarray,
                 speed_mps: np.ndarray, leader_speed_mps: np.ndarray) -> np.ndarray:
        """``command_mps2`` with the human seats' commands put in (a new array).

        Parameters
        ----------
        step : int
        command_mps2, gap_m, speed_mps : (B, N)
        leader_speed_mps : (B,)
            The leader's speed now (unused on a ring).
        """
        seats = self.seats
        g = gap_m[:, seats]
        v = speed_mps[:, seats]
        vp = speed_mps[:, self._ahead]
        if self._behind_leader:
            vp[:, 0] = leader_speed_mps
        if self.delay:
            self._history.append((g, v, vp))
            if len(self._history) > self.delay + 1:
                self._history.pop(0)
            g, v, vp = self._history[0]  # what they saw `delay` steps ago (at first: the start)
        u = self.model_accel_mps2(g, v, vp)
        if self.noise is not None:
            u += self.noise.at(step, seats)
        out = np.array(command_mps2, dtype=np.float64, order="F")
        out[:, seats] = u
        return out


def ovm_hetero_accel_mps2(gap_m: np.ndarray, speed_mps: np.ndarray, pred_speed_mps: np.ndarray,
                          alpha: np.ndarray, beta: np.ndarray, gap_go_m: np.ndarray,
                          params: PlatoonParams = PlatoonParams()) -> np.ndarray:
    """The OVM ``alpha (V(s) - v) + beta (v_pred - v)`` with per-vehicle ``alpha``, ``beta`` and
    ``s_go`` (the benchmark's cosine ``V``: s_st = ``params.gap_stop_m``, v_max 30 m/s)."""
    span = gap_go_m - params.gap_stop_m
    g = np.clip(gap_m, params.gap_stop_m, gap_go_m)
    v_opt = params.ovm_speed_max_mps / 2 * (1 - np.cos(np.pi * (g - params.gap_stop_m) / span))
    return alpha * (v_opt - speed_mps) + beta * (pred_speed_mps - speed_mps)


def _ovm_draws(seed: int, n: int) -> np.ndarray:
    """``(3, N)``: alpha, beta and s_go of every seat of one episode (uniform in the ranges,
    from the stream ``default_rng([seed, PARAMS_KEY])``)."""
    rng = np.random.default_rng([seed, PARAMS_KEY])
    lo = np.array([OVM_ALPHA_RANGE[0], OVM_BETA_RANGE[0], OVM_GAP_GO_RANGE_M[0]])[:, None]
    hi = np.array([OVM_ALPHA_RANGE[1], OVM_BETA_RANGE[1], OVM_GAP_GO_RANGE_M[1]])[:, None]
    return lo + (hi - lo) * rng.random((3, n))
