"""The one controller interface the harness knows, and the episode context it hands over.

A controller is reset once per batch of episodes with an :class:`EpisodeContext`, then asked once
per step for the acceleration commands of all followers, ``(B, N)``. It declares what it sends to
other vehicles as :class:`Message` records (:meth:`Controller.messages`); the closed loop opens one
channel per message with the run's delay and loss before the reset (:func:`reset_controller`), the
controller sends through ``ctx.channel(name)``, and the loop checks that every channel sends once
per step, so delay, loss and the bit count act on everything it exchanges. The harness never
needs to know a controller's family.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from envs.channel import ChannelConfig, V2VChannel
from envs.humans import Arrangement
from envs.params import PlatoonParams
from envs.platoon import PlatoonState
from envs.scenarios import Scenario
from infra.errors import ControllerContractError
from infra.naming import build_config

FAMILIES = ("human", "linear", "mpc", "marl", "data")


@dataclass(frozen=True)
class SpacingPolicy:
    """A constant time-gap spacing policy: the gap a controller aims at,
    ``standstill_m + time_gap_s * v`` (m) for a follower at speed ``v`` (m/s).

    Attributes
    ----------
    standstill_m : float
        Standstill distance ``r`` (m).
    time_gap_s : float
        Time gap ``h`` (s), >= 0 (0: a constant spacing ``r``).
    """

    standstill_m: float
    time_gap_s: float

    def target_gap_m(self, speed_mps: np.ndarray) -> np.ndarray:
        """The policy's gap (m) for followers at ``speed_mps`` (any shape)."""
        return self.standstill_m + self.time_gap_s * np.asarray(speed_mps, dtype=np.float64)

    def describe(self) -> str:
        """``"r + h v"`` with the numbers, e.g. ``"12.5 m + 0.5 s x v"``."""
        return f"{self.standstill_m:.3g} m + {self.time_gap_s:.3g} s x v"

#: ``(controller, scenario, n_vehicles, seeds, params) -> trajectories`` (one per seed, each with
#: ``reward (T,)``, ``collided`` and ``steps``): the signature of the benchmark's closed loop.
ClosedLoop = Callable[["Controller", Scenario, int, Sequence[int], PlatoonParams], list[Any]]


@dataclass(frozen=True)
class Message:
    """One message a controller sends every step, as it declares it; the closed loop opens its
    channel (:class:`envs.channel.V2VChannel`) with the run's delay and loss.

    Attributes
    ----------
    name : str
        Channel name (distinct per controller; also the name of its loss stream).
    width : int
        Numbers per message.
    links : "predecessor", "neighbours", "to_leader" or tuple of (src, dst)
        ``predecessor``: ``i-1 -> i`` for followers ``i = 1..N`` (the leader to follower 1);
        ``neighbours``: both directions between adjacent followers, ``(i-1 -> i)`` for
        ``i = 2..N`` then ``(i+1 -> i)`` for ``i = 1..N-1``; ``to_leader``: ``i -> 0``.
    bits_per_value : int
        Bits per transmitted number (32: float32).
    initial : float
        What a receiver holds before its first message.
    """

    name: str
    width: int
    links: str | tuple[tuple[int, int], ...] = "predecessor"
    bits_per_value: int = 32
    initial: float = 0.0

    def link_list(self, n_vehicles: int, ring: bool = False) -> list[tuple[int, int]]:
        """The directed links ``(src, dst)`` for N followers (vehicle 0 is the leader; on a
        ring, where there is none, follower 1's predecessor is follower N: ``predecessor``
        starts with ``N -> 1``)."""
        n, links = n_vehicles, self.links
        if links == "predecessor":
            return [(n if ring else 0, 1)] + [(i - 1, i) for i in range(2, n + 1)]
        if links == "neighbours":
            return [(i - 1, i) for i in range(2, n + 1)] + [(i + 1, i) for i in range(1, n)]
        if links == "to_leader":
            return [(i, 0) for i in range(1, n + 1)]
        if isinstance(links, str):
            raise ControllerContractError(
                f"message {self.name!r}: unknown link pattern {links!r}; use predecessor, "
                "neighbours, to_leader or a tuple of (src, dst)")
        return list(links)


