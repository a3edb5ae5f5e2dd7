"""A controller that raises mid-episode, for the harness's failure tests."""

from __future__ import annotations

import numpy as np

from controllers.base import Controller, EpisodeContext
from envs.platoon import PlatoonState


class FailingController(Controller):
    """Drives like a constant-speed car, then raises at step 5 of every episode."""

    name = "failing"
    family = "linear"

    def __init__(self, **options: object) -> None:
        super().__init__()

    def reset(self, ctx: EpisodeContext) -> None:
        self.n = ctx.n_vehicles

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        if state.step == 5:
            raise RuntimeError("deliberate failure at step 5")
        return np.zeros((1, self.n))
