"""The real ACC followers of an OpenACC window as a leaderboard row (``openacc-real``).

Not a control law: the recorded followers of the window (their speeds, gaps and accelerations,
from the JRC data) are scored by the same metrics, reward and power model as every simulated
controller, so the leaderboard of an ``openacc-*`` scenario shows how the commercial ACC cars did
(paper Table III). It applies to the OpenACC scenarios only, with at most as many followers as
the window holds (S and L: 5, M: 4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.base import Controller, EpisodeContext
from envs.params import PlatoonParams
from envs.platoon import PlatoonState
from envs.scenarios import Scenario, check_vehicles
from infra.errors import ConfigError


@dataclass(frozen=True)
class RealACCConfig:
    """No options: the record is what it is."""


class RealACCRecord(Controller):
    """Replays nothing: hands the recorded followers of the window to the harness."""

    name = "openacc-real"
    family = "data"
    drives_mixed = False  # recorded cars: the real platoon, as it drove
    needs_leader = True
    config_cls = RealACCConfig  # no options: any given one is refused

    def preflight(self, scenario: Scenario, n_vehicles: int, params: object = None) -> None:
        """Check that the scenario is an OpenACC replay that holds ``n_vehicles`` followers."""
        self._window(scenario, n_vehicles)

    @staticmethod
    def _window(scenario: Scenario, n_vehicles: int) -> object:
        from envs.openacc import load_window

        check_vehicles(n_vehicles)
        if "window" not in scenario.options:
            raise ConfigError(
                f"openacc-real is the recorded ACC platoon of an OpenACC window; scenario "
                f"{scenario.id} has none (use openacc-s-v1, openacc-m-v1 or openacc-l-v1)"
            )
        window = load_window(scenario.options["window"])
        if n_vehicles > window.n_followers:
            raise ConfigError(
                f"the OpenACC window of {scenario.id} holds {window.n_followers} followers; "
                f"--vehicles {n_vehicles} asks for more"
            )
        return window

    def recorded(self, scenario: Scenario, n_vehicles: int) -> dict[str, np.ndarray]:
        """The recorded platoon over the scenario's steps.

        Returns
        -------
        dict
            ``gap_m``, ``speed_mps``, ``accel_mps2`` (T+1, N) and ``leader_speed_mps`` (T+1,);
            accelerations are backward differences of the recorded speeds (row 0: 0), the same
            convention as the simulator's applied acceleration.
        """
        window = self._window(scenario, n_vehicles)
        t1 = scenario.n_steps + 1
        speed = np.asarray(window.follower_speed_mps[:t1, :n_vehicles], dtype=np.float64)  # type: ignore[attr-defined]
        accel = np.zeros_like(speed)
        accel[1:] = np.diff(speed, axis=0) / PlatoonParams().dt_s
        return {
            "gap_m": np.asarray(window.follower_gap_m[:t1, :n_vehicles], dtype=np.float64),  # type: ignore[attr-defined]
            "speed_mps": speed,
            "accel_mps2": accel,
            "leader_speed_mps": np.asarray(window.leader_speed_mps[:t1], dtype=np.float64),  # type: ignore[attr-defined]
        }

    def reset(self, ctx: EpisodeContext) -> None:
        self.preflight(ctx.scenario, ctx.n_vehicles)

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        raise RuntimeError("openacc-real is a record, not a control law: the harness scores it")
