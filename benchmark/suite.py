"""The suite: controllers x scenarios x sizes x seeds (x V2V and lag settings), one run each.

A run is fully described by its :class:`RunKey`; :func:`execute_run` depends on nothing else, so
every executor (serial, process pool, Ray) gives the same numbers. The harness hands the
executors batches of runs that differ only in their seed (:func:`batch_keys`,
:func:`execute_batch`), which batch-invariant controllers step together. Scenarios come in built
(the command layer parses them once), and a key carries its scenario to the workers.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import traceback
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from controllers.registry import canonical_options, check_fits, controller_label, resolve
from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.scenarios import Scenario, as_scenario
from envs.simulators import simulator_label
from infra.errors import ConfigError
from infra.interrupt import raise_if_interrupted

#: Columns that identify a run (runs.csv is sorted by them).
KEY_COLUMNS: tuple[str, ...] = (
    "controller", "scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s", "seed",
)


@dataclass(frozen=True, order=True)
class RunKey:
    """Everything that defines one run. ``options`` is the controller's options as sorted JSON.

    ``scenario`` is the scenario's canonical label (the store's key); ``built`` is the scenario
    itself, as :func:`build_sweep` was given it (not part of the key, never stored). A key read
    back from a record has none, and :func:`execute_run` builds it from the label.
    """

    controller: str
    scenario: str
    n_vehicles: int
    comm_delay_s: float
    packet_loss: float
    lag_s: float
    seed: int
    name: str = ""
    options: str = "{}"
    built: Scenario | None = field(default=None, compare=False, repr=False)
    #: ``builtin`` or ``sumo`` (:mod:`envs.simulators`); a SUMO run's controller label carries
    #: it (``cacc@sumo``), so its id, row and file stem are its own, and a built-in run's key
    #: is what it always was
    simulator: str = "builtin"

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
    scenarios: Sequence[Scenario | str],
    vehicles: Sequence[int],
    seeds: Sequence[int],
    comm_delays_s: Sequence[float] = (0.0,),
    packet_losses: Sequence[float] = (0.0,),
    lags_s: Sequence[float] = (0.0,),
    simulator: str = "builtin",
) -> list[RunKey]:
    """All run keys of the product, sorted; validates controller names (unknown ones raise).
    ``simulator`` is the simulator of every run (:mod:`envs.simulators`).

    ``scenarios`` are built ones (:func:`envs.scenarios.parse_scenarios`); a label is built by
    :func:`envs.scenarios.as_scenario`. Each key names its scenario by the canonical label.
    """
    built = [as_scenario(sc) for sc in scenarios]
    keys = []
    for name, given in controllers:
        resolve(name)
        opts = canonical_options(name, given)
        label = simulator_label(controller_label(name, opts), simulator)
        opt_json = json.dumps(opts, sort_keys=True)
        for sc in built:
            for n in vehicles:
                for d in comm_delays_s:
                    for loss in packet_losses:
                        for lag in lags_s:
                            for seed in seeds:
                                keys.append(
                                    RunKey(label, sc.label, int(n), float(d), float(loss),
                                           float(lag), int(seed), name, opt_json, sc,
                                           simulator)
                                )
    return sorted(set(keys))


def _record(key: RunKey) -> dict:
    """A run's record before it runs: its key, family, status ``ok`` and provenance."""
    from benchmark.provenance import git_sha, version

    return {
        "id": key.id,
        **{f.name: getattr(key, f.name) for f in dataclasses.fields(key)
           if f.compare and f.name != "simulator"},
        **({"simulator": key.simulator} if key.simulator != "builtin" else {}),
        "family": resolve(key.name).family,
        "status": "ok",
        "error": "",
        "version": version(),
        "git_sha": git_sha(),
    }


def _scenario(key: RunKey) -> Scenario:
    """The key's scenario: the one it carries, else built from its label (a key read back)."""
    return key.built if key.built is not None else as_scenario(key.scenario)


