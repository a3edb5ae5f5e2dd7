"""Training stage shared by ``cacc-bench reproduce`` and ``cacc-bench sensitivity``.

A job (:class:`marl.training.PolicyJob`) is done when its folder holds its checkpoint with the
same config and budget, trained there or copied from the shipped checkpoints (with a
``.source.json`` saying which). A job interrupted while it trained continues from its snapshot
(:meth:`marl.training.TrainingKey.snapshots`) when the stage runs again.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from marl.training import PolicyJob

#: Training stops at the first update after its step budget: a shipped run counts as having
#: the same budget when its total lies within this fraction above it.
BUDGET_OVERSHOOT = 0.05


def tuned_config(algo: str, config_scenario: str, extra: dict[str, Any], label: str) -> Any:
    """The config of ``algo`` with its tuned options on ``config_scenario`` and ``extra`` on
    top, built and checked once (:func:`marl.training.learner_config`)."""
    from marl.config import tuned_options
    from marl.training import learner_config

    return learner_config(algo, {**tuned_options(algo, config_scenario), **extra},
                          f"{label} (tuned)")


def is_done(job: PolicyJob) -> bool:
    """Finished in the output folder (trained there, or a shipped copy with the same config)."""
    from marl.checkpoint import same_energy_model
    from marl.training import finished

    key = job.key()
    src = job.file(".source.json")
    if src.exists():
        info = json.loads(src.read_text())
        if (info.get("config") == key.stored_config() and info.get("steps", 0) >= job.steps
                and same_energy_model(info) and _same_arithmetic(info, job)):
            return job.file(".pt").exists()
    return finished(key)


def _same_arithmetic(info: dict[str, Any], job: PolicyJob) -> bool:
    """A copied shipped run serves any arithmetic (its weights are fixed: evaluation gives the
    same numbers on every processor); a trained one, only its own (:mod:`marl.arithmetic`)."""
    return info.get("source") == "shipped" or info.get("arithmetic", "native") == job.arithmetic


def shipped_candidates(job: PolicyJob) -> list[Path]:
    """Where a shipped checkpoint of ``job`` may lie: an ablation (its name not its algorithm's)
    in the variant folder of its name; any other in the shipped folder, then in each variant
    folder (the config tells them apart: :func:`shipped_checkpoint`)."""
    from controllers.policy import CHECKPOINT_DIR, VARIANT_DIR

    name = job.file(".pt").name
    if job.name != job.algo:
        return [VARIANT_DIR / job.name / name]
    return [CHECKPOINT_DIR / name, *sorted(VARIANT_DIR.glob(f"*/{name}"))]


def shipped_checkpoint(job: PolicyJob) -> Path | None:
    """The first of :func:`shipped_candidates` with ``job``'s config, budget and energy model
    (verified: a damaged shipped file is refused, :func:`marl.checkpoint.load_checkpoint`)."""
    from marl.checkpoint import load_checkpoint, same_energy_model

    config = job.key().stored_config()
    for path in shipped_candidates(job):
        curve = path.with_suffix("").with_suffix(".curve.csv")
        if not path.exists() or not curve.exists():
            continue
        data = load_checkpoint(path, algo=job.algo, n_vehicles=job.n_vehicles,
                               scenario=job.scenario.id)
        total = data.get("curve_summary", {}).get("total_steps", data.get("steps", 0))
        if data.get("config") == config and same_energy_model(data) and (
                job.steps <= total <= job.steps * (1 + BUDGET_OVERSHOOT)):
            return path
    return None


def _last_commit(path: Path) -> str:
    try:
        return subprocess.run(["git", "log", "-1", "--format=%h", "--", path.name], cwd=path.parent,
                              capture_output=True, text=True, timeout=10,
                              check=True).stdout.strip() or "uncommitted"
    except Exception:
        return "unknown"


def _shipped_name(path: Path) -> str:
    """A shipped file's path as the source records it: relative to the shipped folder (a
    report never prints where this checkout lies)."""
    from controllers.policy import CHECKPOINT_DIR

    try:
        return str(path.resolve().relative_to(CHECKPOINT_DIR.resolve().parent.parent))
    except ValueError:
        return path.name


def _copier(src: Path) -> Any:
    return lambda tmp: shutil.copyfile(src, tmp)


def copy_shipped(job: PolicyJob, path: Path) -> None:
    """Copy a shipped run's files into the job's folder (each atomically, the source file
    last, so an interrupted copy is not taken as done)."""
    from infra.atomic import StagedFiles
    from marl.arithmetic import of_summary
    from marl.checkpoint import load_checkpoint

    job.out.mkdir(parents=True, exist_ok=True)
    data = load_checkpoint(path, algo=job.algo, n_vehicles=job.n_vehicles, scenario=job.scenario.id)
    with StagedFiles() as staged:
        for suffix in (".pt", ".curve.csv", ".log"):
            src = path.parent / job.file(suffix).name
            if src.exists():
                staged.write_with(job.file(suffix), _copier(src))
        staged.write_text(job.file(".source.json"), json.dumps({
            "source": "shipped", "path": _shipped_name(path), "commit": _last_commit(path),
            "config": data["config"], "energy_model": data.get("energy_model"),
            "arithmetic": of_summary(data["curve_summary"]),  # how it was trained
            "steps": int(data["curve_summary"].get("total_steps", 0)),
            "wall_s": data["curve_summary"].get("wall_s"),
        }, indent=1, sort_keys=True))
        staged.commit()


def record_trained(job: PolicyJob) -> None:
    from benchmark.provenance import git_sha
    from infra.atomic import write_text
    from marl.arithmetic import of_summary
    from marl.checkpoint import load_checkpoint

    data = load_checkpoint(job.file(".final.pt"), algo=job.algo, n_vehicles=job.n_vehicles,
                           scenario=job.scenario.id)
    write_text(job.file(".source.json"), json.dumps({
        "source": "trained", "commit": git_sha(), "config": data["config"],
        "arithmetic": of_summary(data["curve_summary"]),
        "energy_model": data.get("energy_model"),
        "steps": int(data["steps"]), "wall_s": data["curve_summary"].get("wall_s"),
    }, indent=1, sort_keys=True))


def train_stage(jobs: list[PolicyJob], args: Any, reuse_shipped: bool) -> None:
    """Train what is missing (``args``: executor, workers, ray_address, arithmetic); with
    ``reuse_shipped``, copy shipped checkpoints of the same config and budget instead."""
    from benchmark.executors import map_jobs
    from benchmark.progress import Progress
    from commands.train import populations, train_job
    from marl.arithmetic import process_env

    mode = getattr(args, "arithmetic", "native")
    jobs = [replace(job, arithmetic=mode) for job in jobs]
    todo = []
    for job in jobs:
        if is_done(job):
            continue
        shipped = shipped_checkpoint(job) if reuse_shipped else None
        if shipped is not None:
            copy_shipped(job, shipped)
        else:
            todo.append(job)
    print(f"training: {len(jobs) - len(todo)} of {len(jobs)} policies ready, {len(todo)} to train",
          file=sys.stderr)
    progress = Progress(len(todo), "training runs")
    by_key = {j.file(".pt"): j for j in todo}
    device = getattr(args, "device", "cpu")  # where to train; the jobs' results do not say
    keys = populations([j.key(device) for j in todo],
                       getattr(args, "population", None), args.executor, args.workers)
    for res in map_jobs(train_job, keys, args.executor, args.workers, args.ray_address,
                        process_env(mode)):
        for run in res["runs"]:
            job = by_key[Path(run["checkpoint"])]
            record_trained(job)
            progress.advance(note=f"{job.name} {job.scenario.label} s{job.seed}")
    progress.close()
