"""``cacc-bench train``: train any learner of :data:`marl.learners.LEARNERS` on scenarios and
store the policies.

Each job is a :class:`marl.training.TrainingKey` (scenario and config built once, here). Writes
``<out>/<algo>__<scenario>__n<N>__s<seed>.pt`` (the snapshot selected on the validation seeds),
``.final.pt`` (the final weights; the paper's learners), ``.curve.csv``
(:data:`marl.checkpoint.CURVE_COLUMNS`) and ``.log`` (evaluations, bits communicated) per run.
Several seeds of one of the paper's algorithms and scenario train in one process as a population
(``--population``): one stacked network, each run exactly as it would alone; a shared-policy
learner's run is a population of one. Shows progress on a terminal and stays quiet otherwise.

A run's files are written when it finishes, each atomically and together
(:mod:`infra.atomic`): an interrupted or failed run leaves the files of an earlier run byte for
byte as they were. Meanwhile every run keeps a resumable snapshot beside them
(``<stem>.snapshot.pt``, :class:`marl.checkpoint.Snapshots`, every
:data:`marl.checkpoint.SNAPSHOT_EVERY_S` seconds), removed when it finishes: ``--resume``
continues an interrupted run from it, to the weights an uninterrupted run gives. A folder
holding finished runs of the command, or snapshots, is refused unless ``--resume`` (skip the
finished, continue the interrupted) or ``--overwrite`` (train them again) says what to do
(:func:`check_finished`, :func:`check_snapshots`). The command prints where it writes when it
starts, and holds ``--out``'s folder lock (:mod:`benchmark.folder_lock`).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from infra.errors import ConfigError, UnknownNameError
from infra.limits import step_count

if TYPE_CHECKING:
    from marl.training import TrainingKey

#: Default output, beside ``run``'s ``results/run``; never the shipped ``controllers/checkpoints``
#: (what ``cacc-bench run --controllers NAME`` evaluates): the command train prints at its end
#: runs the policies from here (``NAME:checkpoint_dir=...``).
DEFAULT_OUT = "results/checkpoints"


def _parser() -> argparse.ArgumentParser:
    from marl.learners import LEARNERS

    p = argparse.ArgumentParser(
        prog="cacc-bench train",
        description="Train a MARL algorithm (one agent per follower) on a scenario.",
    )
    p.add_argument("--algo", required=True,
                   help=f"one of: {', '.join(LEARNERS)} (the paper's seven, then the "
                        "shared-policy learners of marl/ppo.py and marl/distill.py); a comma "
                        "list, or all (the paper's seven)")
    p.add_argument("--scenario", required=True,
                   help="scenario id, e.g. catchup-v1, or a comma list")
    p.add_argument("--steps", type=step_count, default=600_000,
                   help="environment steps (default 6e5; distill stops at its last round "
                        "(--set rounds, episodes_per_round) or these, whichever comes first)")
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    p.add_argument("--seeds", default=None,
                   help="comma list of training seeds, run through the harness executors "
                        "(overrides --seed)")
    p.add_argument("--executor", choices=("serial", "process", "ray"), default="serial",
                   help="how several populations run (default serial)")
    add_population_argument(p)
    p.add_argument("--workers", type=int, default=2, help="processes or Ray CPUs (default 2)")
    p.add_argument("--ray-address", default=None, help="attach to this Ray cluster")
    add_device_argument(p)
    add_arithmetic_argument(p, "native")
    p.add_argument("--vehicles", type=int, default=8, help="followers N (default 8)")
    p.add_argument("--out", default=DEFAULT_OUT,
                   help="output folder (default: %(default)s; train prints the `cacc-bench run` "
                        "command that evaluates what it wrote)")
    p.add_argument(
        "--episodes-parallel", type=int, default=None,
        help="B episodes stepped together (a shared-policy learner's n_envs)"
    )
    p.add_argument(
        "--resume", action="store_true",
        help="skip runs that finished in --out (their .final.pt, a shared-policy learner's "
             ".pt, exists with the same config); an interrupted run continues from its "
             "snapshot (.snapshot.pt), to the weights an uninterrupted run gives",
    )
    p.add_argument(
        "--overwrite", action="store_true",
        help="train again runs that finished in --out, replacing their files when each "
             "finishes, and interrupted ones from the start (without it or --resume, a folder "
             "holding them is refused)",
    )
    p.add_argument(
        "--tuned", action="store_true",
        help="start from the config `cacc-bench tune` chose for this algorithm and scenario "
             "(the shipped marl/tuned_configs.json); --set applies on top",
    )
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
        help="set a config field of the algorithm (repeatable), e.g. --set gamma=0.995 "
             "--set advantage_norm=true; the checkpoint records the whole config",
    )
    return p


class _Bar:
    """A one-line tqdm bar of training steps on a terminal (nothing otherwise), with the last
    training and validation rewards."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.last_eval = float("nan")
        self._bar: Any = None
        self._steps = 0

    def __call__(self, steps: int, total: int, row: dict[str, float]) -> None:
        value = row.get("eval_reward_sampled", float("nan"))
        if value == value:  # not NaN
            self.last_eval = value
        if not self.enabled:
            return
        if self._bar is None:
            from tqdm import tqdm

            from benchmark.progress import WIDTH

            self._bar = tqdm(total=total, unit=" steps", unit_scale=True, file=sys.stderr,
                             ncols=WIDTH, mininterval=0.2)
        self._bar.set_postfix_str(f"train {row['train_reward']:.0f} val {self.last_eval:.0f}",
                                  refresh=False)
        self._bar.update(max(min(steps, total) - self._steps, 0))
        self._steps = min(steps, total)
        if steps >= total:
            self._bar.close()


