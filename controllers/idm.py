"""The Intelligent Driver Model as a controller: the human-driver baseline ``idm``.

The automated seats are driven by the environment's own human drivers
(:class:`envs.humans.HumanDrivers`, every seat taken as human): the same acceleration
(:func:`envs.humans.idm_accel_mps2`), the same Gaussian noise (:class:`envs.humans.HumanNoise`, a
pure function of the episode seed, the step and the seat, so seat ``i`` gets the noise a human on
seat ``i`` would get) and the same reaction delay. So ``--controllers idm`` on ``ring-v1`` (one automated seat among 21
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
from envs.humans import (
    Arrangement,
    HumanDrivers,
    IDMParams,
    check_human_noise,
    check_reaction_delay,
)
from envs.platoon import PlatoonState
from infra.errors import ConfigError

_DEFAULT = IDMParams()
#: Ranges of the IDM parameters: wide around any human driver, narrow enough that the law's
#: powers and quotients stay finite at every speed and gap of an episode.
IDM_RANGES: dict[str, tuple[float, float]] = {
    "accel_max_mps2": (0.01, 10.0), "decel_comfort_mps2": (0.01, 10.0),
    "desired_speed_mps": (0.1, 100.0), "delta": (0.1, 10.0),
    "time_gap_s": (0.0, 10.0), "standstill_m": (0.0, 100.0),
}


@dataclass(frozen=True)
class IDMConfig:
    """Options of the ``idm`` controller (defaults: :class:`envs.humans.IDMParams`).

    Attributes
    ----------
    accel_max_mps2, decel_comfort_mps2, desired_speed_mps, time_gap_s, standstill_m, delta
        The IDM parameters a, b, v0, T, s0 and delta (ranges: :data:`IDM_RANGES`).
    noise_mps2 : float or None
        Standard deviation of the Gaussian acceleration noise (m/s^2) every step; None: the
        scenario's ``human_noise_mps2`` (what its human seats get).
    reaction_delay_s : float or None
        Reaction delay (s, whole steps of 0.1 s); None: the scenario's ``reaction_delay_s``.
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
        for key, (low, high) in IDM_RANGES.items():
            if not low <= getattr(self, key) <= high:
                raise ConfigError(f"idm option {key} must lie in [{low:g}, {high:g}], got "
                                  f"{getattr(self, key)}")
        if self.noise_mps2 is not None:
            check_human_noise(self.noise_mps2, "idm", "noise_mps2")
        if self.reaction_delay_s is not None:
            check_reaction_delay(self.reaction_delay_s, "idm")

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
    config_cls = IDMConfig
    config: IDMConfig

    def __init__(self, **options: object) -> None:
        super().__init__(**options)
        self._drivers: HumanDrivers | None = None

    def reset(self, ctx: EpisodeContext) -> None:
        given = ctx.arrangement
        cfg = self.config
        every_seat_human = Arrangement(
            (False,) * ctx.n_vehicles, "idm",
            given.reaction_delay_s if cfg.reaction_delay_s is None else cfg.reaction_delay_s,
            given.noise_std_mps2 if cfg.noise_mps2 is None else cfg.noise_mps2)
        self._drivers = HumanDrivers(every_seat_human, ctx.seeds, ctx.scenario.n_steps,
                                     ctx.params, ctx.ring, cfg.params)

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        assert self._drivers is not None, "reset() first"
        return self._drivers.commands(state.step, np.zeros_like(state.speed_mps), state.gap_m,
                                      state.speed_mps, state.leader_speed_now_mps)
