"""``cacc-bench train``: train MARL algorithms on scenarios and store the policies.

Writes ``<out>/<algo>__<scenario>__n<N>__s<seed>.pt`` (the snapshot selected on the validation
seeds), ``.final.pt`` (the final weights), ``.curve.csv`` (episode, steps, training reward,
validation reward and collisions in both evaluation modes) and ``.log`` (evaluations, bits
communicated) per run. Several seeds of one algorithm and scenario train in one process as a
population (``--population``): one stacked network, each run exactly as it would alone.
Shows a progress bar on a terminal and stays quiet otherwise.

A run's files are written when it finishes, each atomically and together
(:mod:`infra.atomic`): an interrupted or failed run leaves the files of an earlier run byte for
byte as they were. The command holds ``--out``'s folder lock (:mod:`benchmark.folder_lock`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from infra.errors import ConfigError, UnknownNameError
from infra.limits import step_count

#: Default output: the folder the ``marl`` controllers load from (``controllers/checkpoints``
#: of the installed package), so ``cacc-bench run --controllers NAME`` uses what was trained.
DEFAULT_OUT = str(Path(__file__).resolve().parent.parent / "controllers" / "checkpoints")


def _parser() -> argparse.ArgumentParser:
    from marl.learners import PAPER_ALGORITHMS

    p = argparse.ArgumentParser(
        prog="cacc-bench train",
        description="Train a MARL algorithm (one agent per follower) on a scenario.",
    )
    p.add_argument("--algo", required=True,
                   help=f"one of: {', '.join(PAPER_ALGORITHMS)}; a comma list, or all; or the "
                        "shared-policy learners ippo, mappo (marl/ppo.py) and distill "
                        "(marl/distill.py), whose config fields --set takes")
    p.add_argument("--scenario", required=True,
                   help="scenario id, e.g. catchup-v1, or a comma list")
    p.add_argument("--steps", type=step_count, default=600_000, help="environment steps (default 6e5)")
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
                   help="output folder (default: the package's controllers/checkpoints, where "
                        "the marl controllers load from)")
    p.add_argument(
        "--episodes-parallel", type=int, default=None, help="B episodes stepped together"
    )
    p.add_argument(
        "--resume", action="store_true",
        help="skip runs that finished in --out (their .final.pt exists with the same config); "
             "an interrupted run starts again",
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


def _train_job(job: dict) -> dict:
    """Train one job's runs, its ``seeds`` (or its one ``seed``), as one population in this
    process (top level, so process and Ray executors can run it). Returns ``{"runs": [...]}``,
    one summary per run."""
    import contextlib

    import torch

    from benchmark.policy_eval import validation_evaluator
    from envs.params import VALIDATION_SEEDS
    from infra.atomic import StagedFiles, temporary_beside
    from infra.naming import checkpoint_stem
    from marl import arithmetic
    from marl.config import algorithm
    from marl.selection import run_population

    arithmetic.require(job.get("arithmetic", "native"))  # before this process's first product
    torch.set_num_threads(1)
    seeds = list(job.get("seeds", [job["seed"]]))
    algo = algorithm(job["algo"])
    config = algo.config_cls(**job["options"])
    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    log_paths = [out / (checkpoint_stem(job["algo"], job["scenario"], job["vehicles"], s) + ".log")
                 for s in seeds]
    # each log grows in a hidden temporary file beside it (``.<stem>.log.*.tmp``, to follow
    # with tail -f) and replaces the .log only once its run's files are written: an interrupted
    # or failed run leaves an earlier run's log as it was
    tmp_logs = [temporary_beside(p) for p in log_paths]
    done = [False] * len(seeds)
    try:
        with contextlib.ExitStack() as stack:
            handles = [stack.enter_context(open(p, "w")) for p in tmp_logs]

            def logger(k: int, fh: Any) -> Any:
                def log(line: str) -> None:
                    fh.write(time.strftime("%H:%M:%S ") + line + "\n")
                    fh.flush()
                    if line.startswith("done:"):  # run_population wrote the run's files
                        done[k] = True
                return log

            logs = [logger(k, fh) for k, fh in enumerate(handles)]
            together = (f", in a population of {len(seeds)} (seeds {seeds})"
                        if len(seeds) > 1 else "")
            for seed, log in zip(seeds, logs, strict=True):
                log(
                    f"train {job['algo']} on {job['scenario']}, N = {job['vehicles']}, seed "
                    f"{seed}, {job['steps']} steps{together}, config "
                    f"{config.resolved(job['scenario'])}"
                )
            results = run_population(
                algo, [config] * len(seeds), job["scenario"], job["vehicles"], job["steps"],
                seeds, out, progress=_Bar(job["progress"] and len(seeds) == 1), logs=logs,
                evaluate=validation_evaluator(
                    job["algo"], job["scenario"], job["vehicles"],
                    VALIDATION_SEEDS[: job.get("validation_episodes") or len(VALIDATION_SEEDS)]),
                device=job.get("device", "cpu"))
    finally:
        with StagedFiles() as staged:
            for tmp, path, finished in zip(tmp_logs, log_paths, done, strict=True):
                if finished:
                    staged.adopt(tmp, path)
            staged.commit()
        for tmp in tmp_logs:
            tmp.unlink(missing_ok=True)
    return {"runs": [
        {"algo": job["algo"], "scenario": job["scenario"], "seed": res.seed,
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


def population_jobs(jobs: list[dict], size: int | None, executor: str, workers: int) -> list[dict]:
    """Group runs that differ only in their seed into population jobs (``seeds``).

    ``size``: most runs per population; None: all runs of a group in one population with the
    serial executor, else split evenly over the ``workers``. Each population trains in one
    process (:func:`_train_job`); every run's numbers are the same whatever the grouping.
    """
    import json
    import math

    groups: dict[str, list[dict]] = {}
    for job in jobs:
        key = json.dumps({k: v for k, v in job.items() if k not in ("seed", "progress")},
                         sort_keys=True, default=str)
        groups.setdefault(key, []).append(job)
    out = []
    for members in groups.values():
        cap = size or (len(members) if executor == "serial"
                       else math.ceil(len(members) / max(workers, 1)))
        for i in range(0, len(members), cap):
            chunk = members[i:i + cap]
            out.append({**chunk[0], "seeds": [j["seed"] for j in chunk]})
    return out


def _names(text: str, flag: str) -> list[str]:
    names = list(dict.fromkeys(x.strip() for x in text.split(",") if x.strip()))
    if not names:
        raise ConfigError(f"{flag}: nothing named")
    return names


def job_config(job: dict) -> dict:
    """The whole resolved config a training job runs with (as recorded in its checkpoint)."""
    import dataclasses

    from marl.config import algorithm

    config = algorithm(job["algo"]).config_cls(**job["options"]).resolved(job["scenario"])
    return dataclasses.asdict(config)


def _finished(job: dict) -> bool:
    """Whether ``job``'s run finished in its folder with the same config and budget (a
    different one is an error: a finished run is never overwritten silently)."""
    from infra.naming import checkpoint_stem
    from marl.checkpoint import energy_model_id, load_checkpoint, same_energy_model

    stem = checkpoint_stem(job["algo"], job["scenario"], job["vehicles"], job["seed"])
    final = Path(job["out"]) / f"{stem}.final.pt"
    if not final.exists():
        return False
    try:  # verified: a damaged or truncated file is refused, naming what to do
        data = load_checkpoint(final, algo=job["algo"], n_vehicles=job["vehicles"],
                               scenario=job["scenario"])
    except ConfigError as exc:
        raise ConfigError(f"{exc} (or remove {final} to train this run again)") from None
    if data["config"] != job_config(job) or data["steps"] < job["steps"]:
        raise ConfigError(
            f"{final} holds a finished run with another config or fewer steps than asked "
            f"({data['steps']} < {job['steps']} or config differs); use another --out, or "
            "remove it to train again"
        )
    from marl.arithmetic import of_summary

    mode = job.get("arithmetic", "native")
    if of_summary(data["curve_summary"]) != mode:
        raise ConfigError(
            f"{final} holds a run trained with {of_summary(data['curve_summary'])} arithmetic, "
            f"not {mode} (--arithmetic); use another --out, or remove it to train again")
    if not same_energy_model(data):
        raise ConfigError(
            f"{final} holds a run trained with another energy model (fingerprint "
            f"{data.get('energy_model')}, this cacc-bench's is {energy_model_id()}: its reward "
            "differs); use another --out, or remove it to train again"
        )
    return True


def main(argv: list[str]) -> int:
    """Entry point: ``cacc-bench train --algo NAME --scenario ID [...]``."""
    from benchmark.executors import map_jobs
    from commands.cli import scenarios_argument
    from controllers.registry import build_config
    from envs.scenarios import check_vehicles
    from marl.arithmetic import process_env
    from marl.config import algorithm, training_device, tuned_options
    from marl.learners import PAPER_ALGORITHMS, SHARED_LEARNERS

    args = _parser().parse_args(argv)
    from benchmark.executors import check_ray_address

    check_ray_address(args.ray_address)  # an address that does not answer: refused before work
    algos = _names(args.algo, "--algo")
    if algos == ["all"]:
        algos = list(PAPER_ALGORITHMS)
    shared = [a for a in algos if a in SHARED_LEARNERS]
    if shared and len(shared) != len(algos):
        raise ConfigError(f"--algo: train the shared-policy learners ({', '.join(shared)}) in a "
                          "command of their own (they take other config fields)")
    for a in algos:
        if a not in PAPER_ALGORITHMS and not shared:
            raise UnknownNameError("algorithm", a, (*PAPER_ALGORITHMS, *SHARED_LEARNERS))
    built = scenarios_argument(args.scenario, "--scenario")  # each built and checked once
    for one in built:
        if one.label != one.id:
            raise ConfigError(
                f"--scenario {one.label}: training takes plain scenario ids (checkpoints are "
                f"named and loaded by id, so a policy trained with options would be read as "
                f"trained on {one.id}); train on {one.id} and evaluate on {one.label} with run")
    scenarios = [one.id for one in built]  # the trainers take the id: checkpoints are named by it
    check_vehicles(args.vehicles)
    from infra.limits import (
        MAX_EPISODES_PARALLEL,
        MAX_TRAIN_SEED,
        MAX_TRAIN_STEPS,
        check_range,
        check_seeds,
    )

    if args.steps < 1:
        raise ConfigError(f"--steps must be >= 1, got {args.steps}")
    check_range(args.steps, "--steps", 1, MAX_TRAIN_STEPS)
    check_population(args.population)
    training_device(args.device)  # ConfigError for an unknown device or a missing GPU
    check_arithmetic(args.arithmetic, args.device)
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
    if shared:
        from commands.train_shared import main_shared

        if args.arithmetic != "native":
            raise ConfigError("--arithmetic portable: the shared-policy learners train natively "
                              "in this process (one run after another); portable arithmetic "
                              "is for the paper's learners")
        return main_shared(args, shared, scenarios, seeds)
    overrides: dict[str, object] = {}
    for pair in args.overrides:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {pair!r}: expected KEY=VALUE, e.g. --set gamma=0.995")
        overrides[key.strip()] = value.strip()
    if args.episodes_parallel is not None:
        check_range(args.episodes_parallel, "--episodes-parallel", 1, MAX_EPISODES_PARALLEL)
        overrides["episodes_parallel"] = args.episodes_parallel
    # typed from the config's fields and validated before anything starts
    configs: dict[tuple[str, str], dict[str, object]] = {}
    for a in algos:
        for sc in scenarios:
            options = {**(tuned_options(a, sc) if args.tuned else {}), **overrides}
            config = build_config(algorithm(a).config_cls, options, f"{a} (--set)")
            configs[(a, sc)] = {f: getattr(config, f) for f in options}
    from benchmark.paths import writable_dir

    writable_dir(args.out)
    tty = sys.stderr.isatty()
    single = len(seeds) * len(configs) == 1 and args.executor == "serial"
    jobs = [
        {"algo": a, "scenario": sc, "vehicles": args.vehicles, "steps": args.steps,
         "seed": seed, "out": args.out, "options": configs[(a, sc)],
         "progress": tty and single, "device": args.device, "arithmetic": args.arithmetic}
        for seed in seeds for sc in scenarios for a in algos
    ]
    from benchmark.folder_lock import folder_lock

    with folder_lock(args.out):  # one writer per folder, as `run`; refused naming the holder
        if args.resume:
            done = [j for j in jobs if _finished(j)]
            if done:
                print(f"resuming: {len(done)} of {len(jobs)} runs already finished in "
                      f"{args.out}", file=sys.stderr)
            jobs = [j for j in jobs if j not in done]
        populations = population_jobs(jobs, args.population, args.executor, args.workers)
        try:
            for res in map_jobs(_train_job, populations, args.executor, args.workers,
                                args.ray_address, process_env(args.arithmetic)):
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
    return 0
