"""``check_controller``: the contract every registered controller must meet.

Contributors run it on their additions; the test suite runs it on every available registered
controller (registering one adds it to the parametrised tests).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from benchmark.rollout import rollout
from controllers.base import FAMILIES, Controller, EpisodeContext
from controllers.registry import make_controller, resolve
from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.scenarios import Scenario, as_scenario
from infra.errors import ControllerContractError


def _episode(ctrl: Controller, scenario: Scenario, n: int, seed: int, steps: int,
             channel: ChannelConfig) -> tuple[np.ndarray, int]:
    """The commands and V2V bits of the first ``steps`` steps of one episode, run by the
    harness's own loop (which refuses commands of the wrong shape or not finite)."""
    sc = dataclasses.replace(scenario, n_steps=min(steps, scenario.n_steps))
    try:
        # a model that drives inside a simulator (plexe:ploeg) is checked in it
        traj = rollout(ctrl, sc, n, seed, PlatoonParams(), channel,
                       getattr(ctrl, "runs_in", None) or "builtin")
    except ControllerContractError as exc:
        raise AssertionError(str(exc)) from None
    return traj.command_mps2, traj.bits_sent


def check_controller(name: str, scenario_id: str | Scenario = "catchup-v1", n_vehicles: int = 8,
                     steps: int = 40, **options: object) -> None:
    """Raise ``AssertionError`` if a registered controller breaks the harness's contract.

    Checks: class attributes (family, flags); ``reset``/``act`` give ``(B, N)`` finite commands;
    every controller gives identical commands on a rerun of the same episode (a stochastic one
    draws from streams of the episode seed), and different episodes are allowed to differ; the
    V2V bits it reports come from the channels of its declared messages and are zero when the
    registry says it sends nothing; with its default options it declares messages exactly when
    the registry's words say it sends some; ``solver_failures`` is a non-negative integer.
    """
    spec = resolve(name)
    ctrl = make_controller(name, **options)
    if spec.family not in FAMILIES or ctrl.family != spec.family:
        raise AssertionError(f"{name}: family {ctrl.family!r} does not match the registry")
    scenario = as_scenario(scenario_id)
    channel = ChannelConfig(0.1, 0.1)
    u1, bits1 = _episode(ctrl, scenario, n_vehicles, 2000, steps, channel)
    u2, bits2 = _episode(make_controller(name, **options), scenario, n_vehicles, 2000, steps,
                         channel)
    if not np.array_equal(u1, u2):
        raise AssertionError(
            f"{name}: a rerun of the same episode gave other commands; draw random numbers from "
            "streams of the episode seed (envs.streams.episode_uniforms)"
        )
    if bits1 != bits2:
        raise AssertionError(f"{name}: V2V bits differ between identical episodes")
    if spec.v2v.startswith("none") and bits1 != 0:
        raise AssertionError(f"{name}: declares no V2V but sent {bits1} bits")
    ctx = EpisodeContext(scenario, n_vehicles, np.array([2000]))
    declared = ctrl.messages(ctx)
    if not options and bool(declared) == spec.v2v.startswith("none"):
        raise AssertionError(f"{name}: the registry says its V2V is {spec.v2v!r}, but it "
                             f"declares {[m.name for m in declared] or 'no messages'}")
    failures = getattr(ctrl, "solver_failures", 0)
    if not isinstance(failures, int) or failures < 0:
        raise AssertionError(f"{name}: solver_failures must be a non-negative int")