def model_expert(name: str) -> Callable[[Any], Callable[[Any], Any]]:
    """A registered model-based controller as :func:`marl.distill.distill`'s expert: for a
    reset env, its commands for the env's states (its V2V through its own ideal channels)."""
    from controllers.base import EpisodeContext, reset_controller
    from controllers.registry import check_fits, make_controller

    def make(env: Any) -> Callable[[Any], Any]:
        ctrl = make_controller(name)
        ctx = EpisodeContext(env.scenario, env.n_vehicles, env.seeds, env.params)
        check_fits(ctrl, env.scenario, env.n_vehicles, env.params)
        reset_controller(ctrl, ctx)
        return lambda state: ctrl.act(state, None)

    return make


def _evaluator(key: TrainingKey) -> Callable[[Any, str], dict[str, float]]:
    """The validation seeds' scores of a policy of ``key``'s learner, ``(net, mode) -> dict``
    (:func:`benchmark.policy_eval.validation_evaluator`), V2V as the learner trains with."""
    from benchmark.policy_eval import validation_evaluator
    from envs.channel import ChannelConfig
    from envs.params import VALIDATION_SEEDS

    channel = ChannelConfig() if key.family == "a2c" else (  # a distilled actor: its own
        key.config.actor_config() if key.family == "distill" else key.config).validation_channel
    seeds = VALIDATION_SEEDS[: key.validation_episodes or len(VALIDATION_SEEDS)]
    roads = key.config.validation_roads(key.scenario) if key.family == "ppo" else key.scenario
    return validation_evaluator(key.algo, roads, key.n_vehicles, seeds, channel)


