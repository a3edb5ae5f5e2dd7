"""The suite: controllers x scenarios x sizes x seeds (x V2V and lag settings), one run each.

A run is fully described by its :class:`RunKey`; :func:`execute_run` depends on nothing else, so
every executor (serial, process pool, Ray) gives the same numbers.
"""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass

from controllers.registry import canonical_options, controller_label, resolve
from envs.channel import ChannelConfig
from envs.errors import ConfigError
from envs.interrupt import raise_if_interrupted
from envs.params import PlatoonParams
from envs.scenarios import make_scenario

#: Columns that identify a run (runs.csv is sorted by them).
KEY_COLUMNS: tuple[str, ...] = (
    "controller", "scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s", "seed",
)


@dataclass(frozen=True, order=True)
class RunKey:
    """Everything that defines one run. ``options`` is the controller's options as sorted JSON."""

    controller: str
    scenario: str
    n_vehicles: int
    comm_delay_s: float
    packet_loss: float
    lag_s: float
    seed: int
    name: str = ""
    options: str = "{}"

    @property
    def id(self) -> str:
        """Stable identifier used as the store's primary key."""
        return (
            f"{self.controller}|{self.scenario}|n{self.n_vehicles}|d{self.comm_delay_s!r}"
            f"|l{self.packet_loss!r}|tau{self.lag_s!r}|s{self.seed}"
        )

    @property
    def file_stem(self) -> str:
        """``<controller>__<scenario>__n<N>__s<seed>`` (plus V2V settings when not default)."""
        stem = f"{self.controller}__{self.scenario}__n{self.n_vehicles}__s{self.seed}"
        if self.comm_delay_s or self.packet_loss or self.lag_s:
            stem += f"__d{self.comm_delay_s:g}_l{self.packet_loss:g}_tau{self.lag_s:g}"
        return stem.replace("/", "_")


def build_sweep(
    controllers: Sequence[tuple[str, dict[str, str]]],
    scenarios: Sequence[str],
    vehicles: Sequence[int],
    seeds: Sequence[int],
    comm_delays_s: Sequence[float] = (0.0,),
    packet_losses: Sequence[float] = (0.0,),
    lags_s: Sequence[float] = (0.0,),
) -> list[RunKey]:
    """All run keys of the product, sorted; validates names (unknown ones raise)."""
    for sc in scenarios:
        make_scenario(sc)
    keys = []
    for name, given in controllers:
        resolve(name)
        opts = canonical_options(name, given)
        label = controller_label(name, opts)
        opt_json = json.dumps(opts, sort_keys=True)
        for sc in scenarios:
            for n in vehicles:
                for d in comm_delays_s:
                    for loss in packet_losses:
                        for lag in lags_s:
                            for seed in seeds:
                                keys.append(
                                    RunKey(label, sc, int(n), float(d), float(loss), float(lag),
                                           int(seed), name, opt_json)
                                )
    return sorted(set(keys))


def execute_run(key: RunKey, keep_trajectory: bool = False) -> dict:
    """Run one episode and return its record (status ``ok`` or ``failed`` with the error).

    Never raises for a controller's failure: the error is part of the record.
    """
    from benchmark.metrics import run_metrics
    from benchmark.provenance import git_sha, version
    from benchmark.rollout import rollout
    from controllers.registry import make_controller

    spec = resolve(key.name)
    record: dict = {
        "id": key.id,
        **asdict(key),
        "family": spec.family,
        "status": "ok",
        "error": "",
        "version": version(),
        "git_sha": git_sha(),
    }
    t0 = time.perf_counter()
    try:
        scenario = make_scenario(key.scenario)
        controller = make_controller(key.name, **json.loads(key.options))
        record["deterministic"] = bool(getattr(controller, "deterministic", True))
        params = PlatoonParams(lag_s=key.lag_s)
        channel = ChannelConfig(key.comm_delay_s, key.packet_loss, params.dt_s)
        traj = rollout(controller, scenario, key.n_vehicles, key.seed, params, channel)
        record.update(run_metrics(traj, scenario.target_gap_m, scenario.target_speed_mps))
        if keep_trajectory:
            record["_trajectory"] = traj
    except Exception as exc:  # a failing controller must not end the sweep
        raise_if_interrupted()  # an interrupted run is not a failed run: it is not stored
        record["status"] = "failed"
        record["error"] = f"{type(exc).__name__}: {exc}"
        record["traceback"] = traceback.format_exc(limit=8)
    record["wall_s"] = time.perf_counter() - t0
    return record


#: The most episodes one setting may ask for (beyond the 50 published seeds, 2000 + 10 k).
MAX_EPISODES = 10_000
#: Seeds are drawn into 32-bit generators.
MAX_SEED = 2**31 - 1


def seeds_from_episodes(episodes: int) -> list[int]:
    """The first ``episodes`` published evaluation seeds (2000, 2010, ...)."""
    from envs.params import EVAL_SEEDS

    if not 1 <= episodes <= MAX_EPISODES:
        raise ConfigError(f"--episodes must lie in 1..{MAX_EPISODES}, got {episodes}")

    return list(EVAL_SEEDS[:episodes]) if episodes <= len(EVAL_SEEDS) else [
        2000 + 10 * k for k in range(episodes)
    ]


def unique(items: Iterable[str]) -> list[str]:
    """Items in first-seen order without repeats."""
    return list(dict.fromkeys(items))