def _setting(key: RunKey) -> tuple[PlatoonParams, ChannelConfig]:
    params = PlatoonParams(lag_s=key.lag_s)
    return params, ChannelConfig(key.comm_delay_s, key.packet_loss, params.dt_s)


def _finish(record: dict, traj: Any, scenario: Scenario, keep_trajectory: bool,
            controller: Any) -> dict:
    """``record`` with the policy ``controller`` acted with and the metrics of its run ``traj``
    on ``scenario``."""
    from benchmark.metrics import run_metrics

    record["policy_sha256"] = str(getattr(controller, "policy_sha256", ""))
    target_gap_m, target_speed_mps = scenario.target_gap_m, scenario.target_speed_mps
    spacing = controller.spacing_policy(target_gap_m, target_speed_mps)
    record.update(run_metrics(traj, target_gap_m, target_speed_mps, spacing))
    if spacing is not None:  # the controller's own gap target, for the figures
        record["spacing_standstill_m"] = float(spacing.standstill_m)
        record["spacing_time_gap_s"] = float(spacing.time_gap_s)
    if keep_trajectory:
        record["_trajectory"] = traj
    return record


def execute_run(key: RunKey, keep_trajectory: bool = False) -> dict:
    """Run one episode and return its record (status ``ok`` or ``failed`` with the error).

    Never raises for a controller's failure: the error is part of the record.
    """
    from benchmark.rollout import rollout
    from controllers.registry import make_controller

    record = _record(key)
    t0 = time.perf_counter()
    try:
        scenario = _scenario(key)
        controller = make_controller(key.name, **json.loads(key.options))
        record["deterministic"] = bool(getattr(controller, "deterministic", True))
        params, channel = _setting(key)
        traj = rollout(controller, scenario, key.n_vehicles, key.seed, params, channel,
                       key.simulator)
        _finish(record, traj, scenario, keep_trajectory, controller)
    except Exception as exc:  # a failing controller must not end the sweep
        raise_if_interrupted()  # an interrupted run is not a failed run: it is not stored
        record["status"] = "failed"
        record["error"] = f"{type(exc).__name__}: {exc}"
        record["traceback"] = traceback.format_exc(limit=8)
    record["wall_s"] = time.perf_counter() - t0
    return record


def execute_batch(keys: Sequence[RunKey], keep_trajectory: bool = False) -> list[dict]:
    """The records of runs that differ only in their seed (one batch of :func:`batch_keys`).

    A controller that is ``batch_invariant`` steps all the seeds together in one
    :func:`benchmark.rollout.rollout_batch`; each record then equals :func:`execute_run`'s
    except ``wall_s`` and the compute times, which are the batch's shares. Any other
    controller, or a batch that raises, runs seed by seed through :func:`execute_run`, so a
    failure is recorded for the run it belongs to.
    """
    from benchmark.rollout import rollout_batch
    from controllers.registry import make_controller

    if len({dataclasses.replace(k, seed=0) for k in keys}) > 1:
        raise ValueError("execute_batch: the keys of one batch may differ only in their seed")
    if len(keys) == 1:
        return [execute_run(keys[0], keep_trajectory)]
    head = keys[0]
    t0 = time.perf_counter()
    try:
        scenario = _scenario(head)
        controller = make_controller(head.name, **json.loads(head.options))
        if not getattr(controller, "batch_invariant", False):
            return [execute_run(k, keep_trajectory) for k in keys]
        params, channel = _setting(head)
        trajs = rollout_batch(controller, scenario, head.n_vehicles, [k.seed for k in keys],
                              params, channel, head.simulator)
    except Exception:  # run one by one: the failure belongs to a run, not to the batch
        raise_if_interrupted()
        return [execute_run(k, keep_trajectory) for k in keys]
    wall_s = (time.perf_counter() - t0) / len(keys)
    records = []
    for key, traj in zip(keys, trajs, strict=True):
        record = _record(key)
        record["deterministic"] = bool(getattr(controller, "deterministic", True))
        _finish(record, traj, scenario, keep_trajectory, controller)
        record["wall_s"] = wall_s
        records.append(record)
    return records


