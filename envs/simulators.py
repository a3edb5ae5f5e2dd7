"""The simulators a run can use: the built-in one (:class:`envs.platoon.PlatoonEnv`) and SUMO.

One registry, one label rule: a run's simulator is a field of its key
(:class:`benchmark.suite.RunKey`) and a suffix of its controller's label (``cacc@sumo``), so
runs of the two simulators never share a store key, a ``runs.csv`` row or a leaderboard row; the
built-in simulator adds nothing, so every label and key of the built-in runs stays as it was.
"""

from __future__ import annotations

from typing import Any

from envs.params import PlatoonParams
from envs.scenarios import Scenario
from infra.errors import ConfigError

#: The simulators, the default first: ``sumo`` is SUMO with the settings that match the
#: built-in simulator (ballistic position update, :mod:`envs.sumo.env`), ``sumo-euler`` the same
#: with SUMO's default semi-implicit Euler position update (what that default changes is
#: measured in ``docs/sumo/report.md``).
SIMULATORS: tuple[str, ...] = ("builtin", "sumo", "sumo-euler")
DEFAULT_SIMULATOR = "builtin"
#: How a label names a simulator other than the built-in one: ``cacc@sumo``.
SIMULATOR_SEPARATOR = "@"


def check_simulator(name: str) -> str:
    """``name`` if it is a simulator this install can run, else a :class:`ConfigError` (an
    unknown name lists the known ones; ``sumo`` without the ``sumo`` extra gives the install
    command, :func:`envs.sumo.require_sumo`)."""
    if name not in SIMULATORS:
        raise ConfigError(f"--simulator must be one of {', '.join(SIMULATORS)}, got {name!r}")
    if name != DEFAULT_SIMULATOR:
        from envs.sumo import require_sumo

        require_sumo()
    return name


def simulator_label(label: str, simulator: str) -> str:
    """A run's controller label in ``simulator``: ``label`` itself in the built-in simulator,
    ``label@sumo`` in SUMO."""
    return label if simulator == DEFAULT_SIMULATOR else f"{label}{SIMULATOR_SEPARATOR}{simulator}"


def make_env(simulator: str, scenario: Scenario, n_vehicles: int, params: PlatoonParams,
             **kwargs: Any) -> Any:
    """The env of ``simulator`` (the built-in :class:`envs.platoon.PlatoonEnv`, or
    :class:`envs.sumo.env.SumoPlatoonEnv`, which subclasses it); ``kwargs`` go to its
    constructor (``observe``)."""
    if simulator == DEFAULT_SIMULATOR:
        from envs.platoon import PlatoonEnv

        return PlatoonEnv(scenario, n_vehicles, params, **kwargs)
    check_simulator(simulator)
    from envs.sumo.env import SumoPlatoonEnv

    integration = "euler" if simulator == "sumo-euler" else "ballistic"
    return SumoPlatoonEnv(scenario, n_vehicles, params, integration=integration, **kwargs)


def check_runs_in(controller: Any, simulator: str) -> None:
    """Refuse (:class:`ConfigError`) a controller that is a model of another simulator (its
    ``runs_in`` attribute: ``plexe:ploeg`` runs in SUMO only), and a recorded platoon
    (``openacc-real``) in any simulator but the built-in one, which scores it as recorded."""
    runs_in = getattr(controller, "runs_in", None)
    if runs_in is not None and runs_in != simulator.split("-")[0]:
        raise ConfigError(f"{controller.name} is a model of {runs_in} and runs in {runs_in} "
                          f"only: add --simulator {runs_in}")
    if simulator != DEFAULT_SIMULATOR and getattr(controller, "recorded", None) is not None:
        raise ConfigError(f"{controller.name} is a recorded platoon that no simulator drives, so "
                          f"its rows would be labelled as {simulator}'s; run it without "
                          f"--simulator {simulator}")


def check_setting(simulator: str, scenario: Scenario, n_vehicles: int,
                  params: PlatoonParams) -> None:
    """Refuse (:class:`ConfigError`) a scenario setting ``simulator`` does not simulate (the
    built-in simulator runs every one; SUMO's limits: :func:`envs.sumo.env.check_sumo_setting`)."""
    if simulator == DEFAULT_SIMULATOR:
        return
    check_simulator(simulator)
    from envs.sumo.env import check_sumo_setting

    check_sumo_setting(scenario, n_vehicles, params)