def train_job(key: TrainingKey) -> dict[str, Any]:
    """Train ``key``'s runs (its seeds) as one population in this process (top level, so
    process and Ray executors can run it). Returns ``{"runs": [...]}``, one summary per run."""
    import contextlib

    import torch

    from infra.atomic import StagedFiles, temporary_beside
    from marl import arithmetic

    arithmetic.require(key.arithmetic)  # before this process's first product
    torch.set_num_threads(1)
    seeds = list(key.seeds)
    key.out.mkdir(parents=True, exist_ok=True)
    log_paths = [key.out / f"{key.stem(s)}.log" for s in seeds]
    # each log grows in a hidden temporary file beside it (``.<stem>.log.*.tmp``, to follow
    # with tail -f) and replaces the .log only once its run's files are written: an interrupted
    # or failed run leaves an earlier run's log as it was
    tmp_logs = [temporary_beside(p) for p in log_paths]
    done = [False] * len(seeds)
    echo = key.progress and key.family != "a2c"  # on a terminal: a bar, or the learner's lines
    try:
        with contextlib.ExitStack() as stack:
            handles = [stack.enter_context(open(p, "w")) for p in tmp_logs]

            def logger(k: int, fh: Any) -> Any:
                def log(line: str) -> None:
                    fh.write(time.strftime("%H:%M:%S ") + line + "\n")
                    fh.flush()
                    if echo:
                        print(line, file=sys.stderr)
                    if line.startswith("done:"):  # the run's files are written
                        done[k] = True
                return log

            logs = [logger(k, fh) for k, fh in enumerate(handles)]
            together = (f", in a population of {len(seeds)} (seeds {seeds})"
                        if len(seeds) > 1 else "")
            for seed, log in zip(seeds, logs, strict=True):
                log(f"train {key.algo} on {key.scenario.id}, N = {key.n_vehicles}, seed {seed}, "
                    f"{key.steps} steps{together}, config {key.resolved_config()}")
            if key.family == "a2c":
                from marl.config import algorithm
                from marl.selection import run_population

                results = run_population(
                    algorithm(key.algo), [key.config] * len(seeds), key.scenario,
                    key.n_vehicles, key.steps, seeds, key.out,
                    progress=_Bar(key.progress and len(seeds) == 1), logs=logs,
                    evaluate=_evaluator(key), device=key.device,
                    snapshots=[key.snapshots(s) for s in seeds])
            else:
                from marl.training import run_shared

                results = [run_shared(key, logs[0], _evaluator(key), model_expert)]
    finally:
        with StagedFiles() as staged:
            for tmp, path, finished in zip(tmp_logs, log_paths, done, strict=True):
                if finished:
                    staged.adopt(tmp, path)
            staged.commit()
        for tmp in tmp_logs:
            tmp.unlink(missing_ok=True)
    return {"runs": [
        {"algo": key.algo, "scenario": key.scenario.id, "seed": res.seed,
         "checkpoint": str(res.checkpoint), "curve": str(res.curve_csv), "log": str(path),
         "env_steps_per_s": res.env_steps_per_s, "population": len(seeds)}
        for res, path in zip(results, log_paths, strict=True)]}


def add_population_argument(p: argparse.ArgumentParser) -> None:
    """The ``--population K`` option (checked by :func:`check_population`)."""
    p.add_argument("--population", type=int, default=None, metavar="K",
                   help="train up to K seeds of one algorithm and scenario in one process as one "
                        "stacked network (each run exactly as alone); default: all seeds with "
                        "the serial executor, split evenly over the workers otherwise; 1: one "
                        "run per process")


def add_device_argument(p: argparse.ArgumentParser) -> None:
    """The ``--device`` option (checked by :func:`marl.config.training_device`)."""
    p.add_argument("--device", default="cpu",
                   help="where the networks train: cpu (default) or cuda[:K]; environments, "
                        "validation and checkpoints stay on the CPU")


def add_arithmetic_argument(p: argparse.ArgumentParser, default: str) -> None:
    """The ``--arithmetic`` option (:mod:`marl.arithmetic`)."""
    from marl.arithmetic import ARITHMETIC_MODES

    p.add_argument("--arithmetic", choices=ARITHMETIC_MODES, default=default,
                   help="native: the processor's fastest float32 kernels, so a seed's weights "
                        "depend on the processor; portable: MKL_CBWR=COMPATIBLE in the training "
                        "processes, the same weights whatever the instruction sets (an Intel Xeon "
                        "and an AMD EPYC train different ones), 1.2 to 2.3 times slower; CPU only "
                        "(default: %(default)s)")


def check_arithmetic(mode: str, device: str) -> None:
    """Refuse portable arithmetic on a GPU (ConfigError): it is MKL's, the CPU's library."""
    if mode == "portable" and device not in (None, "cpu"):
        raise ConfigError(f"--arithmetic portable --device {device}: portable arithmetic is the "
                          "CPU's (MKL); train on the CPU, or natively on the GPU")