def current_policies(keys: Sequence[RunKey]) -> dict[RunKey, str]:
    """The ``policy_sha256`` each key's controller would act with now (its checkpoint as it
    is), loading each controller once per setting; a missing or damaged checkpoint raises its
    :class:`infra.errors.ConfigError`."""
    from controllers.registry import make_controller

    controllers: dict[tuple[str, str], Any] = {}
    found: dict[tuple[str, str, str, int, float], str] = {}
    out = {}
    for key in keys:
        setting = (key.name, key.options, key.scenario, key.n_vehicles, key.lag_s)
        if setting not in found:
            ctrl = controllers.get((key.name, key.options))
            if ctrl is None:
                ctrl = controllers[(key.name, key.options)] = make_controller(
                    key.name, **json.loads(key.options))
            check_fits(ctrl, _scenario(key), key.n_vehicles, _setting(key)[0])
            found[setting] = ctrl.policy_sha256
        out[key] = found[setting]
    return out


#: Most episodes one batch of the harness steps together.
MAX_BATCH = 50


def batch_keys(keys: Sequence[RunKey], workers: int = 1) -> list[list[RunKey]]:
    """Runs grouped into batches that :func:`execute_batch` runs. A batch-invariant
    controller's keys that differ only in their seed form batches (in key order, at most
    :data:`MAX_BATCH`, split so that every worker gets one when there are few); every other run
    is a batch of its own, so it is stored as soon as it finishes. The grouping never changes a
    result: a batch-invariant controller gives every episode the same run in any batch."""
    from controllers.registry import batch_invariant

    groups: dict[RunKey, list[RunKey]] = {}
    singles: list[list[RunKey]] = []
    for key in sorted(keys):
        if batch_invariant(key.name):
            groups.setdefault(dataclasses.replace(key, seed=0), []).append(key)
        else:
            singles.append([key])
    per_worker = math.ceil(sum(map(len, groups.values())) / max(1, workers))
    size = max(1, min(MAX_BATCH, per_worker))
    batches = [grp[i : i + size] for grp in groups.values() for i in range(0, len(grp), size)]
    return batches + singles


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


def seeds_from_set(seed_set: str, episodes: int | None) -> list[int]:
    """The first ``episodes`` seeds of a named seed set (``docs/seed-sets.md``).

    Parameters
    ----------
    seed_set : {"eval", "test", "validation"}
        ``eval``: the published evaluation seeds (:func:`seeds_from_episodes`, 10 when
        ``episodes`` is None); ``test``: :data:`envs.params.TEST_SEEDS`, the final word;
        ``validation``: :data:`envs.params.VALIDATION_SEEDS`, the seeds decisions are made on.
    episodes : int or None
        How many, from the start of the set; None: the whole test or validation set.

    Returns
    -------
    list of int
        The seeds, in the set's order.

    Raises
    ------
    ConfigError
        An unknown set, or ``episodes`` outside 1..the size of the test or validation set.
    """
    from envs.params import SEED_SETS

    if seed_set not in SEED_SETS:
        raise ConfigError(f"--seed-set must be one of {', '.join(SEED_SETS)}, got {seed_set!r}")
    if seed_set == "eval":
        return seeds_from_episodes(10 if episodes is None else episodes)
    seeds = SEED_SETS[seed_set]
    if episodes is None:
        return list(seeds)
    if not 1 <= episodes <= len(seeds):
        raise ConfigError(f"--episodes must lie in 1..{len(seeds)} with --seed-set {seed_set} "
                          f"(the {seed_set} set has {len(seeds)} seeds), got {episodes}")
    return list(seeds[:episodes])


def unique(items: Iterable[str]) -> list[str]:
    """Items in first-seen order without repeats."""
    return list(dict.fromkeys(items))