@dataclass
class EpisodeContext:
    """What a controller may know about the episodes it is about to drive.

    Attributes
    ----------
    scenario : Scenario
        The scenario (targets ``target_gap_m``, ``target_speed_mps``; length ``n_steps``).
    n_vehicles : int
        Followers N.
    seeds : (B,) ints
        Episode seeds (for channels' loss streams; controllers must not peek at the future).
    params : PlatoonParams
        Physics (dt, bounds, lag).
    channel_config : ChannelConfig
        V2V delay and loss of the run.
    channels : dict of str to V2VChannel
        The channels of the controller's declared messages, by name, opened by
        :func:`reset_controller` (the harness sums their bits).
    closed_loop : callable or None
        The benchmark's closed loop (:func:`benchmark.rollout.rollout_batch`, which sets it),
        for a controller that tunes itself by running episodes (``duty`` choosing its k): it
        runs them through the one loop without importing the benchmark.
    """

    scenario: Scenario
    n_vehicles: int
    seeds: np.ndarray
    params: PlatoonParams = PlatoonParams()
    channel_config: ChannelConfig = ChannelConfig()
    channels: dict[str, V2VChannel] = field(default_factory=dict)
    closed_loop: ClosedLoop | None = None

    def __post_init__(self) -> None:
        # the channels count delay in the run's steps: one ChannelConfig, on the run's dt
        if self.channel_config.dt_s != self.params.dt_s:
            self.channel_config = dataclasses.replace(self.channel_config, dt_s=self.params.dt_s)

    @property
    def batch_size(self) -> int:
        """Number of parallel episodes B."""
        return len(self.seeds)

    @property
    def target_gap_m(self) -> float:
        """Scenario target gap d* (m)."""
        return self.scenario.target_gap_m

    @property
    def target_speed_mps(self) -> float:
        """Scenario target speed v* (m/s)."""
        return self.scenario.target_speed_mps

    @property
    def arrangement(self) -> Arrangement:
        """Which seats are automated and how the human ones drive (the scenario's options)."""
        return self.scenario.arrangement(self.n_vehicles)

    @property
    def automated(self) -> np.ndarray:
        """``(N,)`` booleans: the seats this controller commands; the others are human-driven
        (the env drives them, they send nothing and their commands are ignored)."""
        return self.arrangement.mask

    @property
    def ring(self) -> bool:
        """A ring road: no leader, follower 1 follows follower N."""
        return self.scenario.ring

    def open_channels(self, messages: Sequence[Message]) -> None:
        """Open one channel per declared message, with this run's delay and loss; human seats
        send nothing (their links never deliver and are not counted), nor, on a ring, the
        leader that is not there (vehicle 0)."""
        silent = tuple(int(i) + 1 for i in np.flatnonzero(~self.automated))
        if self.ring:
            silent = (0, *silent)
        for m in messages:
            if m.name in self.channels:
                raise ControllerContractError(f"two messages are named {m.name!r}")
            self.channels[m.name] = V2VChannel(
                m.link_list(self.n_vehicles, self.ring), m.width, self.seeds,
                self.channel_config, m.bits_per_value, name=m.name, initial=m.initial,
                silent=silent)

    def channel(self, name: str) -> V2VChannel:
        """The channel of the declared message ``name``."""
        try:
            return self.channels[name]
        except KeyError:
            raise ControllerContractError(
                f"no channel {name!r} is open: declare it in the controller's messages() (the "
                "closed loop opens the declared channels before reset, see reset_controller)"
            ) from None

    @property
    def bits_sent(self) -> int:
        """V2V bits sent so far by all channels, over all episodes of the batch."""
        return sum(ch.bits_sent for ch in self.channels.values())

    def class_groups(self) -> list[tuple[PlatoonParams, np.ndarray]] | None:
        """On a string of vehicle classes (:mod:`envs.vehicle_classes`): each distinct physics
        (the run's, with a class's actuator lag and acceleration bounds) and its seats ``(k,)``,
        in the order of their first seat; None: the homogeneous platoon."""
        vehicles = self.scenario.vehicle_arrays(self.n_vehicles, self.params)
        if vehicles is None:
            return None
        seats: dict[PlatoonParams, list[int]] = {}
        for i in range(self.n_vehicles):
            p_i = dataclasses.replace(self.params, lag_s=float(vehicles.lag_s[i]),
                                      accel_min_mps2=float(vehicles.accel_min_mps2[i]),
                                      accel_max_mps2=float(vehicles.accel_max_mps2[i]))
            seats.setdefault(p_i, []).append(i)
        return [(p_i, np.array(s, dtype=np.int64)) for p_i, s in seats.items()]