def check_population(population: int | None) -> None:
    """Refuse a ``--population`` below 1 (ConfigError)."""
    if population is not None and population < 1:
        raise ConfigError(f"--population must be >= 1, got {population}")


def check_resume_overwrite(resume: bool, overwrite: bool) -> None:
    """Refuse ``--resume`` with ``--overwrite`` (ConfigError), before anything is made."""
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite exclude each other: --resume keeps finished "
                          "work and completes the rest, --overwrite does it all again")


def check_finished(out: str | Path, held: Sequence[str], noun: tuple[str, str], redo: str,
                   resume: bool, overwrite: bool) -> None:
    """The rule of ``train`` and ``tune``, as ``run``'s for stored runs: an ``--out`` that already
    holds finished work of the command (``held``: its names; ``noun``: what one is, singular and
    plural) is refused (ConfigError) unless ``--resume`` completes the command (finished work
    kept, checked by the caller) or ``--overwrite`` redoes it (one line on stderr: ``redo``,
    how its files are replaced); :func:`check_resume_overwrite` refused both before."""
    if not held or resume:
        return
    more = f" and {len(held) - 1} more" if len(held) > 1 else ""
    what = f"{len(held)} {noun[len(held) > 1]} of this command ({held[0]}{more})"
    if not overwrite:
        raise ConfigError(f"{out} already holds {what}; add --resume to complete that command "
                          f"({noun[1]} are kept), --overwrite to do it all again ({redo}), or "
                          "choose another --out")
    print(f"--overwrite: {out} holds {what}; doing it all again: {redo}", file=sys.stderr)


def check_snapshots(keys: Sequence[TrainingKey], out: str | Path, resume: bool,
                    overwrite: bool) -> None:
    """The runs of ``keys`` whose snapshot lies in the folder (an interrupted training): with
    ``--resume`` each is read and verified now, before any training (a damaged one, or one of
    another config or budget, is a ConfigError), and continued; with ``--overwrite`` the
    snapshots are removed and the runs train from the start; otherwise refused (ConfigError)."""
    found = [(k, s) for k in keys for s in k.seeds if k.snapshots(s).path.exists()]
    if not found:
        return
    if resume:
        for k, s in found:
            print(f"{k.stem(s)}: continues from its snapshot at {k.snapshots(s).steps()} steps "
                  "(--resume)", file=sys.stderr)
    elif overwrite:
        for k, s in found:
            k.snapshots(s).remove()
        print(f"--overwrite: removed the snapshots of {len(found)} interrupted run(s) in {out}; "
              "they train from the start", file=sys.stderr)
    else:
        first = found[0][0].snapshots(found[0][1]).path.name
        more = f" and {len(found) - 1} more" if len(found) > 1 else ""
        raise ConfigError(
            f"{out} holds the snapshot of an interrupted run ({first}{more}); add --resume to "
            "continue it, --overwrite to train it from the start, or choose another --out")


def run_command(keys: Sequence[TrainingKey], out: str) -> str:
    """The ``cacc-bench run`` command that evaluates the policies of ``keys`` from ``out``
    (their runs' scenarios and N: one training's)."""
    import shlex

    specs = [f"{k.algo}:checkpoint_dir={out}" + (f",seed={s}" if s else "")
             + (f",vehicles={k.n_vehicles}" if k.family != "a2c" and k.n_vehicles != 8 else "")
             for k in keys for s in k.seeds]
    scenarios = dict.fromkeys(k.scenario.id for k in keys)
    return shlex.join(["cacc-bench", "run", "--controllers", ",".join(dict.fromkeys(specs)),
                       "--scenarios", ",".join(scenarios), "--vehicles",
                       str(keys[0].n_vehicles)])


