"""``cacc-bench tune``: the same hyper-parameter budget for every MARL algorithm, by Optuna.

For every algorithm x scenario one Optuna study (TPE, seeded) runs ``--trials`` trainings of
``--steps`` environment steps each; a trial's score is that of the snapshot the run keeps (chosen
on the validation seeds in the sampled mode, the benchmark's default):

    score = validation reward - 10,000 x validation collisions

so any collision-free config beats any colliding one (rewards differ by far less than 10,000),
then the better mean reward wins. The 50 evaluation seeds are never touched. The first trial of
every study is the algorithm's default config, so tuning never ends below it.

Search space (the same for all seven; ``consensus_eps`` only where the algorithm has it):
``lr_scale`` log-uniform in [1, 8]; ``entropy_coef_final`` log-uniform in [5e-4, 5e-2];
``power_baseline`` in {paper (0 kW), cruise (P(v*, 0))}; ``advantage_norm`` in {off, on};
``consensus_eps`` log-uniform in [1e-4, 1e-2] (DCEA, BDC).

The shared-policy learners ``ippo``, ``mappo`` and ``ippo-bdc`` (:mod:`marl.ppo`) get the same
budget (trials, steps, seeds, score) over their own knobs: ``lr`` log-uniform in [1e-4, 3e-3];
``init_log_std`` uniform in [-3, -1]; ``gamma`` in {0.99, 0.995}; ``n_envs`` in {64, 256};
``reward_alpha`` in {0, 0.5}; for ``ippo-bdc`` also ``consensus_eps`` log-uniform in [1e-4,
1e-2], as for BDC. ``--set KEY=VALUE`` fixes a config field of theirs in every trial
(for example ``--set prior=cacc``, the residual variant) and is recorded with the best config.

Trials 1..3 are random draws that every study shares (sampler seed ``seed + k``), then TPE
proposes from the study's own results.

Resumable: each study is an SQLite file under ``OUT/studies``; a rerun with the same options
and ``--resume`` skips complete trials and redoes an interrupted one (without ``--resume`` or
``--overwrite``, which tunes again from the first trial, an ``OUT`` holding its studies or
results is refused: :func:`commands.train.check_finished`). Trial k of a study draws with
sampler seed ``seed + k``, so an interrupted and resumed study proposes what an uninterrupted
one would.
Studies run in parallel on the harness executors (``--executor process --workers K``); trials
within a study run in order. Writes ``OUT/trials.csv`` (every trial) and
``OUT/tuned_configs.json`` (the best config per algorithm and scenario, with its score, the
budget and the command; ``marl/tuned_configs.json`` is the shipped copy that ``cacc-bench train
--tuned`` reads).
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmark.export import write_csv
from commands.cli import command_parser
from envs.scenarios import Scenario
from infra.errors import ConfigError, UnknownNameError
from infra.limits import step_count
from marl.learners import PPO_LEARNERS

#: Weight of one colliding validation episode in a trial's score.
COLLISION_PENALTY = 10_000.0
#: Trials drawn at random (after the default) before TPE models the results; with sampler seed
#: ``seed + k`` every study draws the same random configs, so the algorithms start equal.
STARTUP_TRIALS = 4
#: Most trials per study.
MAX_TRIALS = 1000
#: Algorithms with a consensus step size (``consensus_eps`` searched in both families).
EPS_ALGOS = ("dcea", "bdc", "ippo-bdc")


#: Learners of one shared policy that ``tune`` also tunes (their own search space): the ``ppo``
#: family of the learner registry.
SHARED_TUNED = PPO_LEARNERS
#: The config fields their search space draws (``--set`` cannot fix these: each trial's value
#: would replace it).
SHARED_SEARCHED = ("lr", "init_log_std", "gamma", "n_envs", "reward_alpha", "consensus_eps")


#: The episodes stepped together that a shared-policy trial draws from.
SHARED_N_ENVS = (64, 256)


def search_space(trial: Any, algo: str) -> dict[str, Any]:
    """Config overrides of one trial (the same ranges for every algorithm of a family)."""
    opts: dict[str, Any]
    if algo in SHARED_TUNED:
        opts = {
            "lr": trial.suggest_float("lr", 1e-4, 3e-3, log=True),
            "init_log_std": trial.suggest_float("init_log_std", -3.0, -1.0),
            "gamma": trial.suggest_categorical("gamma", [0.99, 0.995]),
            "n_envs": trial.suggest_categorical("n_envs", list(SHARED_N_ENVS)),
            "reward_alpha": trial.suggest_categorical("reward_alpha", [0.0, 0.5]),
        }
    else:
        opts = {
            "lr_scale": trial.suggest_float("lr_scale", 1.0, 8.0, log=True),
            "entropy_coef_final": trial.suggest_float("entropy_coef_final", 5e-4, 5e-2,
                                                      log=True),
            "power_baseline_kw": {"paper": 0.0, "cruise": None}[
                trial.suggest_categorical("power_baseline", ["paper", "cruise"])
            ],
            "advantage_norm": trial.suggest_categorical("advantage_norm", [False, True]),
        }
    if algo in EPS_ALGOS:
        opts["consensus_eps"] = trial.suggest_float("consensus_eps", 1e-4, 1e-2, log=True)
    return opts


def default_params(algo: str) -> dict[str, Any]:
    """The search-space point of the algorithm's default config (every study's first trial)."""
    cfg: Any
    if algo in SHARED_TUNED:
        from marl.ppo_nets import PPOConfig

        cfg = PPOConfig()
        params = {"lr": cfg.lr, "init_log_std": cfg.init_log_std, "gamma": cfg.gamma,
                  "n_envs": cfg.n_envs, "reward_alpha": cfg.reward_alpha}
    else:
        from marl.config import algorithm

        cfg = algorithm(algo).config_cls()
        params = {
            "lr_scale": cfg.lr_scale,
            "entropy_coef_final": cfg.entropy_coef_final,
            "power_baseline": "paper" if cfg.power_baseline_kw == 0.0 else "cruise",
            "advantage_norm": cfg.advantage_norm,
        }
    if algo in EPS_ALGOS:
        params["consensus_eps"] = cfg.consensus_eps
    return params


def trial_score(summary: dict[str, float]) -> float:
    """Score of a run from its kept snapshot's sampled validation numbers."""
    return summary["selected_eval_reward_sampled"] - COLLISION_PENALTY * summary[
        "selected_eval_collisions_sampled"
    ]