class Controller(ABC):
    """Base class of every controller (linear law, MPC, learned policy).

    Class attributes
    ----------------
    name : str
        Registered name.
    family : str
        One of ``human``, ``linear``, ``mpc``, ``marl``.
    deterministic : bool
        Whether the same episode always gives the same commands.
    needs_observation : bool
        Whether :meth:`act` needs the agent observations ``(B, N, 15)``.
    batch_invariant : bool
        Whether an episode gives the same run, to the last bit, alone or stepped with others
        (every metric but the wall times; tested for each such controller). The harness steps
        the seeds of one setting together only for these. True for the cheap laws and the
        learned policies (whose network always sees at least eight rows, see
        ``controllers.policy.MIN_LANES``, where this machine's kernels pass the probe
        ``controllers.policy.rows_are_batch_invariant``); False for the MPC family (its
        solver-failure count is the batch's).
    """

    name: str = "controller"
    family: str = "linear"
    deterministic: bool = True
    needs_observation: bool = False
    batch_invariant: bool = False
    #: Whether it can command the automated seats of a string with human drivers (False: the
    #: paper's per-agent policies, trained on homogeneous strings, and other fixed-platoon laws).
    drives_mixed: bool = True
    #: Whether it needs a scripted leader (its profile or broadcast): refused on a ring.
    needs_leader: bool = False
    #: The frozen config dataclass whose fields are the controller's options (None: its options
    #: are its constructor's keyword arguments); :meth:`__init__` builds :attr:`config` from it.
    config_cls: type | None = None
    config: Any
    _policy_sha256: str = ""

    def __init__(self, **options: object) -> None:
        self.solver_failures = 0
        self.options: dict[str, object] = dict(options)
        if self.config_cls is not None:  # strings coerced, unknown options refused
            self.config = build_config(self.config_cls, options, self.name)

    @property
    def policy_sha256(self) -> str:
        """A hash of the learned policy this controller acts with since its last load (its
        weights and the checkpoint fields that decide how it acts); empty for a controller
        without learned weights. The harness stores it with each run, and a resumed sweep
        refuses stored runs of a policy that has changed since. A controller that loads learned
        weights sets ``_policy_sha256`` when it loads them
        (:func:`marl.checkpoint.policy_id`)."""
        return self._policy_sha256

    def preflight(self, scenario: Scenario, n_vehicles: int, params: PlatoonParams | None = None
                  ) -> None:
        """Fail now (:class:`infra.errors.ConfigError`) if this controller cannot run
        ``scenario`` with N followers and ``params``: a sweep calls it for every setting
        before its first run. Default: nothing to check."""
        return None

    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """What this controller sends over V2V each step in the episodes of ``ctx`` (default:
        nothing). The closed loop opens their channels, then calls :meth:`reset`, which takes
        them with ``ctx.channel(name)``."""
        return ()

    @abstractmethod
    def reset(self, ctx: EpisodeContext) -> None:
        """Prepare for a batch of episodes (build problems, take the channels of its messages
        with ``ctx.channel(name)``)."""

    @abstractmethod
    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        """Acceleration commands ``(B, N)`` in m/s^2 for the current state.

        Parameters
        ----------
        state : PlatoonState
            Current state (read only: gaps, speeds, last applied accelerations, the leader's
            current speed and planned acceleration).
        observation : (B, N, 15) or None
            Agent observations, when ``needs_observation`` is set.
        """

    def spacing_policy(self, target_gap_m: float, target_speed_mps: float
                       ) -> SpacingPolicy | None:
        """The constant time-gap policy this controller aims at on a scenario whose reward
        targets are ``target_gap_m`` and ``target_speed_mps``, or None (the default): it has
        no spacing policy of its own and aims at the scenario's constant target gap (the
        published reward's). The harness measures ``gap_rmse_own_policy_m`` against it and
        ``plot`` draws it."""
        return None

    def intervention_totals(self) -> tuple[np.ndarray, np.ndarray] | None:
        """For a safety filter (:mod:`controllers.safety_filter`): per episode of the batch since
        the reset, ``(B,)`` each, the follower-steps whose command it lowered and the sum of how
        much (m/s^2). None (the default): the controller filters nothing."""
        return None

    def describe(self) -> str:
        """Options as a stable string (recorded in the run's provenance)."""
        return ",".join(f"{k}={v}" for k, v in sorted(self.options.items()))


def reset_controller(controller: Controller, ctx: EpisodeContext) -> None:
    """Open the channels of the messages ``controller`` declares, then reset it: the start of
    every batch of episodes in the closed loop (and in tests that step a controller by hand)."""
    ctx.open_channels(controller.messages(ctx))
    controller.reset(ctx)
