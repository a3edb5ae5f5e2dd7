"""``cacc-bench sensitivity``: BDC-MARL's knobs one at a time, and its tolerance of V2V faults.

From BDC's tuned config on each scenario one knob changes at a time: the consensus step eps
(0.01x to 10x the tuned value), the QSGD levels s (1, 2, 4, off), what is shared (the critic's
LSTM, the whole critic) and gamma (0.99, 0.995). Each variant trains (seed 0 unless --seeds)
into ``OUT/checkpoints/<variant>``; the unchanged config reuses the shipped policy when its
config and budget match. Every variant then runs on the evaluation seeds, and the unchanged
policy also under V2V delay 0.1-0.3 s and packet loss 10-30 %. ``OUT/sensitivity.csv``,
``OUT/report.md`` and figures come out; everything is resumable. The command holds OUT's
folder lock and works inside OUT (:mod:`benchmark.work_folder`): run labels name checkpoint
folders relative to it, so OUT spelled otherwise or moved reruns nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmark.executors import add_executor_options
from benchmark.export import write_csv
from commands.cli import plain, scenarios_argument
from commands.train import add_arithmetic_argument, add_device_argument, check_arithmetic
from envs.scenarios import Scenario
from infra.atomic import write_text
from infra.errors import ConfigError, UnknownNameError
from infra.files import read_csv, read_json
from infra.limits import step_count
from marl.training import PolicyJob

#: Multiples of the tuned consensus eps tried (two decades and more around it).
EPS_FACTORS: tuple[float, ...] = (0.01, 0.1, 1.0, 10.0)
#: QSGD levels s tried (0: QSGD off).
QSGD_LEVELS: tuple[int, ...] = (1, 2, 4, 0)
GAMMAS: tuple[float, ...] = (0.99, 0.995)
#: V2V degradation at execution: delays (s) at no loss, and losses at no delay.
DELAYS_S: tuple[float, ...] = (0.1, 0.2, 0.3)
LOSSES: tuple[float, ...] = (0.1, 0.2, 0.3)
KNOBS: tuple[str, ...] = ("consensus_eps", "qsgd_levels", "shared", "gamma", "v2v")
DEFAULT_SCENARIOS = ("catchup-v1", "slowdown-v1")
N_VEHICLES = 8
MANIFEST = "sensitivity.json"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cacc-bench sensitivity",
                                description=plain(__doc__.split("\n")[0]))
    p.add_argument("--scenarios", default=",".join(DEFAULT_SCENARIOS),
                   help="comma list of scenario ids (default: %(default)s)")
    p.add_argument("--knobs", default=",".join(KNOBS),
                   help="comma list among " + ", ".join(KNOBS) + " (default: all)")
    p.add_argument("--seeds", default="0", help="training seeds (default: %(default)s)")
    p.add_argument("--steps", type=step_count, default=600_000,
                   help="environment steps per training run (default 6e5, the shipped budget)")
    p.add_argument("--validation-episodes", type=int, default=32,
                   help="validation episodes per snapshot evaluation (default: 32)")
    p.add_argument("--episodes", type=int, default=50,
                   help="first K published evaluation seeds (default: %(default)s)")
    p.add_argument("--out", default="results/sensitivity",
                   help="output folder (default: %(default)s)")
    p.add_argument("--resume", action="store_true", help="complete a study in --out")
    add_executor_options(p)
    add_device_argument(p)
    add_arithmetic_argument(p, "native")
    return p


def variants(knobs: list[str], tuned: dict[str, Any]) -> list[dict[str, Any]]:
    """The trained variants: ``name``, ``knob``, ``value``, config ``overrides``, ``is_base``.

    The unchanged (tuned) config comes first and stands as one value of every knob.
    """
    eps = float(tuned["consensus_eps"])
    out = [{"name": "base", "knob": "", "value": "", "overrides": {}, "is_base": True}]

    def add(name: str, knob: str, value: Any, overrides: dict[str, Any]) -> None:
        out.append({"name": name, "knob": knob, "value": value, "overrides": overrides,
                    "is_base": False})

    if "consensus_eps" in knobs:
        for f in EPS_FACTORS:
            if f != 1.0:
                add(f"eps_x{f:g}", "consensus_eps", float(f"{eps * f:.3g}"),
                    {"consensus_eps": eps * f})
    if "qsgd_levels" in knobs:
        for s in QSGD_LEVELS:
            if s != tuned["qsgd_levels"]:
                add(f"qsgd_s{s}" if s else "qsgd_off", "qsgd_levels", s or "off",
                    {"qsgd_levels": s})
    if "shared" in knobs and not tuned["share_whole_critic"]:
        add("share_whole_critic", "shared", "whole critic", {"share_whole_critic": True})
    if "gamma" in knobs:
        for g in GAMMAS:
            if g != tuned["gamma"]:
                add(f"gamma_{g:g}", "gamma", g, {"gamma": g})
    return out


def _base_value(knob: str, tuned: dict[str, Any]) -> Any:
    return {"consensus_eps": float(f"{float(tuned['consensus_eps']):.3g}"),
            "qsgd_levels": tuned["qsgd_levels"] or "off",
            "shared": "whole critic" if tuned["share_whole_critic"] else "critic LSTM",
            "gamma": tuned["gamma"]}[knob]


def plan(built: Sequence[Scenario], knobs: list[str], seeds: list[int], steps: int,
         validation_episodes: int, out: Path) -> tuple[list[PolicyJob], list[dict[str, Any]]]:
    """Training jobs and evaluation settings on the scenarios ``built`` (see
    :func:`studies.sensitivity.sensitivity_frame`; ``training`` holds the jobs until their
    summaries are read)."""
    from commands.policy_training import tuned_config
    from controllers.registry import controller_label

    jobs: list[PolicyJob] = []
    settings: list[dict[str, Any]] = []
    for sc in built:
        tuned = dataclasses.asdict(tuned_config("bdc", sc.label, {}, "bdc"))
        for v in variants(knobs, tuned):
            folder = out / "checkpoints" / v["name"]
            config = tuned_config("bdc", sc.label, v["overrides"], f"bdc {v['name']}")
            vjobs = [PolicyJob("bdc", sc, N_VEHICLES, (seed,), steps, config, folder,
                               validation_episodes=validation_episodes,
                               name="bdc" if v["is_base"] else f"bdc-{v['name']}",
                               study="sensitivity") for seed in seeds]
            jobs += vjobs
            ctrls = [("bdc", {"checkpoint_dir": str(folder), "seed": str(seed)})
                     for seed in seeds]
            labels = [controller_label(name, opts) for name, opts in ctrls]
            rows = []
            if v["is_base"]:
                rows = [(k, _base_value(k, tuned), 0.0, 0.0) for k in knobs if k != "v2v"]
                if "v2v" in knobs:
                    rows += [("v2v_delay_s", 0.0, 0.0, 0.0)]
                    rows += [("v2v_delay_s", d, d, 0.0) for d in DELAYS_S]
                    rows += [("v2v_packet_loss", 0.0, 0.0, 0.0)]
                    rows += [("v2v_packet_loss", x, 0.0, x) for x in LOSSES]
            else:
                rows = [(v["knob"], v["value"], 0.0, 0.0)]
            for knob, value, delay, loss in rows:
                settings.append({"scenario": sc.label, "knob": knob, "knob_value": value,
                                 "variant": v["name"], "is_base": v["is_base"] and not delay
                                 and not loss, "labels": labels, "controllers": ctrls,
                                 "comm_delay_s": delay, "packet_loss": loss, "training": vjobs})
        settings.append({"scenario": sc.label, "knob": "reference", "knob_value": "",
                         "variant": "ovm", "is_base": False, "labels": ["ovm"],
                         "controllers": [("ovm", {})], "comm_delay_s": 0.0, "packet_loss": 0.0,
                         "training": []})
    return jobs, settings


def _eval_keys(settings: list[dict[str, Any]], seeds: list[int],
               built: Sequence[Scenario]) -> list[Any]:
    """The evaluation runs of ``settings``, on the scenarios the command built (by label)."""
    from benchmark.suite import build_sweep

    by_label = {sc.label: sc for sc in built}
    keys = {k for s in settings
            for k in build_sweep(s["controllers"], [by_label[s["scenario"]]], [N_VEHICLES],
                                 seeds, [s["comm_delay_s"]], [s["packet_loss"]])}
    return sorted(keys, key=lambda k: k.id)


def _summaries(settings: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``settings`` with each training job replaced by its checkpoint's curve summary (each
    checkpoint verified, :func:`marl.checkpoint.load_checkpoint`)."""
    from marl.checkpoint import load_checkpoint

    cache: dict[str, dict[str, float]] = {}
    out = []
    for s in settings:
        summaries = []
        for job in s["training"]:
            path = str(job.file(".pt"))
            if path not in cache:
                cache[path] = load_checkpoint(path, algo=job.algo,
                                              n_vehicles=job.n_vehicles)["curve_summary"]
            summaries.append(cache[path])
        out.append({**s, "training": summaries})
    return out