def _parser() -> argparse.ArgumentParser:
    from marl.learners import PAPER_ALGORITHMS

    p = command_parser("tune", "Tune every MARL algorithm with the same budget (Optuna, "
                       "validation seeds).")
    p.add_argument("--algos", default=",".join(PAPER_ALGORITHMS),
                   help="comma list of algorithms (default: all seven; also ippo, mappo, "
                        "ippo-bdc)")
    p.add_argument("--scenarios", default="catchup-v1,slowdown-v1",
                   help="comma list of scenarios (default catchup-v1,slowdown-v1)")
    p.add_argument("--vehicles", type=int, default=8, help="followers N (default 8)")
    p.add_argument("--trials", type=int, default=8, help="trials per study (default 8)")
    p.add_argument("--steps", type=step_count, default=200_000,
                   help="environment steps per trial (default 2e5)")
    p.add_argument("--seed", type=int, default=0,
                   help="sampler seed and training seed of the trials (default 0)")
    p.add_argument("--out", default="results/tune", help="output folder (default results/tune)")
    p.add_argument("--executor", choices=("serial", "process", "ray"), default="serial",
                   help="how studies run side by side (default serial)")
    p.add_argument("--workers", type=int, default=2, help="processes or Ray CPUs (default 2)")
    p.add_argument("--ray-address", default=None, help="attach to this Ray cluster")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="fix a config field of ippo/mappo/ippo-bdc in every trial "
                        "(repeatable)")
    p.add_argument("--resume", action="store_true",
                   help="complete the studies in --out: keep their complete trials, redo an "
                        "interrupted one, run the missing ones")
    p.add_argument("--overwrite", action="store_true",
                   help="tune again from the first trial: delete the studies in --out this "
                        "command runs, and its trials.csv and tuned_configs.json")
    return p


