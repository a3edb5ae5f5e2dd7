"""Training stage shared by ``cacc-bench reproduce`` and ``cacc-bench sensitivity``.

A job is a dict (algorithm, scenario, N, seed, folder, config options, budget); a job is done
when its folder holds its checkpoint with the same config and budget, trained there or copied
from the shipped checkpoints (with a ``.source.json`` saying which). A job interrupted while it
trained continues from its snapshot (:meth:`marl.training.TrainingKey.snapshots`) when the
stage runs again.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

#: Training stops at the first update after its step budget: a shipped run counts as having
#: the same budget when its total lies within this fraction above it.
BUDGET_OVERSHOOT = 0.05


def make_job(name: str, algo: str, scenario: str, vehicles: int, seed: int, folder: Path,
             options: dict[str, Any], steps: int, study: str,
             validation_episodes: int = 32) -> dict[str, Any]:
    """One training run: ``name`` (the algorithm, or an ablation/variant of it) trained into
    ``folder`` with config ``options`` for ``steps`` environment steps."""
    return {"name": name, "algo": algo, "scenario": scenario, "vehicles": vehicles,
            "steps": steps, "seed": seed, "out": str(folder), "options": options,
            "progress": False, "study": study, "validation_episodes": validation_episodes}


def tuned_config(algo: str, config_scenario: str, extra: dict[str, Any], label: str
                 ) -> dict[str, Any]:
    """The tuned options of ``algo`` on ``config_scenario`` with ``extra`` on top, checked."""
    from controllers.registry import build_config
    from marl.config import algorithm, tuned_options

    options = {**tuned_options(algo, config_scenario), **extra}
    config = build_config(algorithm(algo).config_cls, options, f"{label} (tuned)")
    return {f: getattr(config, f) for f in options}


def stem(job: dict[str, Any]) -> str:
    from infra.naming import checkpoint_stem

    return checkpoint_stem(job["algo"], job["scenario"], job["vehicles"], job["seed"])


def source_file(job: dict[str, Any]) -> Path:
    return Path(job["out"]) / f"{stem(job)}.source.json"


def is_done(job: dict[str, Any]) -> bool:
    """Finished in the output folder (trained there, or a shipped copy with the same config)."""
    from commands.train import job_key
    from marl.checkpoint import same_energy_model
    from marl.training import finished

    key = job_key(job)
    src = source_file(job)
    if src.exists():
        info = json.loads(src.read_text())
        if (info.get("config") == key.stored_config() and info.get("steps", 0) >= job["steps"]
                and same_energy_model(info) and _same_arithmetic(info, job)):
            return (Path(job["out"]) / f"{stem(job)}.pt").exists()
    return finished(key)


def _same_arithmetic(info: dict[str, Any], job: dict[str, Any]) -> bool:
    """A copied shipped run serves any arithmetic (its weights are fixed: evaluation gives the
    same numbers on every processor); a trained one, only its own (:mod:`marl.arithmetic`)."""
    return info.get("source") == "shipped" or (
        info.get("arithmetic", "native") == job.get("arithmetic", "native"))


def shipped_candidates(job: dict[str, Any]) -> list[Path]:
    """Where a shipped checkpoint of ``job`` may lie: an ablation (its name not its algorithm's)
    in the variant folder of its name; any other in the shipped folder, then in each variant
    folder (the config tells them apart: :func:`shipped_checkpoint`)."""
    from controllers.policy import CHECKPOINT_DIR, VARIANT_DIR

    name = f"{stem(job)}.pt"
    if job["name"] != job["algo"]:
        return [VARIANT_DIR / job["name"] / name]
    return [CHECKPOINT_DIR / name, *sorted(VARIANT_DIR.glob(f"*/{name}"))]


def shipped_checkpoint(job: dict[str, Any]) -> Path | None:
    """The first of :func:`shipped_candidates` with ``job``'s config, budget and energy model
    (verified: a damaged shipped file is refused, :func:`marl.checkpoint.load_checkpoint`)."""
    from commands.train import job_key
    from marl.checkpoint import load_checkpoint, same_energy_model

    config = job_key(job).stored_config()
    for path in shipped_candidates(job):
        curve = path.with_suffix("").with_suffix(".curve.csv")
        if not path.exists() or not curve.exists():
            continue
        data = load_checkpoint(path, algo=job["algo"], n_vehicles=job["vehicles"],
                               scenario=job["scenario"])
        total = data.get("curve_summary", {}).get("total_steps", data.get("steps", 0))
        if data.get("config") == config and same_energy_model(data) and (
                job["steps"] <= total <= job["steps"] * (1 + BUDGET_OVERSHOOT)):
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


def copy_shipped(job: dict[str, Any], path: Path) -> None:
    """Copy a shipped run's files into the job's folder (each atomically, the source file
    last, so an interrupted copy is not taken as done)."""
    from infra.atomic import StagedFiles
    from marl.arithmetic import of_summary
    from marl.checkpoint import load_checkpoint

    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    name = stem(job)
    data = load_checkpoint(path, algo=job["algo"], n_vehicles=job["vehicles"],
                           scenario=job["scenario"])
    with StagedFiles() as staged:
        for suffix in (".pt", ".curve.csv", ".log"):
            src = path.parent / f"{name}{suffix}"
            if src.exists():
                staged.write_with(out / f"{name}{suffix}", _copier(src))
        staged.write_text(source_file(job), json.dumps({
            "source": "shipped", "path": _shipped_name(path), "commit": _last_commit(path),
            "config": data["config"], "energy_model": data.get("energy_model"),
            "arithmetic": of_summary(data["curve_summary"]),  # how it was trained
            "steps": int(data["curve_summary"].get("total_steps", 0)),
            "wall_s": data["curve_summary"].get("wall_s"),
        }, indent=1, sort_keys=True))
        staged.commit()


def record_trained(job: dict[str, Any]) -> None:
    from benchmark.provenance import git_sha
    from infra.atomic import write_text
    from marl.arithmetic import of_summary
    from marl.checkpoint import load_checkpoint

    data = load_checkpoint(Path(job["out"]) / f"{stem(job)}.final.pt", algo=job["algo"],
                           n_vehicles=job["vehicles"], scenario=job["scenario"])
    write_text(source_file(job), json.dumps({
        "source": "trained", "commit": git_sha(), "config": data["config"],
        "arithmetic": of_summary(data["curve_summary"]),
        "energy_model": data.get("energy_model"),
        "steps": int(data["steps"]), "wall_s": data["curve_summary"].get("wall_s"),
    }, indent=1, sort_keys=True))


def train_stage(jobs: list[dict[str, Any]], args: Any, reuse_shipped: bool) -> None:
    """Train what is missing (``args``: executor, workers, ray_address, arithmetic); with
    ``reuse_shipped``, copy shipped checkpoints of the same config and budget instead."""
    from benchmark.executors import map_jobs
    from benchmark.progress import Progress
    from commands.train import job_key, populations, train_job
    from marl.arithmetic import process_env

    mode = getattr(args, "arithmetic", "native")
    jobs = [{**job, "arithmetic": mode} for job in jobs]
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
    by_key = {str(Path(j["out"]) / f"{stem(j)}.pt"): j for j in todo}
    device = getattr(args, "device", "cpu")  # where to train; the jobs' results do not say
    keys = populations([job_key({**j, "device": device}) for j in todo],
                       getattr(args, "population", None), args.executor, args.workers)
    for res in map_jobs(train_job, keys, args.executor, args.workers, args.ray_address,
                        process_env(mode)):
        for run in res["runs"]:
            job = by_key[str(Path(run["checkpoint"]))]
            record_trained(job)
            progress.advance(note=f"{job['name']} {job['scenario']} s{job['seed']}")
    progress.close()
