"""``cacc-bench reproduce``: the paper's tables, curves and claims from one command.

Stages, each resumable: (1) the MARL policies, three training seeds each, with the configs
``cacc-bench tune`` chose (``marl/tuned_configs.json``): trained into ``OUT/checkpoints`` unless
a finished run with the same config is already there, or (paper budget, without ``--retrain``)
a shipped checkpoint with that config and budget exists, which is copied with its curve and
provenance; (2) every policy and the baselines on the evaluation seeds, through the results
store; (3) ``OUT/report.md`` with its figures and the CSV behind every table.

The command holds OUT's folder lock and works inside OUT (:mod:`benchmark.work_folder`): run
labels name checkpoint folders relative to it (``bdc[checkpoint_dir=checkpoints,seed=1]``), so
``--resume`` with OUT spelled otherwise, or after moving it, reruns nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmark.executors import EXECUTORS
from commands.cli import check_executor, plain, scenarios_argument
from commands.policy_training import train_stage, tuned_config
from commands.train import (
    add_arithmetic_argument,
    add_device_argument,
    add_population_argument,
    check_arithmetic,
    check_population,
)
from envs.scenarios import Scenario, as_scenario, make_scenario
from infra.atomic import write_text
from infra.errors import ConfigError, UnknownNameError
from infra.files import read_csv, read_json
from marl.training import PolicyJob
from studies.paper import (
    ABLATIONS,
    BASELINES,
    BUDGETS,
    DEFAULT_SCENARIOS,
    N_VEHICLES,
    OPENACC_BASELINES,
    OPENACC_GROUPS,
    OPENACC_VEHICLES,
    SIZE_ALGOS,
    SIZE_SCENARIO,
    SIZES,
    STUDIES,
    Budget,
)

MANIFEST = "reproduce.json"
#: What to do about a damaged manifest: finished training and runs are kept without it.
RESTART = "remove it or restore it, and rerun with --resume (finished training and runs are kept)"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cacc-bench reproduce", description=plain(__doc__.split("\n")[0]))
    p.add_argument("--out", default="results/reproduce", help="output folder (default: %(default)s)")
    p.add_argument("--budget", choices=sorted(BUDGETS), default="paper",
                   help="quick: a smoke test in minutes; paper: 3 seeds x 6e5 steps, 50 episodes "
                        "(default: %(default)s)")
    p.add_argument("--algos", default="all",
                   help="comma list of MARL algorithms, or all (default: all seven)")
    p.add_argument("--scenarios", default=",".join(DEFAULT_SCENARIOS),
                   help="comma list of scenario ids (default: %(default)s)")
    p.add_argument("--skip", default="",
                   help="comma list of studies to leave out: " + ", ".join(STUDIES)
                        + " (BDC without QSGD; BDC and IA2C at N = 2, 4, 6; BDC on OpenACC)")
    p.add_argument("--executor", choices=EXECUTORS, default="serial")
    p.add_argument("--workers", type=int, default=2, help="processes or Ray CPUs (default 2)")
    add_population_argument(p)
    add_device_argument(p)
    # portable, as the shipped policies of the committed report (docs/paper-reproduction) were
    # trained: --retrain gives their weights again (on the processors measured, marl.arithmetic)
    add_arithmetic_argument(p, "portable")
    p.add_argument("--retrain", action="store_true",
                   help="train every policy instead of copying the shipped checkpoints of the "
                        "same config and budget (--budget paper copies them by default)")
    p.add_argument("--ray-address", default=None, help="attach to this Ray cluster")
    p.add_argument("--resume", action="store_true",
                   help="complete a reproduction in --out (finished training and runs are kept)")
    return p


# ------------------------------------------------------------------------------ training
def _train_plan(algos: list[str], scenarios: Sequence[Scenario | str], budget: Budget,
                out: Path, studies: set[str]) -> list[PolicyJob]:
    """Every training run of the reproduction, with its tuned config and its folder.

    - ``main``: each algorithm (and ablation) on each scenario at N = 8;
    - ``sizes``: :data:`SIZE_ALGOS` at N in :data:`SIZES` on catchup-v1 (catchup-v1's tuned config);
    - ``openacc``: BDC on each OpenACC training family at N = 4 (catchup-v1's tuned config).
    """
    built = {sc.label: sc for sc in map(as_scenario, scenarios)}
    ckpt = out / "checkpoints"
    variants: list[tuple[str, str, dict[str, Any]]] = [(a, a, {}) for a in algos]
    if "ablations" in studies:
        variants += [(name, a, extra) for name, (a, extra) in ABLATIONS.items() if a in algos]
    # (name, algo, scenario, N, folder, config, study) of the runs, each trained with every seed
    runs: list[tuple[str, str, Scenario, int, Path, Any, str]] = [
        (name, algo, sc, N_VEHICLES, ckpt if name == algo else ckpt / name,
         tuned_config(algo, label, extra, name), "main")
        for name, algo, extra in variants for label, sc in built.items()]
    if "sizes" in studies and SIZE_SCENARIO in built:
        runs += [(algo, algo, built[SIZE_SCENARIO], n, ckpt, config, "sizes")
                 for algo in SIZE_ALGOS if algo in algos
                 for config in [tuned_config(algo, SIZE_SCENARIO, {}, algo)] for n in SIZES]
    if "openacc" in studies and "bdc" in algos:
        config = tuned_config("bdc", SIZE_SCENARIO, {}, "bdc")
        runs += [("bdc", "bdc", make_scenario(train_id), OPENACC_VEHICLES, ckpt, config, "openacc")
                 for train_id in OPENACC_GROUPS.values()]
    return [PolicyJob(algo, sc, n, (seed,), budget.steps, config, folder,
                      validation_episodes=budget.validation_episodes, name=name, study=study)
            for name, algo, sc, n, folder, config, study in runs for seed in budget.seeds]


# ------------------------------------------------------------------------------ evaluation
def _policy(job: PolicyJob) -> tuple[str, dict[str, str]]:
    opts = {"checkpoint_dir": str(job.out), "seed": str(job.seed)}
    if job.study == "openacc":
        opts["scenario"] = job.scenario.label
    return job.algo, opts


def eval_keys(jobs: list[PolicyJob], scenarios: Sequence[Scenario | str], budget: Budget
              ) -> tuple[list[Any], dict[str, str]]:
    """The evaluation runs of every study and the map label -> name shown in the tables."""
    from benchmark.suite import build_sweep, seeds_from_episodes
    from controllers.registry import controller_label

    seeds = seeds_from_episodes(budget.episodes)
    names: dict[str, str] = {}
    keys: set[Any] = set()

    def add(ctrls: list[tuple[str, dict[str, str]]], scs: Sequence[Scenario | str], ns: list[int],
            shown: list[str]) -> None:
        keys.update(build_sweep(ctrls, scs, ns, seeds))
        for (algo, opts), name in zip(ctrls, shown, strict=True):
            names[controller_label(algo, opts)] = name

    seen: dict[str, tuple[str, tuple[str, dict[str, str]]]] = {}
    for j in jobs:
        algo, opts = _policy(j)
        seen.setdefault(json.dumps([j.study, algo, opts], sort_keys=True), (j.name, (algo, opts)))
    by_study: dict[str, list[tuple[str, tuple[str, dict[str, str]]]]] = {}
    for key, val in seen.items():
        by_study.setdefault(json.loads(key)[0], []).append(val)
    main_pol = by_study.get("main", [])
    add([(b, {}) for b in BASELINES] + [c for _, c in main_pol], scenarios, [N_VEHICLES],
        list(BASELINES) + [n for n, _ in main_pol])
    size_pol = by_study.get("sizes", [])
    if size_pol:
        add([("ovm", {})] + [c for _, c in size_pol], [SIZE_SCENARIO], list(SIZES),
            ["ovm"] + [n for n, _ in size_pol])
    for test_id, train_id in OPENACC_GROUPS.items():
        pol = [(n, c) for n, c in by_study.get("openacc", []) if c[1]["scenario"] == train_id]
        if pol:
            add([(b, {}) for b in OPENACC_BASELINES] + [c for _, c in pol], [test_id],
                [OPENACC_VEHICLES], list(OPENACC_BASELINES) + [n for n, _ in pol])
    return sorted(keys), names


def eval_stage(jobs: list[PolicyJob], scenarios: Sequence[Scenario], budget: Budget,
               args: argparse.Namespace, out: Path) -> dict[str, str]:
    """Run every policy and baseline on the evaluation seeds (resumable store)."""
    from commands.run import execute_sweep
    from marl.arithmetic import process_env

    keys, names = eval_keys(jobs, scenarios, budget)
    print(f"evaluation: {len(keys)} runs", file=sys.stderr)
    rc = execute_sweep(keys, out / "runs", resume=True, executor=args.executor,
                       workers=args.workers, ray_address=args.ray_address, quiet=True,
                       first_seed=min(k.seed for k in keys), pool_seeds=True,
                       env=process_env(args.arithmetic))
    if rc != 0:
        raise ConfigError(f"some evaluation runs failed (see {out / 'runs' / 'runs.csv'}); fix the "
                          "cause and rerun with --resume")
    return names


# ------------------------------------------------------------------------------ main
def _holds_files(folder: Path) -> bool:
    """Whether ``folder`` holds anything but a lock left by an earlier command."""
    from benchmark.folder_lock import LOCK_FILES

    return folder.is_dir() and any(p.name not in LOCK_FILES for p in folder.iterdir())


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench reproduce``."""
    from marl.config import training_device
    from marl.learners import PAPER_ALGORITHMS

    t0 = time.perf_counter()
    args = _parser().parse_args(argv)

    budget = BUDGETS[args.budget]
    algos = [a.strip() for a in args.algos.split(",") if a.strip()]
    if algos == ["all"]:
        algos = list(PAPER_ALGORITHMS)
    if not algos:
        raise ConfigError("--algos: nothing named")
    for a in algos:
        if a not in PAPER_ALGORITHMS:
            raise UnknownNameError("algorithm", a, PAPER_ALGORITHMS)
    built = scenarios_argument(args.scenarios)
    scenarios = [sc.label for sc in built]  # names of checkpoints, report sections, the manifest
    check_executor(args.workers, args.ray_address)
    check_population(args.population)
    training_device(args.device)  # ConfigError for an unknown device or a missing GPU
    check_arithmetic(args.arithmetic, args.device)
    from benchmark.paths import writable_dir

    out = writable_dir(args.out)
    manifest_path = out / MANIFEST
    skip = [x.strip() for x in args.skip.split(",") if x.strip()]
    for x in skip:
        if x not in STUDIES:
            raise UnknownNameError("study", x, STUDIES)
    studies = {x for x in STUDIES if x not in skip}
    settings = {"budget": budget.name, "algos": algos, "scenarios": scenarios,
                "studies": sorted(studies), "arithmetic": args.arithmetic,
                "retrain": args.retrain}
    previous = (read_json(manifest_path, "the reproduction manifest", RESTART)
                if manifest_path.exists() else None)
    if previous is not None:
        if not args.resume:
            raise ConfigError(f"{out} already holds a reproduction; add --resume to complete it, "
                              "or choose another --out")
        # a reproduction from before --arithmetic (--retrain) existed trained natively (copied)
        if {"arithmetic": "native", "retrain": False, **previous.get("settings", {})} != settings:
            raise ConfigError(f"{out} holds a reproduction with other settings "
                              f"({previous.get('settings')}); use another --out")
    elif _holds_files(out) and not args.resume:
        raise ConfigError(f"{out} is not empty; choose another --out (or --resume)")
    from benchmark.work_folder import command_text, working_in
    from studies.reproduction_report import check_job_files, write_report

    out.mkdir(parents=True, exist_ok=True)
    # inside OUT, locked: every recorded path (checkpoint folders in run labels, the report)
    # is relative to it, so --out spelled otherwise or a moved folder reruns nothing
    with working_in(out):
        here = Path(".")
        jobs = _train_plan(algos, built, budget, here, studies)
        check_job_files(jobs)  # a damaged file of a finished job: refused before any work
        manifest: dict[str, Any] = {"settings": settings,
                                    "command": command_text("cacc-bench reproduce", argv)}
        write_text(here / MANIFEST, json.dumps({**manifest, "status": "started"}, indent=1))
        train_stage(jobs, args, reuse_shipped=budget.name == "paper" and not args.retrain)
        names = eval_stage(jobs, built, budget, args, here)
        train_wall = sum(float(read_json(j.file(".source.json"), "the source record")
                               .get("wall_s") or 0.0) for j in jobs)
        runs = read_csv(here / "runs" / "runs.csv", "the runs table", columns=("wall_s",))
        manifest.update({"wall_s": time.perf_counter() - t0, "train_wall_s": train_wall,
                         "eval_wall_s": float(runs["wall_s"].sum())})
        report = out / write_report(jobs, names, built, budget, here, manifest)
        write_text(here / MANIFEST, json.dumps({**manifest, "status": "done"}, indent=1))
    print(f"wrote {report}")
    return 0
