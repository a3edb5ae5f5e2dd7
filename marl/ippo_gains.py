"""``ippo-gains``: IPPO that schedules Ploeg's CACC along a segment of gains certified string
stable.

The policy does not command an acceleration. Every step each follower's shared actor picks a
point ``s`` in [0, 1] of a segment of CACC settings, from ``(kp, kd, h)`` = ``(kp_start,
kd_start, time_gap_start_s)`` to ``(kp_end, kd_end, time_gap_end_s)``, and the command is
Ploeg's CACC with those gains and time gap (:func:`envs.accel_mode.cacc_from_observation`, given
the state's unclipped relative speed and last command, as the ``cacc-exact`` prior: with a
constant ``s`` it is the registered ``cacc`` controller with those options). So the policy
chooses *which* string-stable law acts, never a command outside that family.

Why the segment keeps string stability: follower ``i``'s command filters its own spacing error
and its predecessor's command, so the ratio of consecutive accelerations ``Gamma_i`` depends on
follower ``i``'s own ``(kp, kd, h)`` only (the actuator lag is the same for all); every point of
the default segment has ``||Gamma||_inf <= 1`` for V2V delays of 0, 0.1 and 0.2 s and actuator
lags of 0 and 0.1 s, by the continuous loop and by the simulator's exact discrete loop
(:mod:`analysis.stability`). This layer may not import that analysis, so the segment is given as
config numbers: :mod:`studies.string_stability` certifies the segment every shipped checkpoint
records, and ``tests/test_marl/test_ippo_gains.py`` the defaults. The certificate is for frozen gains;
under a small disturbance around the equilibrium the spacing error is small, and a gain that
moves with the state changes the command only at second order, so a small-amplitude sweep
measures the frozen law the policy picks there (measured: ``docs/string-stability/report.md``).
A schedule that moves fast under large errors is not covered by the certificate.

The default segment was chosen on the validation seeds alone (``cacc-bench string-stability``
records the grid it was read from): on ``catchup-v1`` the stiff end, on ``slowdown-v1`` the
soft end scores above ``cacc``'s defaults.

The actor is :class:`marl.ppo_nets.SharedActor` whose squashed output is the segment's
coordinate instead of a command (:class:`GainActor`); training steps an env that turns the
coordinate into CACC's command (:class:`ScheduledEnv`); acting does the same through the policy
controller (:class:`GainActing`). Everything else is ``ippo``'s trainer.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch

from envs import accel_mode
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv, PlatoonState, StepResult
from envs.scenarios import Scenario
from infra.errors import ConfigError
from marl.acting import SharedActing, load_weights
from marl.ppo import PPOTrainer, World
from marl.ppo_nets import PPOConfig, SharedActor

#: A segment of CACC settings: ``((kp, kd, h) at s = 0, (kp, kd, h) at s = 1)``.
Segment = tuple[tuple[float, float, float], tuple[float, float, float]]


@dataclass(frozen=True)
class GainScheduleConfig(PPOConfig):
    """:class:`marl.ppo_nets.PPOConfig` plus the segment the policy schedules along.

    Attributes
    ----------
    kp_start, kd_start, time_gap_start_s : float
        Ploeg's gains (1/s^2, 1/s) and time gap (s) at ``s = 0`` (the soft end).
    kp_end, kd_end, time_gap_end_s : float
        The same at ``s = 1`` (the stiff end). Every point between is linear in ``s``.
    """

    algo: str = "ippo-gains"
    kp_start: float = 0.2
    kd_start: float = 2.0
    time_gap_start_s: float = 0.5
    kp_end: float = 0.6
    kd_end: float = 3.0
    time_gap_end_s: float = 0.8

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.algo != "ippo-gains":
            raise ConfigError(f"this config is ippo-gains'; algo must be ippo-gains, got "
                              f"{self.algo!r}")
        if self.action_mode != "accel" or self.prior:
            raise ConfigError("ippo-gains schedules CACC's acceleration command: action_mode "
                              "must be accel and prior empty")
        for name in ("kp_start", "kd_start", "time_gap_start_s", "kp_end", "kd_end",
                     "time_gap_end_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 < value <= 100):
                raise ConfigError(f"{name} must lie in (0, 100], got {value}")

    @property
    def segment(self) -> Segment:
        """The two ends of the schedule, ``(kp, kd, h)`` each."""
        return ((self.kp_start, self.kd_start, self.time_gap_start_s),
                (self.kp_end, self.kd_end, self.time_gap_end_s))


def gains_at(s: np.ndarray, segment: Segment) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(kp, kd, h)`` at the coordinates ``s`` (any shape, in [0, 1]) of ``segment``."""
    s = np.asarray(s, dtype=np.float64)
    start, end = segment
    kp, kd, h = (a + s * (b - a) for a, b in zip(start, end, strict=True))
    return kp, kd, h