def _holds_files(folder: Path) -> bool:
    """Whether ``folder`` holds anything but a lock left by an earlier command."""
    from benchmark.folder_lock import LOCK_FILES

    return folder.is_dir() and any(p.name not in LOCK_FILES for p in folder.iterdir())


def _names(text: str, flag: str, valid: tuple[str, ...] | None = None) -> list[str]:
    names = list(dict.fromkeys(x.strip() for x in text.split(",") if x.strip()))
    if not names:
        raise ConfigError(f"{flag}: nothing named")
    for n in names:
        if valid is not None and n not in valid:
            raise UnknownNameError(flag.lstrip("-").rstrip("s"), n, valid)
    return names


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench sensitivity``."""
    from benchmark.suite import seeds_from_episodes
    from commands.policy_training import train_stage
    from commands.run import execute_sweep
    from marl.arithmetic import process_env
    from marl.config import training_device
    from studies.sensitivity import sensitivity_frame, write_report

    args = _parser().parse_args(argv)
    from benchmark.executors import check_ray_address

    check_ray_address(args.ray_address)  # an address that does not answer: refused before work
    built = scenarios_argument(args.scenarios)
    scenarios = [sc.label for sc in built]  # names of checkpoints, settings and the manifest
    knobs = _names(args.knobs, "--knobs", KNOBS)
    try:
        seeds = [int(x) for x in _names(args.seeds, "--seeds")]
    except ValueError:
        raise ConfigError(f"--seeds must be a comma list of integers, got {args.seeds!r}") from None
    for flag, value, low in (("--steps", args.steps, 1), ("--episodes", args.episodes, 1),
                             ("--validation-episodes", args.validation_episodes, 1),
                             ("--workers", args.workers, 1)):
        if value < low:
            raise ConfigError(f"{flag} must be >= {low}, got {value}")
    from infra.limits import MAX_TRAIN_SEED, MAX_TRAIN_STEPS, check_range, check_seeds

    check_seeds(seeds, "--seeds", MAX_TRAIN_SEED)  # training seeds
    check_range(args.steps, "--steps", 1, MAX_TRAIN_STEPS)
    training_device(args.device)  # ConfigError for an unknown device or a missing GPU
    check_arithmetic(args.arithmetic, args.device)
    from benchmark.paths import writable_dir

    out = writable_dir(args.out)
    settings_key = {"scenarios": scenarios, "knobs": knobs, "seeds": seeds, "steps": args.steps,
                    "validation_episodes": args.validation_episodes, "episodes": args.episodes,
                    "arithmetic": args.arithmetic}
    manifest = out / MANIFEST
    if manifest.exists():
        previous = read_json(manifest, "the sensitivity manifest", "remove it or restore it, and "
                             "rerun with --resume (finished training and runs are kept)")
        if not args.resume:
            raise ConfigError(f"{out} already holds a sensitivity study; add --resume to "
                              "complete it, or choose another --out")
        if {"arithmetic": "native", **previous} != settings_key:  # native before the option
            raise ConfigError(f"{out} holds a study with other settings ({previous}); use "
                              "another --out")
    elif _holds_files(out) and not args.resume:
        raise ConfigError(f"{out} is not empty; choose another --out (or --resume)")
    from benchmark.work_folder import command_text, working_in
    from studies.reproduction_report import check_job_files

    out.mkdir(parents=True, exist_ok=True)
    # inside OUT, locked: checkpoint folders in run labels are relative to it, so --out
    # spelled otherwise or a moved folder reruns nothing
    with working_in(out):
        here = Path(".")
        jobs, settings = plan(built, knobs, seeds, args.steps, args.validation_episodes, here)
        check_job_files(jobs)  # a damaged file of a finished job: refused before any work
        write_text(here / MANIFEST, json.dumps(settings_key, indent=1))
        print(f"sensitivity: {len(jobs)} training runs, {len(settings)} settings",
              file=sys.stderr)
        train_stage(jobs, args, reuse_shipped=True)
        eval_seeds = seeds_from_episodes(args.episodes)
        keys = _eval_keys(settings, eval_seeds, built)
        print(f"evaluation: {len(keys)} runs", file=sys.stderr)
        rc = execute_sweep(keys, here / "runs", resume=True, executor=args.executor,
                           workers=args.workers, ray_address=args.ray_address, quiet=True,
                           first_seed=eval_seeds[0], env=process_env(args.arithmetic))
        if rc != 0:
            raise ConfigError(f"some evaluation runs failed (see {out / 'runs' / 'runs.csv'}); "
                              "fix the cause and rerun with --resume")
        runs = read_csv(here / "runs" / "runs.csv", "the runs table", columns=("status",))
        runs = runs[runs["status"] == "ok"]
        df = sensitivity_frame(runs, _summaries(settings))
        write_csv(df, here / "sensitivity.csv")
        report = out / write_report(df, here, command_text("cacc-bench sensitivity", argv),
                                    args.steps, seeds, args.episodes)
    print(f"wrote {out / 'sensitivity.csv'} ({len(df)} rows) and {report}")
    return 0
