"""The Intelligent Driver Model as a controller: the human-driver baseline ``idm``.

The automated seats drive exactly as the environment's IDM humans do
(:class:`envs.humans.HumanDrivers`): the same acceleration (:func:`envs.humans.idm_accel_mps2`),
the same Gaussian noise (:class:`envs.humans.HumanNoise`, a pure function of the episode
seed, the step and the seat, so seat ``i`` gets the noise a human on seat ``i`` would get) and the
same reaction delay (act on what was seen ``delay`` steps ago; before that many steps have passed,
on the first observation). So ``--controllers idm`` on ``ring-v1`` (one automated seat among 21
IDM humans) *is* the all-human ring ``ring-v1:cavs=0``, to the last bit, for the same seeds: the
baseline the wave dampers (:mod:`controllers.wave_dampers`) are measured against.

The IDM (Treiber, Hennecke, Helbing 2000) with Flow's ``IDMController`` parameters::

    a_cmd = a [1 - (v / v0)^delta - (s* / s)^2] + noise,
    s*    = s0 + v T + v (v - v_pred) / (2 sqrt(a b)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.base import Controller, EpisodeContext
from controllers.registry import build_config
from envs.humans import (
    MAX_HUMAN_NOISE_MPS2,
    MAX_REACTION_DELAY_S,
    HumanNoise,
    IDMParams,
    idm_accel_mps2,
)
from envs.platoon import PlatoonState
from infra.errors import ConfigError

_DEFAULT = IDMParams()


@dataclass(frozen=True)
class IDMConfig:
    """Options of the ``idm`` controller (defaults: :class:`envs.humans.IDMParams`).

    Attributes
    ----------
    accel_max_mps2, decel_comfort_mps2, desired_speed_mps, time_gap_s, standstill_m, delta
        The IDM parameters a, b, v0, T, s0 and delta.
    noise_mps2 : float or None
        Standard deviation of the Gaussian acceleration noise (m/s^2) every step; None: the
        scenario's ``human_noise_mps2`` (what its human seats get).
    reaction_delay_s : float or None
        Reaction delay (s, rounded to whole steps); None: the scenario's ``reaction_delay_s``.
    """

    accel_max_mps2: float = _DEFAULT.accel_max_mps2
    decel_comfort_mps2: float = _DEFAULT.decel_comfort_mps2
    desired_speed_mps: float = _DEFAULT.desired_speed_mps
    time_gap_s: float = _DEFAULT.time_gap_s
    standstill_m: float = _DEFAULT.standstill_m
    delta: float = _DEFAULT.delta
    noise_mps2: float | None = None
    reaction_delay_s: float | None = None

    def __post_init__(self) -> None:
        for key in ("accel_max_mps2", "decel_comfort_mps2", "desired_speed_mps", "delta"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"idm option {key} must be > 0, got {getattr(self, key)}")
        for key in ("time_gap_s", "standstill_m"):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"idm option {key} must be >= 0, got {getattr(self, key)}")
        if self.noise_mps2 is not None and not 0 <= self.noise_mps2 <= MAX_HUMAN_NOISE_MPS2:
            raise ConfigError(f"idm option noise_mps2 must lie in [0, {MAX_HUMAN_NOISE_MPS2}] "
                              f"m/s^2, got {self.noise_mps2}")
        if (self.reaction_delay_s is not None
                and not 0 <= self.reaction_delay_s <= MAX_REACTION_DELAY_S):
            raise ConfigError(f"idm option reaction_delay_s must lie in [0, "
                              f"{MAX_REACTION_DELAY_S}] s, got {self.reaction_delay_s}")

    @property
    def params(self) -> IDMParams:
        """The IDM parameters as :class:`envs.humans.IDMParams`."""
        return IDMParams(self.accel_max_mps2, self.decel_comfort_mps2, self.desired_speed_mps,
                         self.time_gap_s, self.standstill_m, self.delta)


class IDMController(Controller):
    """Every automated seat drives the IDM with noise and reaction delay, as a human seat does.

    Own sensors only (gap, own speed, predecessor's speed); sends nothing over V2V.
    """

    name = "idm"
    family = "human"
    deterministic = True  # the noise is a pure function of (episode seed, step, seat)
    batch_invariant = True
    drives_mixed = True
    needs_leader = False

    config_cls = IDMConfig

    def __init__(self, **options: object) -> None:
        super().__init__()
        self.config: IDMConfig = build_config(self.config_cls, options, "idm")
        self.options = dict(options)
        self.idm = self.config.params
        self.delay_steps = 0
        self.noise: HumanNoise | None = None
        self._seats = np.zeros(0, dtype=np.int64)
        self._history: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def reset(self, ctx: EpisodeContext) -> None:
        arrangement = ctx.arrangement
        std = (arrangement.noise_std_mps2 if self.config.noise_mps2 is None
               else self.config.noise_mps2)
        delay_s = (arrangement.reaction_delay_s if self.config.reaction_delay_s is None
                   else self.config.reaction_delay_s)
        # the rule of envs.humans.Arrangement.delay_steps
        self.delay_steps = int(round(delay_s / ctx.params.dt_s + 1e-9))
        n_steps = ctx.scenario.n_steps
        # the very draw HumanDrivers makes, so seat i gets a human's noise of seat i
        self.noise = HumanNoise(ctx.seeds, ctx.n_vehicles, n_steps, std) if std > 0 else None
        self._seats = np.arange(ctx.n_vehicles)
        self._history = []

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        # what HumanDrivers.commands does, for every seat (the env keeps the automated ones)
        seen = (state.gap_m.copy(), state.speed_mps.copy(), state.pred_speed_mps.copy())
        self._history.append(seen)
        if len(self._history) > self.delay_steps + 1:
            self._history.pop(0)
        gap, speed, pred_speed = self._history[0]  # seen `delay` steps ago (the start, before)
        u = idm_accel_mps2(gap, speed, pred_speed, self.idm)
        if self.noise is not None:
            u += self.noise.at(state.step, self._seats)
        return np.asarray(u, dtype=np.float64)