def scheduled_command(s: np.ndarray, obs: np.ndarray, state: PlatoonState,
                      targets: tuple[float, float], params: PlatoonParams,
                      segment: Segment) -> np.ndarray:
    """Ploeg's CACC command ``(B, N)`` with each follower's gains and time gap at its
    coordinate ``s (B, N)`` of ``segment``, computed from the ``accel`` observation ``obs (B, N,
    12)`` with the state's unclipped relative speed and last command (``targets``: the
    scenario's gap and speed). The one law of training (:class:`ScheduledEnv`) and acting
    (:class:`GainActing`)."""
    kp, kd, h = gains_at(s, segment)
    # numpy broadcasts the per-follower gains through the law written for scalars
    return accel_mode.cacc_from_observation(
        obs, targets[0], targets[1], params, time_gap_s=cast(float, h), kp=cast(float, kp),
        kd=cast(float, kd), relative_speed_mps=state.pred_speed_mps - state.speed_mps,
        last_command_mps2=state.command_mps2)


class GainActor(SharedActor):
    """The shared actor whose squashed output is the segment's coordinate
    ``s = (1 + tanh z) / 2`` (its :meth:`command`), with the segment it schedules along."""

    def __init__(self, config: GainScheduleConfig, params: PlatoonParams = PlatoonParams(),
                 n_agents: int = 0) -> None:
        super().__init__(config, params, n_agents)
        self.segment = config.segment

    def command(self, z: torch.Tensor) -> torch.Tensor:
        """The coordinate ``s`` in [0, 1] of the pre-squash sample ``z``."""
        return 0.5 * (1.0 + torch.tanh(z))


class ScheduledEnv(PlatoonEnv):
    """The training env of ``ippo-gains``: :meth:`step` takes each follower's coordinate ``s``
    and applies the scheduled CACC command (:func:`scheduled_command`), which is also the V2V
    message the follower behind receives."""

    segment: Segment = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))

    def step(self, command_mps2: np.ndarray) -> StepResult:
        """One step with the coordinates ``command_mps2 (B, N)`` (in [0, 1], named as
        :meth:`PlatoonEnv.step`'s argument the trainer passes)."""
        s = self._require_state()
        targets = (self.target_gap_m, self.target_speed_mps)
        return super().step(scheduled_command(np.clip(command_mps2, 0.0, 1.0),
                                              self.observation(), s, targets, self.params,
                                              self.segment))


class GainScheduleTrainer(PPOTrainer):
    """``ippo``'s trainer with the :class:`GainActor` and :class:`ScheduledEnv`."""

    cfg: GainScheduleConfig
    actor_cls, env_cls = GainActor, ScheduledEnv

    def make_world(self, sc: Scenario, n: int, delay_s: float, loss: float) -> World:
        """``ippo``'s world, its :class:`ScheduledEnv` along the config's segment."""
        world = super().make_world(sc, n, delay_s, loss)
        cast(ScheduledEnv, world.env).segment = self.cfg.segment
        return world


def load_gain_actor(data: dict[str, Any]) -> GainActor:
    """The actor of a loaded ``ippo-gains`` checkpoint dict (float32 weights, the segment its
    config records; :func:`marl.acting.load_weights`)."""
    fields = {f.name for f in dataclasses.fields(GainScheduleConfig)}
    return load_weights(data, lambda saved: GainActor(
        GainScheduleConfig(**{k: v for k, v in saved.items() if k in fields})))


class GainActing(SharedActing):
    """Acting with an ``ippo-gains`` actor: the observation and V2V of the shared learners'
    ``accel`` mode, the command Ploeg's CACC at the coordinate the actor picks."""

    net: GainActor

    @classmethod
    def load(cls, algo: str, data: dict[str, Any]) -> GainActing:
        return cls(algo, load_gain_actor(data))

    def commands(self, action: torch.Tensor, state: PlatoonState, obs: np.ndarray) -> np.ndarray:
        """Ploeg's CACC at the coordinates ``s`` of the pre-squash samples ``action``
        (:func:`scheduled_command`)."""
        s = self.net.command(action).numpy().astype(np.float64)
        return scheduled_command(s, obs, state, self.targets, self.params, self.net.segment)


#: The trainer of ``ippo-gains`` (its registry entry names this module).
TRAINER = GainScheduleTrainer