def populations(keys: Sequence[TrainingKey], size: int | None, executor: str, workers: int
                ) -> list[TrainingKey]:
    """Group runs that differ only in their seed into population keys (several ``seeds``).

    ``size``: most runs per population; None: all runs of a group in one population with the
    serial executor, else split evenly over the ``workers``. A shared-policy learner's run trains
    alone (a population of one). Each population trains in one process (:func:`train_job`);
    every run's numbers are the same whatever the grouping.
    """
    import math

    groups: list[list[TrainingKey]] = []
    for key in keys:
        alike = [g for g in groups if replace(g[0], seeds=()) == replace(key, seeds=())]
        if alike:
            alike[0].append(key)
        else:
            groups.append([key])
    out = []
    for members in groups:
        cap = 1 if members[0].family != "a2c" else size or (
            len(members) if executor == "serial" else math.ceil(len(members) / max(workers, 1)))
        for i in range(0, len(members), cap):
            out.append(replace(members[0], seeds=tuple(s for m in members[i:i + cap]
                                                       for s in m.seeds)))
    return out


def _names(text: str, flag: str) -> list[str]:
    names = list(dict.fromkeys(x.strip() for x in text.split(",") if x.strip()))
    if not names:
        raise ConfigError(f"{flag}: nothing named")
    return names


def set_options(items: Sequence[str]) -> dict[str, str]:
    """``--set KEY=VALUE`` items (repeatable; a later one wins) as options, untyped: the one
    parser of ``train`` and ``tune`` (:func:`marl.training.learner_config` types and checks them)."""
    options: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. --set gamma=0.995")
        if key.strip() == "algo":
            raise ConfigError("--set algo: name the learner with --algo")
        options[key.strip()] = value.strip()
    return options