@dataclass(frozen=True)
class StudyJob:
    """One Optuna study: ``trials`` trainings of ``algo`` on ``scenario`` with N followers,
    built and checked once at the command line (it pickles: the executors hand it to their
    workers as it is).

    Attributes
    ----------
    algo : str
        A learner of :data:`marl.learners.PAPER_ALGORITHMS` or :data:`SHARED_TUNED`.
    scenario : Scenario
        Built (:func:`commands.cli.scenarios_argument`); the study is named by its label.
    vehicles, trials, steps, seed : int
        Followers N, trials, environment steps per trial, sampler and training seed.
    out : Path
        The tuning folder (the study file under ``studies/``, the trials under ``trials/``).
    fixed : dict
        ``--set`` fields of a shared learner fixed in every trial (untyped strings, typed by
        :func:`marl.training.learner_config`).
    """

    algo: str
    scenario: Scenario
    vehicles: int
    trials: int
    steps: int
    seed: int
    out: Path
    fixed: dict[str, str] = field(default_factory=dict, hash=False)

    @property
    def name(self) -> str:
        """The study's name (its file's stem)."""
        return f"{self.algo}__{self.scenario.label}__n{self.vehicles}"


def _study_job(job: StudyJob) -> list[dict]:
    """Run a study's missing trials (top level, so process and Ray executors can run it)."""
    import optuna
    import torch

    from commands.cli import no_space

    torch.set_num_threads(1)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    name, out = job.name, job.out
    (out / "studies").mkdir(parents=True, exist_ok=True)
    db = out / "studies" / f"{name}.sqlite3"
    try:
        return _run_study(job, name, out, f"sqlite:///{db}")
    except Exception as exc:
        # Optuna's error wraps SQLAlchemy's, which wraps sqlite3's (90 lines): its cause found
        causes: list[BaseException] = []
        cause: BaseException | None = exc
        while cause is not None and len(causes) < 20:
            causes.append(getattr(cause, "orig", None) or cause)
            cause = cause.__cause__ or cause.__context__
        full = next((c for c in causes if no_space(c) and not isinstance(c, OSError)), None)
        if full is None:  # another error, or a file's (cli's line names it)
            raise
        raise ConfigError(
            f"tuning into {out} stopped: its study file {db} could not be written ({full}: a "
            "full disk or a file-size limit); complete trials were kept: free some space and "
            "rerun with --resume") from None


def _run_study(job: StudyJob, name: str, out: Path, storage: str) -> list[dict]:
    """The trials of :func:`_study_job`'s study, in ``storage``."""
    import optuna

    from benchmark.policy_eval import validation_evaluator
    from infra.interrupt import held, raise_if_interrupted
    from marl.checkpoint import load_checkpoint
    from marl.config import algorithm
    from marl.selection import run_training
    from marl.training import learner_config

    algo_name, scenario, n = job.algo, job.scenario, job.vehicles
    study = optuna.create_study(study_name=name, storage=storage, direction="maximize",
                                load_if_exists=True)
    meta: dict[str, Any] = {"steps": job.steps, "seed": job.seed, "vehicles": n}
    if job.fixed:
        meta["fixed"] = job.fixed
    if study.user_attrs.get("budget", meta) != meta:
        raise ConfigError(
            f"study {name} in {out} was run with {study.user_attrs['budget']}, not {meta}; "
            "use the same options, --overwrite to tune it again, or another --out"
        )
    study.set_user_attr("budget", meta)
    for t in study.get_trials(deepcopy=False):
        if t.state == optuna.trial.TrialState.RUNNING:  # interrupted: discard, redo
            study._storage.set_trial_state_values(t._trial_id, optuna.trial.TrialState.FAIL)
    shared = algo_name in SHARED_TUNED
    algo = None if shared else algorithm(algo_name)

    def complete() -> list[Any]:
        return study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))

    while len(complete()) < job.trials:
        k = len(complete())
        study.sampler = optuna.samplers.TPESampler(seed=job.seed + k,
                                                   n_startup_trials=STARTUP_TRIALS)
        if k == 0 and not study.get_trials(states=(optuna.trial.TrialState.WAITING,)):
            study.enqueue_trial(default_params(algo_name))
        with held():  # a trial is in the study only with a try that ends it
            trial = study.ask()
        try:
            raise_if_interrupted()
            options = search_space(trial, algo_name)
            run_dir = out / "trials" / name / f"t{k:03d}"
            if shared:
                summary = _shared_trial(job, options, run_dir)
                options = {**job.fixed, **options}
            else:
                assert algo is not None
                config = learner_config(algo_name, options, f"{algo_name} (tune)")
                result = run_training(algo, config, scenario, n, job.steps, job.seed, run_dir,
                                      evaluate=validation_evaluator(algo_name, scenario, n))
                assert result.checkpoint is not None
                summary = load_checkpoint(result.checkpoint)["curve_summary"]
            with held():  # its attributes and score recorded together, or not at all
                trial.set_user_attr("options", {k2: v for k2, v in options.items()})
                for key in ("selected_eval_reward_sampled", "selected_eval_collisions_sampled",
                            "selected_eval_reward_greedy", "selected_eval_collisions_greedy",
                            "selected_at_steps"):
                    trial.set_user_attr(key, summary[key])
                study.tell(trial, trial_score(summary))
        except KeyboardInterrupt:  # the study records the trial in flight as failed, then stops
            with held():
                study.tell(trial, state=optuna.trial.TrialState.FAIL)
            raise
        raise_if_interrupted()  # a signal during the recording: the trial is complete
    # "trial" counts complete trials (an interrupted, redone trial keeps its place);
    # "optuna_trial" is Optuna's number in the study file
    return [
        {"algo": algo_name, "scenario": scenario.label, "vehicles": n, "trial": k,
         "optuna_trial": t.number, "score": t.value, **t.params,
         **{f"config.{key}": v for key, v in t.user_attrs["options"].items()},
         **{key: v for key, v in t.user_attrs.items() if key != "options"}}
        for k, t in enumerate(complete()[: job.trials])
    ]


