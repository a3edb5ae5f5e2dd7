"""The thin stateful platoon environment over the pure step functions, batched over episodes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.accel_mode import (
    ACCEL_OBS_DIM,
    accel_observations,
    check_action_mode,
    open_accel_channels,
    transmit_accel_messages,
)
from envs.channel import ChannelConfig
from envs.dynamics import (
    BLOCK_DIM,
    OBS_DIM,
    action_to_command_mps2,
    agent_observations,
    combine_reward,
    physics_step,
    predecessor_speed_mps,
    reward_terms,
    vehicle_blocks,
)
from envs.humans import HumanDrivers
from envs.params import OVM_ACTIONS, PlatoonParams, RewardWeights
from envs.scenarios import Scenario, as_scenario, check_vehicles
from envs.vehicle_classes import VEHICLE_CLASSES, VehicleArrays
from infra.errors import ConfigError

COLLISION_MODES = ("terminate", "published")


def check_actions(actions: Any, shape: tuple[int, ...], params: PlatoonParams, discrete: bool,
                  name: str = "actions") -> np.ndarray:
    """``actions`` as an array if it has ``shape`` and holds OVM-gain indices (``discrete``: whole
    numbers 0..3) or finite accelerations (m/s^2; the env clips them to the bounds), else a
    ConfigError naming the shape and range expected: the one rule of :meth:`PlatoonEnv.step`,
    :meth:`PlatoonEnv.step_actions` and the adapters (:mod:`envs.adapters`)."""
    try:
        a = np.asarray(actions)
    except ValueError:  # ragged
        a = np.asarray(actions, dtype=object)
    k = len(OVM_ACTIONS)
    numeric = a.shape == shape and a.dtype.kind in "iuf"
    if numeric and not discrete and np.isfinite(a).all():
        return a
    if numeric and discrete and (a.size == 0 or (a.min() >= 0 and a.max() < k and (
            a.dtype.kind != "f" or (a == np.floor(a)).all()))):
        return a
    if discrete:
        rule = f"OVM-gain indices (whole numbers 0..{k - 1})"
        bad = a[(a < 0) | (a >= k) | (a != np.floor(a))] if numeric else a
    else:
        lo, hi = params.accel_min_mps2, params.accel_max_mps2
        rule = f"finite accelerations in m/s^2 (outside [{lo:g}, {hi:g}] clipped)"
        bad = a[~np.isfinite(a)] if numeric else a
    got = f"{bad.flat[0]}" if a.shape == shape and a.size else f"shape {a.shape}"
    where = f"of shape {shape}" if shape else "(one number)"
    raise ConfigError(f"{name} must be {rule} {where}, got {got}")


@dataclass
class PlatoonState:
    """Mutable state of ``B`` episodes (arrays are owned by the env; copy to keep them).

    Attributes
    ----------
    step : int
        Steps taken since reset (all episodes of a batch step together).
    gap_m, speed_mps : (B, N)
        Gaps to the predecessor and speeds of the followers.
    realised_accel_mps2 : (B, N)
        Lag state: the realised acceleration (equal to the clipped command without lag).
    applied_accel_mps2 : (B, N)
        Applied acceleration of the last step ``(v_t - v_{t-1})/dt``, 0 at reset (``u_last``).
    command_mps2 : (B, N)
        The last step's command clipped to the acceleration bounds, 0 at reset (what a
        controller whose state is its own last command, as ``cacc``'s filter, remembers).
    leader_speed_mps : (B, T+1)
        Leader profile of each episode.
    collided : (B,) bool
        Whether a collision happened (latched).
    done : (B,) bool
        Whether the episode has ended (frozen from then on).
    collision_step : (B,) int
        Step of the collision, -1 if none.
    """

    step: int
    gap_m: np.ndarray
    speed_mps: np.ndarray
    realised_accel_mps2: np.ndarray
    applied_accel_mps2: np.ndarray
    command_mps2: np.ndarray
    leader_speed_mps: np.ndarray
    collided: np.ndarray
    done: np.ndarray
    collision_step: np.ndarray
    dt_s: float = 0.1
    automated: np.ndarray | None = None
    ring: bool = False

    @property
    def automated_mask(self) -> np.ndarray:
        """``(N,)`` booleans: the seats the controller commands (the others are human-driven by
        the env; every seat in the published platoon)."""
        if self.automated is None:
            return np.ones(self.speed_mps.shape[1], dtype=bool)
        return self.automated

    @property
    def leader_speed_now_mps(self) -> np.ndarray:
        """Leader speed at the current step, ``(B,)`` (on a ring: follower N's, the speed of
        follower 1's predecessor)."""
        if self.ring:
            return self.speed_mps[:, -1]
        return self.leader_speed_mps[:, min(self.step, self.leader_speed_mps.shape[1] - 1)]

    @property
    def leader_accel_now_mps2(self) -> np.ndarray:
        """Leader acceleration over the coming step ``(v0[t+1] - v0[t]) / dt``, ``(B,)`` (on a
        ring, where nobody's plan is known: follower N's last applied acceleration)."""
        if self.ring:
            return self.applied_accel_mps2[:, -1]
        t = min(self.step, self.leader_speed_mps.shape[1] - 2)
        return (self.leader_speed_mps[:, t + 1] - self.leader_speed_mps[:, t]) / self.dt_s

    @property
    def pred_speed_mps(self) -> np.ndarray:
        """Speed of each follower's predecessor, ``(B, N)`` (on a ring, follower N is follower
        1's)."""
        return predecessor_speed_mps(self.leader_speed_now_mps, self.speed_mps, self.ring)


@dataclass
class StepResult:
    """What :meth:`PlatoonEnv.step` returns.

    Attributes
    ----------
    reward : (B, N)
        Reward of every agent (training or evaluation form, see the env's ``training`` flag).
    done : (B,) bool
        Episodes that have ended (at the last step, or by collision).
    collided : (B,) bool
        Episodes with a collision so far.
    power_kw : (B, N)
        Battery power of every follower over the step (fitted polynomial).
    applied_accel_mps2 : (B, N)
        Applied accelerations of the step.
    observation : (B, N, 15) or (B, N, 12) or None
        Agent observations after the step (if the env observes; the width is the action mode's,
        :attr:`PlatoonEnv.obs_dim`).
    tracking_reward : (B, N)
        The evaluation reward without the power term (the published benchmark's reward), by the
        same rules: the collision penalty at a collision step, 0 once an episode has ended.
    """

    reward: np.ndarray
    done: np.ndarray
    collided: np.ndarray
    power_kw: np.ndarray
    applied_accel_mps2: np.ndarray
    observation: np.ndarray | None
    tracking_reward: np.ndarray


class PlatoonEnv:
    """Batched platoon environment: ``B`` episodes of one scenario and size, stepped together.

    Parameters
    ----------
    scenario : Scenario or str
        Scenario object or registered id.
    n_vehicles : int
        Followers N (2..64).
    params : PlatoonParams
        Physics (``lag_s`` for the actuator lag).
    training : bool
        Include the safety term in the reward (published: training only).
    include_power : bool
        Include the power term ``-10 P`` in the reward (the paper's reward; True by default).
    collision_mode : {"terminate", "published"}
        ``terminate``: a collision ends the episode (benchmark rule). ``published``: the state
        freezes, every agent gets -1000 at that and every later step, and the episode ends at the
        next multiple of 60 steps (published training rule).
    observe : bool
        Compute agent observations every step (MARL); controllers that read the state directly
        may turn this off.
    dtype : numpy dtype
        Float type of the observations (physics is always float64).
    action_mode : {"ovm-gain", "accel"}
        ``ovm-gain`` (published): :meth:`step_actions` takes OVM-gain indices and agents observe
        15 numbers. ``accel``: :meth:`step` takes the acceleration commands as the action, and
        agents observe the 12 numbers of :func:`envs.accel_mode.accel_observations`, whose V2V
        part passes through the channel ``channel`` (:mod:`envs.accel_mode`).
    channel : ChannelConfig
        V2V delay and loss of the ``accel`` mode's messages (ideal by default).
    """

    def __init__(
        self,
        scenario: Scenario | str,
        n_vehicles: int = 8,
        params: PlatoonParams = PlatoonParams(),
        *,
        training: bool = False,
        include_power: bool = True,
        collision_mode: str = "terminate",
        observe: bool = True,
        weights: RewardWeights = RewardWeights(),
        dtype: type = np.float32,
        action_mode: str = "ovm-gain",
        channel: ChannelConfig = ChannelConfig(),
    ) -> None:
        self.action_mode = check_action_mode(action_mode)
        self.channel_config = channel
        self.scenario = as_scenario(scenario)
        self.n_vehicles = check_vehicles(n_vehicles)
        if collision_mode not in COLLISION_MODES:
            raise ConfigError(
                f"collision_mode must be one of {', '.join(COLLISION_MODES)}, got {collision_mode!r}"
            )
        self.params = params
        self.training = training
        self.include_power = include_power
        self.collision_mode = collision_mode
        self.observe = observe
        self.weights = weights
        self.dtype = dtype
        self.n_steps = self.scenario.n_steps
        self.target_gap_m = self.scenario.target_gap_m
        self.target_speed_mps = self.scenario.target_speed_mps
        from envs.energy import load_power_polynomial

        self.power = load_power_polynomial()
        #: The polynomial is evaluated inside its fit domain only: beyond the hardest braking of
        #: the fit (-3 m/s^2) the friction brakes take the rest, so the battery power stays at the
        #: edge value (this matters for the published slowdown-v1 quirk, whose first step
        #: "decelerates" at tens of m/s^2).
        self.power_accel_range_mps2 = tuple(self.power.metadata.get("grid", {})
                                            .get("accel_range_mps2", (-3.0, 2.5)))
        self.state: PlatoonState | None = None
        self.seeds: np.ndarray = np.zeros(0, dtype=np.int64)
        self._obs: np.ndarray | None = None
        self._blocks: np.ndarray | None = None
        self._pred_held = np.zeros((0, 0))
        self._leader_held = np.zeros((0, 0, 2))
        self._channels: tuple[Any, Any] | None = None
        self._humans: HumanDrivers | None = None
        self.vehicles: VehicleArrays | None = None
        self._string_power: Any = None
        self._drag_saving: Any = None

    #: The step of the physics (:func:`envs.dynamics.physics_step`'s signature); another simulator
    #: behind the same env (:class:`envs.sumo.env.SumoPlatoonEnv`) overrides it.
    _physics = staticmethod(physics_step)

    @property
    def obs_dim(self) -> int:
        """Floats in one agent's observation (15 in the ``ovm-gain`` mode, 12 in ``accel``)."""
        return ACCEL_OBS_DIM if self.action_mode == "accel" else OBS_DIM

    # ------------------------------------------------------------------ API
    def reset(
        self,
        seeds: Sequence[int] | np.ndarray | int,
        perturbation: float | Sequence[float] | np.ndarray | None = None,
    ) -> np.ndarray | None:
        """Start one episode per seed; returns the observations ``(B, N, 15)`` (or None).

        Parameters
        ----------
        seeds : int or sequence of int
            Episode seeds (published seeding of ``U``).
        perturbation : float or (B,) floats, optional
            Explicit ``U`` in [0, 1] overriding the seeded draw.

        Raises
        ------
        ConfigError
            For a perturbation of another shape, or outside [0, 1].
        """
        seeds_arr = np.atleast_1d(np.asarray(seeds, dtype=np.int64))
        try:
            u_shape = None if perturbation is None else np.asarray(perturbation, np.float64).shape
        except (TypeError, ValueError):
            u_shape = (-1,)
        if u_shape not in (None, (), seeds_arr.shape):
            raise ConfigError(f"perturbation must be one number in [0, 1] or one per episode "
                              f"(B = {len(seeds_arr)}), got {perturbation!r}")
        ep = self.scenario.episodes(seeds_arr, self.n_vehicles, perturbation)
        b, n = len(seeds_arr), self.n_vehicles
        self.seeds = seeds_arr
        self.perturbation = ep.perturbation
        self.arrangement = self.scenario.arrangement(n)
        #: per-vehicle lags and bounds of a heterogeneous string (None: the published platoon)
        self.vehicles = self.scenario.vehicle_arrays(n, self.params)
        from envs.energy.classes import DragSaving, StringPower

        classes = None if self.vehicles is None else self.vehicles.classes
        self._string_power = (None if classes is None
                              else StringPower(classes, self._i3_power_kw))
        #: the platoon's drag saving (scenario option drag_saving; None: off, the default)
        self._drag_saving = (None if self.scenario.options.get("drag_saving", "none") == "none"
                             else DragSaving(classes or (VEHICLE_CLASSES["i3"],) * n))
        self._humans = (None if self.arrangement.homogeneous else
                        HumanDrivers(self.arrangement, seeds_arr, self.n_steps, self.params,
                                     self.scenario.ring))
        ring = self.scenario.ring
        # Follower arrays are (B, N) in Fortran order (the batch axis innermost in memory):
        # elementwise physics does not care, and the neighbour shifts of the observation become
        # long contiguous copies (about 10x faster at B = 1024).
        self.state = PlatoonState(
            step=0,
            gap_m=np.asfortranarray(ep.gap_m, dtype=np.float64).copy(order="F"),
            speed_mps=np.asfortranarray(ep.speed_mps, dtype=np.float64).copy(order="F"),
            realised_accel_mps2=np.zeros((b, n), order="F"),
            applied_accel_mps2=np.zeros((b, n), order="F"),
            command_mps2=np.zeros((b, n), order="F"),
            leader_speed_mps=ep.leader_speed_mps.astype(np.float64),
            collided=np.zeros(b, dtype=bool),
            done=np.zeros(b, dtype=bool),
            collision_step=np.full(b, -1, dtype=np.int64),
            dt_s=self.params.dt_s,
            automated=None if self._humans is None else self.arrangement.mask,
            ring=ring,
        )
        if ring:  # no scripted leader: record follower N's speed, follower 1's predecessor
            self.state.leader_speed_mps[:, 0] = self.state.speed_mps[:, -1]
        # observation storage (15, N, B) viewed as (B, N, 15); the own block is a view into it
        self._obs = np.zeros((OBS_DIM, n, b), dtype=self.dtype).transpose(2, 1, 0)
        self._blocks = self._obs[:, :, 0:BLOCK_DIM]
        if self.action_mode == "accel":
            self._channels = open_accel_channels(n, seeds_arr, self.channel_config,
                                                 silent=self.silent_senders, ring=ring)
            self._pred_held = np.zeros((b, n))
            self._leader_held = np.zeros((b, n, 2))
        return self.observation() if self.observe else None

    @property
    def silent_senders(self) -> tuple[int, ...]:
        """Vehicle indices (1..N) of the human seats: they send nothing over V2V."""
        if self.state is None or self.state.automated is None:
            return ()
        return tuple(int(i) + 1 for i in np.flatnonzero(~self.state.automated))

    @property
    def batch_size(self) -> int:
        """Number of parallel episodes B."""
        return len(self.seeds)

    def observation(self) -> np.ndarray:
        """Agent observations of the current state: ``(B, N, 15)`` (own, front, rear blocks) in
        the ``ovm-gain`` mode, ``(B, N, 12)`` in the ``accel`` mode."""
        s = self._require_state()
        if self.action_mode == "accel":
            return accel_observations(
                s.gap_m, s.speed_mps, s.pred_speed_mps, s.applied_accel_mps2,
                s.realised_accel_mps2, self._pred_held, self._leader_held, self.target_gap_m,
                self.target_speed_mps, self.params, self.dtype)
        assert self._obs is not None and self._blocks is not None
        vehicle_blocks(s.gap_m, s.speed_mps, s.pred_speed_mps, s.applied_accel_mps2,
                       self.target_gap_m, self.target_speed_mps, self.params, out=self._blocks)
        return agent_observations(self._blocks, out=self._obs)

    def step_actions(self, actions: np.ndarray) -> StepResult:
        """Step with discrete MARL actions ``(B, N)`` (OVM gains, published mapping; whole numbers
        0..3, else a ConfigError, :func:`check_actions`)."""
        s = self._require_state()
        if self.action_mode != "ovm-gain":
            raise ConfigError(
                "step_actions takes OVM-gain indices; this env is in the accel mode: pass the "
                "acceleration commands to step()")
        actions = check_actions(actions, s.gap_m.shape, self.params, discrete=True)
        u = action_to_command_mps2(actions.astype(np.int64, copy=False), s.gap_m, s.speed_mps,
                                   s.pred_speed_mps, self.params)
        return self._advance(s, u)

    def step(self, command_mps2: np.ndarray) -> StepResult:
        """Apply acceleration commands ``(B, N)`` (finite, clipped to the bounds) for one step.

        In the ``accel`` mode the commands are also this step's V2V messages (sent before the
        physics, observed from the next step on, as ``cacc`` does).

        Raises
        ------
        ConfigError
            For commands of another shape or not finite (:func:`check_actions`).
        """
        s = self._require_state()
        check_actions(command_mps2, s.gap_m.shape, self.params, discrete=False, name="commands")
        return self._advance(s, command_mps2)

    def _advance(self, s: PlatoonState, command_mps2: np.ndarray) -> StepResult:
        """One step of checked commands ``(B, N)``."""
        if s.step >= self.n_steps:
            raise RuntimeError("episode over: call reset()")
        t = s.step
        if self._humans is not None:  # the human seats take no command: their model drives
            command_mps2 = self._humans.commands(t, command_mps2, s.gap_m, s.speed_mps,
                                                 s.leader_speed_now_mps)
        if self._channels is not None and self.action_mode == "accel":
            self._pred_held, self._leader_held = transmit_accel_messages(
                *self._channels, np.asarray(command_mps2, dtype=np.float64),
                s.leader_accel_now_mps2, s.leader_speed_now_mps, self.target_speed_mps,
                self.params)
        gap, v, a, applied = self._physics(
            s.gap_m, s.speed_mps, s.realised_accel_mps2, np.asarray(command_mps2, dtype=np.float64),
            s.leader_speed_mps[:, t], s.leader_speed_mps[:, t + 1], self.params, s.ring,
            self.vehicles)
        power = self.battery_power_kw(v, applied)
        if self._drag_saving is not None:  # a follower's power in its predecessor's wake
            power = power + self._drag_saving.delta_kw(gap, v, applied)
        terms = reward_terms(gap, v, applied, power, self.target_gap_m, self.target_speed_mps,
                             self.params, self.weights)
        reward = combine_reward(terms, training=self.training, include_power=self.include_power)
        tracking = combine_reward(terms, training=False, include_power=False)
        new_collision = (gap < self.params.gap_min_m).any(axis=1)
        frozen = s.done | s.collided
        if new_collision.any() or frozen.any():
            new_collision &= ~frozen
            s.collision_step[new_collision] = t + 1
            s.collided |= new_collision
            keep = frozen[:, None]
            gap = np.where(keep, s.gap_m, gap)
            v = np.where(keep, s.speed_mps, v)
            a = np.where(keep, s.realised_accel_mps2, a)
            applied = np.where(keep, 0.0, applied)
            power = np.where(keep, 0.0, power)
            hit = s.collided & ~s.done
            reward[hit] = tracking[hit] = self.weights.collision
            reward[s.done] = tracking[s.done] = 0.0
            if self.collision_mode == "terminate":
                s.done |= s.collided
            else:
                s.done |= s.collided & ((t + 1) % 60 == 0)
        if self.vehicles is None and self.params.lag_s <= 0:
            command = a  # without lag the realised acceleration is the clipped command
        else:  # the bounds of each vehicle's class, or the run's
            bounds: PlatoonParams | VehicleArrays = self.vehicles or self.params
            command = np.clip(command_mps2, bounds.accel_min_mps2, bounds.accel_max_mps2)
            if frozen.any():
                command = np.where(frozen[:, None], s.command_mps2, command)
        s.gap_m, s.speed_mps, s.realised_accel_mps2, s.applied_accel_mps2 = gap, v, a, applied
        s.command_mps2 = command
        s.step = t + 1
        if s.ring:
            s.leader_speed_mps[:, t + 1] = v[:, -1]
        if s.step >= self.n_steps:
            s.done[:] = True
        obs = self.observation() if self.observe else None
        return StepResult(reward, s.done.copy(), s.collided.copy(), power, applied, obs, tracking)

    def battery_power_kw(self, speed_mps: np.ndarray, accel_mps2: np.ndarray) -> np.ndarray:
        """Battery power (kW) of every follower: the fitted polynomial inside its fit domain, or,
        in a heterogeneous string, each vehicle's class model (:mod:`envs.energy.classes`; the
        ``i3`` seats keep the polynomial)."""
        if self._string_power is not None:
            return self._string_power(speed_mps, accel_mps2)
        return self._i3_power_kw(speed_mps, accel_mps2)

    def _i3_power_kw(self, speed_mps: np.ndarray, accel_mps2: np.ndarray) -> np.ndarray:
        """Battery power (kW) by the fitted polynomial, evaluated inside its fit domain."""
        lo, hi = self.power_accel_range_mps2
        if accel_mps2.min() < lo or accel_mps2.max() > hi:
            return self.power(speed_mps, np.clip(accel_mps2, lo, hi))
        return self.power(speed_mps, accel_mps2)

    def score_recorded(
        self, gap_m: np.ndarray, speed_mps: np.ndarray, accel_mps2: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Power and rewards of a recorded (not simulated) platoon, by this env's own rules.

        Parameters
        ----------
        gap_m, speed_mps, accel_mps2 : (T, N)
            States after each step and the accelerations that led to them.

        Returns
        -------
        power_kw : (T, N)
        reward, tracking_reward : (T,)
            Sum over agents of the evaluation reward with and without the power term
            (-1000 per agent at a step with a gap below ``gap_min``).
        collided : (T,) bool
        """
        power = self.battery_power_kw(speed_mps, accel_mps2)
        terms = reward_terms(gap_m, speed_mps, accel_mps2, power, self.target_gap_m,
                             self.target_speed_mps, self.params, self.weights)
        reward = combine_reward(terms, training=False, include_power=True)
        tracking = combine_reward(terms, training=False, include_power=False)
        collided: np.ndarray = np.asarray((gap_m < self.params.gap_min_m).any(axis=1))
        n = gap_m.shape[1]
        reward_sum = np.where(collided, self.weights.collision * n, reward.sum(axis=1))
        tracking_sum = np.where(collided, self.weights.collision * n, tracking.sum(axis=1))
        return power, reward_sum, tracking_sum, collided

    def _require_state(self) -> PlatoonState:
        if self.state is None:
            raise RuntimeError("call reset() first")
        return self.state
