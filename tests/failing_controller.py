"""A controller that raises mid-episode, for the harness's failure tests."""

from __future__ import annotations

import numpy as np

from controllers.base import Controller, EpisodeContext, Message
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


class DefectiveController(Controller):
    """Breaks the loop's contract at step 3: a command of the wrong shape (``defect="shape"``)
    or a NaN (``defect="nan"``); or declares a message and never sends it, reading the
    predecessor's speed from the state instead (``defect="silent_v2v"``: it would escape delay,
    loss and the bit count); or swallows the exception of a SIGINT it receives at step 3
    (``defect="swallow_sigint"``); or skips sending its declared message at step 3
    (``defect="skip_send"``)."""

    name = "defective"
    family = "linear"

    def __init__(self, defect: str = "shape") -> None:
        super().__init__()
        self.defect = defect

    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        sends = self.defect in ("silent_v2v", "skip_send")
        return (Message("speed", 1, "predecessor"),) if sends else ()

    def reset(self, ctx: EpisodeContext) -> None:
        self.b, self.n = ctx.batch_size, ctx.n_vehicles
        if self.defect == "skip_send":
            self.channel = ctx.channel("speed")

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        u = np.zeros((self.b, self.n))
        if self.defect == "skip_send" and state.step != 3:
            payload = np.zeros((self.b, self.n + 1))
            payload[:, 1:] = state.speed_mps
            self.channel.transmit(payload)
        if self.defect == "swallow_sigint" and state.step == 3:
            import os
            import signal

            try:  # as a solver library that turns the signal's exception into its own status
                os.kill(os.getpid(), signal.SIGINT)
            except BaseException:  # noqa: BLE001 - swallowing it is the defect under test
                pass
            return u
        if state.step == 3 and self.defect in ("shape", "nan"):
            return u[:, :1] if self.defect == "shape" else u + np.nan
        return u