def _shared_trial(job: StudyJob, options: dict[str, Any], run_dir: Path) -> dict[str, float]:
    """Train one ``ippo``/``mappo`` trial (fixed ``--set`` fields, then the trial's) and return
    its kept snapshot's validation numbers under the paper learners' summary keys."""
    from commands.train import train_job
    from marl.checkpoint import load_checkpoint
    from marl.training import TrainingKey, finished, learner_config

    key = TrainingKey(job.algo, job.scenario, job.vehicles, (job.seed,), job.steps,
                      learner_config(job.algo, {**job.fixed, **options}), run_dir)
    if not finished(key):  # a trial interrupted after its files were written is not redone
        train_job(key)
    best = load_checkpoint(key.finished_file(job.seed))["curve_summary"]
    return {"selected_eval_reward_sampled": best["best_reward"],
            "selected_eval_collisions_sampled": best["best_collisions"],
            "selected_eval_reward_greedy": math.nan, "selected_eval_collisions_greedy": math.nan,
            "selected_at_steps": best["best_steps"]}


def main(argv: list[str]) -> int:
    """Entry point: ``cacc-bench tune [--algos ...] [--trials 8] [--steps 200000]``."""
    import pandas as pd

    from benchmark.executors import map_jobs
    from benchmark.progress import Progress
    from commands.cli import scenarios_argument
    from envs.scenarios import check_vehicles
    from marl.learners import PAPER_ALGORITHMS

    args = _parser().parse_args(argv)
    from benchmark.executors import check_ray_address

    check_ray_address(args.ray_address)  # an address that does not answer: refused before work
    from commands.train import check_finished, check_resume_overwrite

    check_resume_overwrite(args.resume, args.overwrite)
    algos = [a.strip() for a in args.algos.split(",") if a.strip()]
    for a in algos:
        if a not in (*PAPER_ALGORITHMS, *SHARED_TUNED):
            raise UnknownNameError("algorithm", a, (*PAPER_ALGORITHMS, *SHARED_TUNED))
    fixed: dict[str, str] = {}
    if args.overrides:
        if not all(a in SHARED_TUNED for a in algos):
            raise ConfigError(f"--set fixes a field of {'/'.join(SHARED_TUNED)} only; tune "
                              "the paper's algorithms without it")
        from commands.train import set_options
        from marl.training import learner_config

        fixed = set_options(args.overrides)
        for key in fixed:
            if key in SHARED_SEARCHED:
                raise ConfigError(f"--set {key}: tune searches this field itself (it "
                                  f"searches {', '.join(SHARED_SEARCHED)}); fix another field, "
                                  "or train with --set instead of tuning")
        for a in algos:  # typed and checked now, before any trial
            learner_config(a, fixed)
    args.fixed = fixed
    scenarios = scenarios_argument(args.scenarios)  # each built and checked once, here
    if not algos:
        raise ConfigError("--algos and --scenarios must name at least one each")
    check_vehicles(args.vehicles)
    from infra.limits import MAX_TRAIN_SEED, MAX_TRAIN_STEPS, check_range, check_seeds

    check_range(args.trials, "--trials", 1, MAX_TRIALS)
    check_range(args.steps, "--steps", 1, MAX_TRAIN_STEPS)
    check_seeds([args.seed], "--seed", MAX_TRAIN_SEED)  # the trials' training seed
    if any(a in SHARED_TUNED for a in algos):  # every trial's rollout fits its budget
        from marl.training import learner_config

        rollout = max(SHARED_N_ENVS) * max(
            learner_config(a, fixed).rollout_steps for a in algos if a in SHARED_TUNED)
        if rollout > args.steps:
            raise ConfigError(f"--steps {args.steps}: a trial may step {max(SHARED_N_ENVS)} "
                              f"episodes x rollout_steps, {rollout:,} environment steps per "
                              "update, more than its budget; raise --steps or fix a smaller "
                              "rollout_steps with --set")
    try:
        import optuna  # noqa: F401
    except ImportError:
        raise ConfigError("cacc-bench tune needs Optuna, in the marl extra: install it with "
                          "`pip install -e '.[marl]'`") from None
    from commands.cli import out_folder
    from infra.atomic import write_text

    # one writer per folder, as `run`: a second tune on --out is refused naming the first
    with out_folder(args.out) as out:
        jobs = [StudyJob(a, sc, args.vehicles, args.trials, args.steps, args.seed, out, fixed)
                for a in algos for sc in scenarios]
        studies = [Path("studies") / f"{job.name}.sqlite3" for job in jobs]
        held = [p for p in (*studies, Path("trials.csv"), Path("tuned_configs.json"))
                if (out / p).exists()]
        check_finished(out, [str(p) for p in held], ("tuning result", "tuning results"),
                       "deleting them, then tuning from the first trial",
                       args.resume, args.overwrite)
        if args.overwrite:
            import shutil

            for p in held:
                (out / p).unlink()
            for job in jobs:
                shutil.rmtree(out / "trials" / job.name, ignore_errors=True)
        progress = Progress(len(jobs), "studies")
        rows: list[dict] = []
        for res in map_jobs(_study_job, jobs, args.executor, args.workers, args.ray_address):
            rows.extend(res)
            progress.advance(note=f"{res[0]['algo']} {res[0]['scenario']}" if res else "")
        progress.close()
        table = pd.DataFrame(rows).sort_values(["algo", "scenario", "trial"])
        write_csv(table, out / "trials.csv")
        command = "cacc-bench tune " + " ".join(shlex.quote(a) for a in argv)
        best = tuned_configs(table, args, command)
        write_text(out / "tuned_configs.json", json.dumps(best, indent=1, sort_keys=True) + "\n")
    for key, entry in sorted(best["configs"].items()):
        print(f"{key}: score {entry['score']:.1f} (trial {entry['trial']}) "
              f"{json.dumps(entry['config'], sort_keys=True)}")
    print(f"trials: {out / 'trials.csv'}; best configs: {out / 'tuned_configs.json'}",
          file=sys.stderr)
    return 0