def main(argv: list[str]) -> int:
    """Entry point: ``cacc-bench train --algo NAME --scenario ID [...]``."""
    from benchmark.executors import check_ray_address, map_jobs
    from benchmark.folder_lock import folder_lock
    from benchmark.paths import writable_dir
    from commands.cli import scenarios_argument
    from envs.scenarios import ENTRY_POINT_GROUP, check_vehicles
    from infra.limits import (
        MAX_EPISODES_PARALLEL,
        MAX_TRAIN_SEED,
        MAX_TRAIN_STEPS,
        check_range,
        check_seeds,
    )
    from marl.arithmetic import process_env
    from marl.config import training_device, tuned_options
    from marl.learners import LEARNERS, PAPER_ALGORITHMS
    from marl.training import TrainingKey, finished, learner_config

    args = _parser().parse_args(argv)
    check_ray_address(args.ray_address)  # an address that does not answer: refused before work
    algos = _names(args.algo, "--algo")
    if algos == ["all"]:
        algos = list(PAPER_ALGORITHMS)
    for a in algos:
        if a not in LEARNERS:
            raise UnknownNameError("algorithm", a, tuple(LEARNERS))
    built = scenarios_argument(args.scenario, "--scenario")  # each built and checked once
    for one in built:
        if one.base_name != one.id:  # a ScenarioSpec of one's own, named by its reference
            raise ConfigError(
                f"--scenario {one.label}: training takes scenario ids (checkpoints are named and "
                f"loaded by id), and {one.base_name} is a scenario of your own whose id "
                f"{one.id} names nothing by itself; add it through the entry-point group "
                f"{ENTRY_POINT_GROUP} of an installed package (docs/contributing.md, Add a "
                f"scenario), then train on {one.id}")
        if one.label != one.id:
            raise ConfigError(
                f"--scenario {one.label}: training takes plain scenario ids (checkpoints are "
                f"named and loaded by id, so a policy trained with options would be read as "
                f"trained on {one.id}); train on {one.id} and evaluate on {one.label} with run")
    check_vehicles(args.vehicles)
    check_range(args.steps, "--steps", 1, MAX_TRAIN_STEPS)
    check_population(args.population)
    check_resume_overwrite(args.resume, args.overwrite)
    training_device(args.device)  # ConfigError for an unknown device or a missing GPU
    check_arithmetic(args.arithmetic, args.device)
    if any(LEARNERS[a].family != "a2c" for a in algos):
        if args.arithmetic != "native":
            raise ConfigError("--arithmetic portable: the shared-policy learners train natively; "
                              "portable arithmetic is for the paper's learners")
        if args.device not in (None, "cpu"):
            raise ConfigError(f"--device {args.device}: the shared-policy learners train on "
                              "the CPU")
    if args.seeds is not None:
        try:
            seeds = list(dict.fromkeys(int(x) for x in args.seeds.split(",") if x.strip()))
        except ValueError:
            raise ConfigError(f"--seeds must be a comma list of integers, got {args.seeds!r}") from None
        if not seeds:
            raise ConfigError("--seeds: no seed given")
    else:
        seeds = [args.seed]
    # training episode seeds derive from the run's seed in 32-bit generators: one bound
    check_seeds(seeds, "--seeds" if args.seeds is not None else "--seed", MAX_TRAIN_SEED)
    options: dict[str, Any] = set_options(args.overrides)
    if args.episodes_parallel is not None:
        check_range(args.episodes_parallel, "--episodes-parallel", 1, MAX_EPISODES_PARALLEL)
    configs = {}  # typed from the config's fields and validated before anything starts
    for a in algos:
        batch = {} if args.episodes_parallel is None else {
            "episodes_parallel" if LEARNERS[a].family == "a2c" else "n_envs":
            args.episodes_parallel}
        for sc in built:
            tuned = tuned_options(a, sc.id) if args.tuned else {}
            configs[(a, sc.id)] = learner_config(a, {**tuned, **options, **batch})
    writable_dir(args.out)
    single = len(seeds) * len(configs) == 1 and args.executor == "serial"
    keys = [TrainingKey(a, sc, args.vehicles, (seed,), args.steps, configs[(a, sc.id)],
                        Path(args.out), args.arithmetic, args.device,
                        progress=sys.stderr.isatty() and single)
            for seed in seeds for sc in built for a in algos]
    asked = keys
    with folder_lock(args.out):  # one writer per folder, as `run`; refused naming the holder
        check_finished(args.out, [k.stem(k.seeds[0]) for k in keys if k.held()],
                       ("finished run", "finished runs"),
                       "a run's files are replaced when it finishes",
                       args.resume, args.overwrite)
        if args.resume:  # every finished run checked before any training
            done = [finished(k) for k in keys]
            for k in (k for k, d in zip(keys, done, strict=True) if d):
                print(f"{k.stem(k.seeds[0])}: finished before, skipped (--resume)",
                      file=sys.stderr)
            if any(done):
                print(f"resuming: {sum(done)} of {len(keys)} runs already finished in "
                      f"{args.out}", file=sys.stderr)
            keys = [k for k, d in zip(keys, done, strict=True) if not d]
        check_snapshots(keys, args.out, args.resume, args.overwrite)
        if keys:
            from marl.checkpoint import SNAPSHOT_EVERY_S

            print(f"training {len(keys)} run{'s' * (len(keys) > 1)} into {args.out} (each "
                  f"keeps a snapshot there every {SNAPSHOT_EVERY_S:.0f} s: after an "
                  "interruption, the same command with --resume continues it)", file=sys.stderr)
        try:
            for res in map_jobs(train_job,
                                populations(keys, args.population, args.executor, args.workers),
                                args.executor, args.workers, args.ray_address,
                                process_env(args.arithmetic)):
                for run in res["runs"]:
                    together = (f" (population of {run['population']})"
                                if run["population"] > 1 else "")
                    print(f"{run['algo']} {run['scenario']} seed {run['seed']}: checkpoint "
                          f"{run['checkpoint']}, curve {run['curve']}, log {run['log']}; "
                          f"{run['env_steps_per_s']:.0f} env steps/s{together}")
        except OSError as exc:  # a full disk, a folder made unwritable meanwhile
            raise ConfigError(
                f"training into {args.out} stopped: {exc.strerror or exc}"
                f"{f' ({exc.filename})' if exc.filename else ''}; runs that did not finish "
                "left the files there as they were: fix that and rerun with --resume"
            ) from None
    print(f"evaluate with: {run_command(asked, args.out)}")
    return 0
