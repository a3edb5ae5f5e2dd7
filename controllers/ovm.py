"""The optimal velocity model as a controller: the human-driver baseline ``ovm``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.base import Controller, EpisodeContext
from envs.dynamics import ovm_command_mps2
from envs.platoon import PlatoonState
from infra.errors import ConfigError


@dataclass(frozen=True)
class OVMConfig:
    """OVM gains: ``u = alpha (V(gap) - v) + beta (v_pred - v)``; (0.5, 0.5) is MARL action 3."""

    alpha: float = 0.5
    beta: float = 0.5

    def __post_init__(self) -> None:
        if self.alpha < 0 or self.beta < 0:
            raise ConfigError("OVM gains alpha and beta must be >= 0")


class OVMController(Controller):
    """Every follower drives the OVM with the same gains (published ``ovm`` baseline)."""

    name = "ovm"
    family = "human"
    batch_invariant = True
    config_cls = OVMConfig
    config: OVMConfig

    def reset(self, ctx: EpisodeContext) -> None:
        self.params = ctx.params

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        return ovm_command_mps2(
            state.gap_m,
            state.speed_mps,
            state.pred_speed_mps,
            self.config.alpha,
            self.config.beta,
            self.params,
        )
