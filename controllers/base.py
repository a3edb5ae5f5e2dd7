"""The one controller interface the harness knows, and the episode context it hands over.

A controller is reset once per batch of episodes with an :class:`EpisodeContext`, then asked once
per step for the acceleration commands of all followers, ``(B, N)``. Whatever it sends to other
vehicles goes through channels made by :meth:`EpisodeContext.make_channel`, so delay and packet
loss act on it and its bits are counted; the closed loop checks that a controller declaring V2V
opened its channels and that each channel sends once per step. The harness never needs to know a
controller's family.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from envs.channel import ChannelConfig, V2VChannel
from envs.params import PlatoonParams
from envs.platoon import PlatoonState
from envs.scenarios import Scenario

FAMILIES = ("human", "linear", "mpc", "marl", "data")

#: ``(controller, scenario, n_vehicles, seeds, params) -> trajectories`` (one per seed, each with
#: ``reward (T,)``, ``collided`` and ``steps``): the signature of the benchmark's closed loop.
ClosedLoop = Callable[["Controller", Scenario, int, Sequence[int], PlatoonParams], list[Any]]


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
    channels : list of V2VChannel
        Every channel the controller made (the harness sums their bits).
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
    channels: list[V2VChannel] = field(default_factory=list)
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

    def make_channel(
        self,
        width: int,
        name: str,
        links: Sequence[tuple[int, int]] | str = "predecessor",
        bits_per_value: int = 32,
        initial: float | np.ndarray = 0.0,
    ) -> V2VChannel:
        """Create a V2V channel with this run's delay and loss; its bits are counted.

        Parameters
        ----------
        width : int
            Numbers per message.
        name : str
            Stream name (distinct per channel of one controller).
        links : "predecessor", "neighbours" or a list of (src, dst)
            ``predecessor``: ``i-1 -> i`` for followers (leader to follower 1);
            ``neighbours``: both directions between adjacent followers.
        """
        n = self.n_vehicles
        if links == "predecessor":
            link_list = [(i - 1, i) for i in range(1, n + 1)]
        elif links == "neighbours":
            link_list = [(i - 1, i) for i in range(2, n + 1)] + [
                (i + 1, i) for i in range(1, n)
            ]
        elif isinstance(links, str):
            raise ValueError(f"unknown link pattern {links!r}")
        else:
            link_list = list(links)
        ch = V2VChannel(link_list, width, self.seeds, self.channel_config, bits_per_value,
                        name=name, initial=initial)
        self.channels.append(ch)
        return ch

    @property
    def bits_sent(self) -> int:
        """V2V bits sent so far by all channels, over all episodes of the batch."""
        return sum(ch.bits_sent for ch in self.channels)


def sends_v2v(controller: object) -> bool:
    """Whether a controller declares V2V messages (its ``v2v`` is not ``none...``): such a
    controller must open its channels with :meth:`EpisodeContext.make_channel` at reset, so
    that delay, loss and bit counting act on what it exchanges (the closed loop checks it)."""
    return not str(getattr(controller, "v2v", "none")).startswith("none")


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
    v2v : str
        What it receives over V2V, in words (``none`` for none).
    needs_observation : bool
        Whether :meth:`act` needs the agent observations ``(B, N, 15)``.
    batch_invariant : bool
        Whether an episode gives the same run, to the last bit, alone or stepped with others
        (every metric but the wall times; tested for each such controller). The harness steps
        the seeds of one setting together only for these. True for the cheap laws and the
        learned policies (whose network always sees at least two rows, see
        ``controllers.policy.MIN_LANES``, where this machine's kernels pass the probe
        ``controllers.policy.rows_are_batch_invariant``); False for the MPC family (its
        solver-failure count is the batch's).
    """

    name: str = "controller"
    family: str = "linear"
    deterministic: bool = True
    v2v: str = "none"
    needs_observation: bool = False
    batch_invariant: bool = False

    def __init__(self) -> None:
        self.solver_failures = 0
        self.options: dict[str, object] = {}

    def preflight(self, scenario: Scenario, n_vehicles: int, params: PlatoonParams | None = None
                  ) -> None:
        """Fail now (:class:`envs.errors.ConfigError`) if this controller cannot run
        ``scenario`` with N followers and ``params``: a sweep calls it for every setting
        before its first run. Default: nothing to check."""
        return None

    @abstractmethod
    def reset(self, ctx: EpisodeContext) -> None:
        """Prepare for a batch of episodes (build problems, make channels)."""

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

    def describe(self) -> str:
        """Options as a stable string (recorded in the run's provenance)."""
        return ",".join(f"{k}={v}" for k, v in sorted(self.options.items()))