def tuned_configs(table: Any, args: argparse.Namespace, command: str) -> dict[str, Any]:
    """The best trial per algorithm and scenario (ties: the earlier trial) as shippable data."""
    configs: dict[str, Any] = {}
    for (algo, scenario), grp in table.groupby(["algo", "scenario"], sort=True):
        best = grp.sort_values(["score", "trial"], ascending=[False, True]).iloc[0]
        config = {
            c.split(".", 1)[1]: (None if isinstance(v, float) and math.isnan(v) else v)
            for c, v in best.items() if c.startswith("config.")
        }
        config = {k: v for k, v in config.items() if not (k == "consensus_eps" and v is None)}
        configs[f"{algo}/{scenario}"] = {
            "config": {k: _plain(v) for k, v in config.items()},
            "score": float(best["score"]),
            "trial": int(best["trial"]),
            "validation_reward_sampled": float(best["selected_eval_reward_sampled"]),
            "validation_collisions_sampled": float(best["selected_eval_collisions_sampled"]),
        }
    return {
        "budget": {"trials": args.trials, "steps_per_trial": args.steps, "seed": args.seed,
                   "vehicles": args.vehicles, **({"fixed": dict(sorted(args.fixed.items()))}
                                                 if args.fixed else {})},
        "command": command,
        "configs": configs,
    }


def _plain(value: Any) -> Any:
    """A numpy scalar as the Python value (JSON), anything else unchanged."""
    item = getattr(value, "item", None)
    return item() if callable(item) else value
