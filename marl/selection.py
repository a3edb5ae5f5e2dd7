"""Training with validation and checkpoint selection: :func:`run_training` (one run) and
:func:`run_population` (K runs at once, each as alone).

Every ``eval_every_steps`` (and at the end) a run's acting network, rounded to the checkpoint's
precision, is evaluated on the validation seeds in both modes by the benchmark's own closed loop
(an :data:`Evaluator`); the snapshot kept is the evaluated one with the fewest collisions, then
the best reward, in ``selection_mode`` (a tie goes to the later one). When the run finishes its
learning curve, final weights and kept snapshot are written together
(:func:`marl.checkpoint.write_run`). The trainer underneath: :class:`marl.a2c.Trainer` (K runs
at once; one run is a population of one).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from envs.params import EVAL_MODES
from envs.scenarios import Scenario, as_scenario
from infra.errors import ConfigError, TrainingDivergedError
from infra.naming import checkpoint_stem
from marl import arithmetic
from marl.a2c import Run, Trainer
from marl.checkpoint import (
    CURVE_EVAL_KEYS,
    WEIGHT_DTYPE,
    Snapshots,
    checkpoint_payload,
    plain_state,
    write_run,
)
from marl.config import A2CConfig, Algorithm
from marl.networks import AgentNet, execution_bits_per_agent_step, training_step_bits_per_agent

ProgressFn = Callable[[int, int, dict[str, float]], None]

#: Signature of the validation evaluator :func:`run_training` takes: ``(net, mode)`` -> mean over
#: the validation episodes of ``reward`` and ``tracking_reward``, and ``collisions`` (a count).
#: The benchmark's own closed loop provides it (:func:`benchmark.policy_eval.validation_evaluator`).
Evaluator = Callable[["AgentNet", str], dict[str, float]]


@dataclass
class TrainResult:
    """What :func:`run_training` returns."""

    algo: str
    scenario: str
    n_vehicles: int
    seed: int
    steps: int
    episodes: int
    wall_s: float
    env_steps_per_s: float
    bits: dict[str, float]
    curve: list[dict[str, float]] = field(default_factory=list)
    checkpoint: Path | None = None
    final_checkpoint: Path | None = None
    curve_csv: Path | None = None
    #: The kept snapshot's checkpoint contents, held in memory until the run finishes.
    kept: dict[str, Any] | None = field(default=None, repr=False)


def run_training(
    algo: Algorithm,
    config: A2CConfig,
    scenario: str | Scenario,
    n_vehicles: int = 8,
    total_steps: int = 600_000,
    seed: int = 0,
    out_dir: str | Path | None = None,
    progress: ProgressFn | None = None,
    log: Callable[[str], None] | None = None,
    schedule_steps: int | None = None,
    evaluate: Evaluator | None = None,
    device: str | torch.device = "cpu",
    snapshots: Snapshots | None = None,
) -> TrainResult:
    """Train ``algo`` for ``total_steps`` environment steps; write checkpoints and curve CSV.

    Every ``config.eval_every_steps`` (and at the end) the policy is evaluated on the validation
    seeds in both modes by ``evaluate``; the snapshot kept as ``<stem>.pt`` is the best in
    ``config.selection_mode`` (fewest collisions, then mean reward; a tie goes to the later
    snapshot). The final weights are saved as ``<stem>.final.pt``. One run of
    :func:`run_population`.

    Parameters
    ----------
    scenario : Scenario or str
        The scenario, built (or its id); the checkpoints are named by its id.
    schedule_steps : int, optional
        Run length the entropy schedule assumes (default ``total_steps``); the throughput
        measurement runs the first steps of a 6e5-step run with it.
    out_dir : path, optional
        Where ``<stem>.pt``, ``<stem>.final.pt`` and ``<stem>.curve.csv`` go (None: write
        nothing, no evaluation; used by the throughput measurement).
    progress : callable(steps, total_steps, info), optional
        Called after every batch of episodes.
    log : callable(str), optional
        Receives one line per evaluation and a summary.
    evaluate : callable(net, mode) -> dict, optional
        Validation evaluator (required with ``out_dir``): the benchmark's closed loop on the
        validation seeds, :func:`benchmark.policy_eval.validation_evaluator`.
    device : str or torch.device
        Where to train (:func:`training_device`); validation and checkpoints stay on the CPU.
    snapshots : marl.checkpoint.Snapshots, optional
        The run's resumable snapshot: it continues from the file where there is one, and keeps
        one there every so often (removed when the run's files are written).
    """
    return run_population(algo, [config], scenario, n_vehicles, total_steps, [seed], out_dir,
                          progress, [log], schedule_steps, evaluate, device,
                          None if snapshots is None else [snapshots])[0]


def run_population(
    algo: Algorithm,
    configs: Sequence[A2CConfig],
    scenario: str | Scenario,
    n_vehicles: int = 8,
    total_steps: int = 600_000,
    seeds: Sequence[int] = (0,),
    out_dir: str | Path | None = None,
    progress: ProgressFn | None = None,
    logs: Sequence[Callable[[str], None] | None] | None = None,
    schedule_steps: int | None = None,
    evaluate: Evaluator | None = None,
    device: str | torch.device = "cpu",
    snapshots: Sequence[Snapshots | None] | None = None,
) -> list[TrainResult]:
    """Train K runs of ``algo`` at once (one :class:`marl.a2c.Trainer`): run ``k`` with
    ``configs[k]`` and ``seeds[k]``, each evaluated, selected and saved exactly as
    :func:`run_training` alone.

    ``snapshots[k]`` (optional) is run k's resumable snapshot: the run continues from it where
    the file exists (each run from its own: a run trains as it would alone, whatever the
    others do) and keeps one at the end of a batch every so often
    (:meth:`marl.a2c.Trainer.run_state`, with its curve, validation schedule and kept snapshot).

    A run stops at its own budget; one whose weights become non-finite stops there while the
    others go on, and the error is raised after they finished (their checkpoints are written).
    ``logs[k]`` receives run k's lines; ``progress`` is called per run and batch. Wall time and
    throughput of each result are the population's (its steps over the population's time).
    """
    scenario = as_scenario(scenario)  # built by the caller (or here, from an id), once
    if out_dir is not None and evaluate is None:
        raise ConfigError(
            "run_training with an output folder needs a validation evaluator: pass "
            "evaluate=benchmark.policy_eval.validation_evaluator(algo, scenario, N)"
        )
    if len({int(s) for s in seeds}) != len(seeds):
        raise ConfigError(f"the runs of a population need distinct seeds, got {list(seeds)}")
    trainer = Trainer(algo, list(configs), scenario.id, n_vehicles, list(seeds), device, scenario)
    runs = trainer.runs
    log_of = list(logs) if logs is not None else [None] * len(runs)
    for r in runs:
        r.total_steps = schedule_steps or total_steps
    curves: list[list[dict[str, float]]] = [[] for _ in runs]
    next_eval = [r.config.eval_every_steps if out_dir is not None else math.inf for r in runs]
    best = [(-math.inf, -math.inf) for _ in runs]
    results = [TrainResult(algo.name, scenario.id, n_vehicles, r.seed, 0, 0, 0.0, 0.0, {},
                           curves[r.index]) for r in runs]
    views: dict[int, AgentNet] = {}  # each run's acting network, reused at every validation
    snaps = list(snapshots) if snapshots is not None else [None] * len(runs)
    # seconds a resumed run spent before, in all and training (not validating)
    before = [(0.0, 0.0) for _ in runs]
    for r, snap in zip(runs, snaps, strict=True):
        if snap is None:
            continue
        plain_state(r.hook_state, (r.generator,))  # what a snapshot cannot hold fails at once
        state = snap.read()
        if state is None:
            continue
        trainer.restore_run(r, state["run"])
        curves[r.index].extend(dict(row) for row in state["curve"])
        next_eval[r.index], best[r.index] = state["next_eval"], tuple(state["best"])
        results[r.index].kept = state["kept"]
        before[r.index] = (float(state["seconds"][0]), float(state["seconds"][1]))
        log = log_of[r.index]
        if log is not None:
            log(f"resumed from {snap.path}: {r.steps} steps, {r.episodes} episodes")
    t0 = time.perf_counter()
    evaluating = 0.0  # seconds spent in validation, not training

    def on_batch(r: Run, steps: int, train_reward: float) -> bool:
        nonlocal evaluating
        k, cfg, log = r.index, r.config, log_of[r.index]
        row: dict[str, float] = {
            "episode": r.episodes,
            "steps": r.steps,
            "train_reward": train_reward,
            **{f"eval_{key}_{m}": math.nan for m in EVAL_MODES for key in CURVE_EVAL_KEYS},
        }
        curves[k].append(row)
        last = r.steps >= total_steps
        if r.steps >= next_eval[k] or (out_dir is not None and last):
            assert evaluate is not None
            te = time.perf_counter()
            net = acting_net(trainer, r, views)
            for mode in EVAL_MODES:
                ev = evaluate(net, mode)
                for key in CURVE_EVAL_KEYS:
                    row[f"eval_{key}_{mode}"] = float(ev[key])
            next_eval[k] = r.steps + cfg.eval_every_steps
            # fewest collisions first: a colliding episode ends early, so its mean reward
            # over the steps it ran can look better than a safe one's; a tie keeps the
            # later snapshot
            select = cfg.selection_mode
            score = (-row[f"eval_collisions_{select}"], row[f"eval_reward_{select}"])
            better = score >= best[k]
            best[k] = max(best[k], score)
            now = time.perf_counter()
            _finish(results[k], trainer, r, net, before[k][0] + now - t0,
                    before[k][1] + now - t0 - evaluating - (now - te), out_dir, better)
            evaluating += time.perf_counter() - te
            if log is not None:
                log(
                    f"steps {r.steps} episodes {r.episodes} train {train_reward:.2f} "
                    + " ".join(
                        f"{m} {row[f'eval_reward_{m}']:.2f} "
                        f"({row[f'eval_collisions_{m}']:.0f} collisions)" for m in EVAL_MODES
                    )
                    + (" [kept]" if better else "")
                    + f" consensus bits/agent {r.bits['consensus']:.0f}"
                )
        if progress is not None:
            progress(r.steps, total_steps, row)
        snap = snaps[k]
        if snap is not None and not last and snap.due():
            now = time.perf_counter()
            snap.write(r.steps, {
                "run": trainer.run_state(r), "curve": curves[k], "next_eval": next_eval[k],
                "best": list(best[k]), "kept": results[k].kept,
                "seconds": [before[k][0] + now - t0, before[k][1] + now - t0 - evaluating]})
        return not last

    trainer.train(on_batch)
    train_time = time.perf_counter() - t0 - evaluating
    wall = time.perf_counter() - t0
    for r in runs:
        if r.failed is not None:
            continue
        res = results[r.index]
        _finish(res, trainer, r, acting_net(trainer, r, views), before[r.index][0] + wall,
                before[r.index][1] + train_time, out_dir, False, final=True)
        snap = snaps[r.index]
        if snap is not None:  # the run's files are written: they are the product
            snap.remove()
        log = log_of[r.index]
        if log is not None:
            log(
                f"done: {r.steps} steps in {res.wall_s:.0f} s "
                f"({res.env_steps_per_s:.0f} env steps/s training"
                + (f", population of {len(runs)}" if len(runs) > 1 else "")
                + f"), execution "
                f"{res.bits['execution_bits_per_vehicle_per_s']:.0f} bit/vehicle/s, training "
                f"bits sent per agent: {res.bits['training_step_bits_per_agent_step']:.0f} per "
                f"step (blocks, messages, action for the critics, message gradients) and "
                f"consensus {res.bits['training_consensus_bits_per_agent']:.0f} in all "
                f"(QSGD applied locally: {res.bits['local_qsgd_payload_bits_per_agent']:.0f} "
                f"bits of payload, not sent); checkpoint {res.checkpoint}"
            )
    failed = [r.failed for r in runs if r.failed is not None]
    if failed:
        raise TrainingDivergedError("; ".join(failed))
    return results


def acting_net(trainer: Trainer, run: Run, views: dict[int, AgentNet] | None = None) -> AgentNet:
    """The run's acting network as its checkpoint stores it: N agents, no critic, weights
    rounded to the checkpoint's precision (validation scores what is saved, and a saved
    snapshot scores in the harness exactly what validation measured). ``views`` keeps one
    network per run to refill at the next call."""
    views = {} if views is None else views
    view = views.get(run.index)
    if view is None:
        with torch.device("cpu"):  # validation and checkpoints on the CPU
            view = trainer.algo.build_net(run.config, trainer.n_vehicles, False,
                                          torch.Generator().manual_seed(0))
        view.requires_grad_(False)
        views[run.index] = view
    whole = dict(trainer.net.named_parameters())
    with torch.no_grad():
        for name, p in view.named_parameters():
            p.copy_(whole[name][run.rows].to(WEIGHT_DTYPE))
    return view


def _finish(
    result: TrainResult,
    trainer: Trainer,
    run: Run,
    net: AgentNet,
    wall_s: float,
    train_s: float,
    out_dir: str | Path | None,
    save_weights: bool,
    final: bool = False,
) -> None:
    """Fill the run's result numbers; with an output folder, keep the snapshot in memory when
    ``save_weights`` (a new best on the validation seeds) and, when ``final``, write the run's
    files: the curve, the final weights (``net``: the run's acting network) and the kept
    snapshot with the run's totals.

    Nothing is written before the run finishes, and the three files are written together
    (:func:`marl.checkpoint.write_run`).
    """
    exec_bits = execution_bits_per_agent_step(net)
    result.steps, result.episodes = run.steps, run.episodes
    result.wall_s = wall_s
    result.env_steps_per_s = run.steps / max(train_s, 1e-9)
    result.bits = {
        "execution_bits_per_agent_step": float(exec_bits),
        "execution_bits_per_vehicle_per_s": exec_bits / run.env.params.dt_s,
        "training_step_bits_per_agent_step": float(training_step_bits_per_agent(net)),
        "training_consensus_bits_per_agent": run.bits["consensus"],
        "local_qsgd_payload_bits_per_agent": run.bits["qsgd_local"],
        "updates": float(run.updates),
    }
    if out_dir is None:
        return
    out = Path(out_dir)
    stem = checkpoint_stem(trainer.algo.name, trainer.scenario_id, trainer.n_vehicles, run.seed)
    curve = result.curve
    result.curve_csv = out / f"{stem}.curve.csv"
    mode = run.config.selection_mode
    evals = [r for r in curve if not math.isnan(r[f"eval_reward_{mode}"])]
    summary = {
        "final_train_reward": curve[-1]["train_reward"] if curve else math.nan,
        "final_eval_reward": evals[-1][f"eval_reward_{mode}"] if evals else math.nan,
        "best_eval_reward": max(r[f"eval_reward_{mode}"] for r in evals) if evals else math.nan,
        "wall_s": wall_s,
        "env_steps_per_s": result.env_steps_per_s,
        "selected_at_steps": float(run.steps),
        **{f"selected_eval_{k}_{m}": (evals[-1][f"eval_{k}_{m}"] if evals else math.nan)
           for m in EVAL_MODES for k in CURVE_EVAL_KEYS},
        **result.bits,
        **arithmetic.summary(arithmetic.current()),  # portable runs say so; native: no key
    }
    result.checkpoint = out / f"{stem}.pt"

    def payload() -> dict[str, Any]:
        return checkpoint_payload(
            algo=trainer.algo.name,
            config=dataclasses.asdict(run.config),
            scenario=trainer.scenario_id,
            n_vehicles=trainer.n_vehicles,
            seed=run.seed,
            steps=run.steps,
            curve_summary={**summary, "total_steps": float(run.steps)},
            weights=net.acting_state_dict(),
        )

    if save_weights:
        result.kept = payload()
    if not final:
        return
    final_data = payload()
    kept = result.kept if result.kept is not None else final_data
    # the kept weights with the run's totals (its own selected_* numbers stay)
    selected = {k: v for k, v in kept["curve_summary"].items() if k.startswith("selected_")}
    kept = {**kept, "curve_summary": {**kept["curve_summary"], **final_data["curve_summary"],
                                      **selected, "total_steps": float(run.steps)}}
    result.final_checkpoint = out / f"{stem}.final.pt"
    write_run(out, stem, curve, {".final.pt": final_data, ".pt": kept})
