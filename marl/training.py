"""A training job as a typed key (:class:`TrainingKey`), a study's training run
(:class:`PolicyJob`), and the run of the shared-policy learners (:func:`run_shared`; the
paper's learners run in :func:`marl.selection.run_population`).

A key says everything a job trains from, built once at the command line: the learner, the
scenario itself, N, the seeds (runs that differ only in their seed train as one population), the
step budget, the config object, the arithmetic, the device and the folder. It pickles, so the
executors (process, Ray) hand it to their workers as it is.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from envs.scenarios import Scenario
from infra.errors import ConfigError
from infra.naming import build_config, checkpoint_stem
from marl.learners import LEARNERS, load

if TYPE_CHECKING:
    from marl.checkpoint import Snapshots
    from marl.selection import TrainResult


@dataclass(frozen=True)
class TrainingKey:
    """One training job: ``seeds`` runs of ``algo`` on ``scenario`` with N followers.

    Attributes
    ----------
    algo : str
        A learner of :data:`marl.learners.LEARNERS`.
    scenario : Scenario
        Built (:func:`envs.scenarios.make_scenario`); checkpoints are named by its id.
    n_vehicles, steps : int
        Followers N; environment steps of each run (a distillation stops at its config's last
        round or at these, whichever comes first).
    seeds : tuple of int
        Training seeds, one run each (one: a population of one).
    config : object
        The learner's config (:func:`config_class`), built and checked once.
    out : Path
        Where the runs' files go (:func:`marl.checkpoint.write_run`).
    arithmetic, device : str
        :mod:`marl.arithmetic`'s mode; where the networks train
        (:func:`marl.config.training_device`).
    validation_episodes : int or None
        The first that many validation seeds choose the kept snapshot (None: all).
    progress : bool
        Show progress on this terminal (not part of the job: runs differing in it group).
    """

    algo: str
    scenario: Scenario
    n_vehicles: int
    seeds: tuple[int, ...]
    steps: int
    config: Any
    out: Path
    arithmetic: str = "native"
    device: str = "cpu"
    validation_episodes: int | None = None
    progress: bool = field(default=False, compare=False)

    @property
    def family(self) -> str:
        """The learner's family (:data:`marl.learners.LEARNER_FAMILIES`): its training loop."""
        return LEARNERS[self.algo].family

    def stem(self, seed: int) -> str:
        """File stem of the run of ``seed`` (:func:`infra.naming.checkpoint_stem`)."""
        return checkpoint_stem(self.algo, self.scenario.id, self.n_vehicles, seed)

    def finished_file(self, seed: int) -> Path:
        """The file whose presence marks the run of ``seed`` finished: the final weights
        (``.final.pt``) where the learner keeps them, else the kept snapshot (``.pt``)."""
        return self.out / f"{self.stem(seed)}{'.final.pt' if self.family == 'a2c' else '.pt'}"

    def held(self) -> list[Path]:
        """The files of the key's runs already in its folder: a run's files are written
        together when it finishes, so each names finished work that training would replace."""
        return [p for seed in self.seeds for suffix in (".pt", ".final.pt", ".curve.csv", ".log")
                if (p := self.out / f"{self.stem(seed)}{suffix}").exists()]

    def snapshots(self, seed: int) -> Snapshots:
        """The resumable snapshot of the run of ``seed`` (:class:`marl.checkpoint.Snapshots`):
        ``<stem>.snapshot.pt`` in the folder, recording the run it belongs to (everything of
        the key but the folder, its other seeds and the progress display)."""
        from marl.checkpoint import SNAPSHOT_SUFFIX, Snapshots, energy_model_id

        identity = {"algo": self.algo, "scenario": self.scenario.label, "n_vehicles":
                    self.n_vehicles, "seed": int(seed), "budget_steps": self.steps,
                    "config": self.stored_config(), "arithmetic": self.arithmetic,
                    "device": self.device, "validation_episodes": self.validation_episodes,
                    "energy_model": energy_model_id()}
        return Snapshots(self.out / f"{self.stem(seed)}{SNAPSHOT_SUFFIX}", identity)

    def resolved_config(self) -> Any:
        """The config the runs train with (the paper learners': resolved for the scenario)."""
        return self.config.resolved(self.scenario) if self.family == "a2c" else self.config

    def stored_config(self) -> dict[str, Any]:
        """The config as the checkpoints record it (a distilled actor's with its action mode)."""
        out = dataclasses.asdict(self.resolved_config())
        if self.family != "a2c":
            out.setdefault("action_mode", "accel")
        return out


@dataclass(frozen=True)
class PolicyJob(TrainingKey):
    """One policy-training run of a study (``cacc-bench reproduce``, ``sensitivity``): a
    :class:`TrainingKey` of one seed with the name it has in the study and the study itself.

    Attributes
    ----------
    name : str
        The algorithm, or an ablation or variant of it (its shipped folder).
    study : str
        The study it serves (``main``, ``sizes``, ``openacc``, ``sensitivity``).
    """

    name: str = field(default="", compare=False)
    study: str = field(default="", compare=False)

    @property
    def seed(self) -> int:
        """Its training seed (a study's job is one run)."""
        (seed,) = self.seeds
        return seed

    def key(self, device: str = "cpu") -> TrainingKey:
        """The plain training key of the job on ``device``."""
        return TrainingKey(**{f.name: getattr(self, f.name)
                              for f in dataclasses.fields(TrainingKey)}
                           | {"device": device})

    def file(self, suffix: str) -> Path:
        """Its file ``<stem><suffix>`` (:meth:`TrainingKey.stem`; ``.pt``, ``.source.json``)."""
        return self.out / f"{self.stem(self.seed)}{suffix}"


def finished(key: TrainingKey) -> bool:
    """Whether the run of ``key`` (one seed) finished in its folder with the same config,
    budget, arithmetic and energy model; a damaged file, or a finished run of another setting,
    is a ConfigError saying what to do (``--resume`` never trains over a finished run)."""
    from marl.arithmetic import of_summary
    from marl.checkpoint import energy_model_id, load_checkpoint, same_energy_model

    (seed,) = key.seeds
    path = key.finished_file(seed)
    if not path.exists():
        return False
    try:  # verified: a damaged or truncated file is refused, naming what to do
        data = load_checkpoint(path, algo=key.algo, n_vehicles=key.n_vehicles,
                               scenario=key.scenario.id)
    except ConfigError as exc:
        raise ConfigError(f"{exc} (or remove {path} to train this run again)") from None
    want, got, summary = key.stored_config(), data["config"], data["curve_summary"]
    diff = sorted(k for k in {*want, *got} if got.get(k) != want.get(k))
    budget = summary.get("budget_steps")  # the shared learners record it; the others stop past it
    why = (f"config fields {', '.join(diff)} differ" if diff
           else f"budget {budget:.0f} steps, not {key.steps}" if budget not in (None, key.steps)
           else f"{data['steps']} steps, fewer than the {key.steps} asked"
           if budget is None and data["steps"] < key.steps else "")
    again = "use another --out, or remove it to train again"
    if why:
        raise ConfigError(f"{path} holds a finished run of another config or budget ({why}); "
                          f"--resume never trains over it: {again}")
    if of_summary(summary) != key.arithmetic:
        raise ConfigError(f"{path} holds a run trained with {of_summary(summary)} arithmetic, "
                          f"not {key.arithmetic} (--arithmetic); {again}")
    if not same_energy_model(data):
        raise ConfigError(
            f"{path} holds a run trained with another energy model (fingerprint "
            f"{data.get('energy_model')}, this cacc-bench's is {energy_model_id()}: its reward "
            f"differs); {again}")
    return True


def config_class(algo: str) -> type:
    """The config class of a learner of :data:`marl.learners.LEARNERS` (its entry names it)."""
    return load(LEARNERS[algo].config)  # type: ignore[no-any-return]


def learner_config(algo: str, options: dict[str, Any], owner: str = "") -> Any:
    """The config of ``algo`` (:func:`config_class`) with ``options`` (strings typed, values
    checked by :func:`infra.naming.build_config`, the one option rule); a config that serves
    several learners (its ``algo`` field) is told which.

    Raises
    ------
    ConfigError
        For an unknown option or a bad value, naming ``owner`` (default ``<algo> (--set)``).
    """
    cls = config_class(algo)
    if "algo" in {f.name for f in dataclasses.fields(cls)}:  # one config for several learners
        options = {**options, "algo": algo}
    return build_config(cls, options, owner or f"{algo} (--set)")


def run_shared(key: TrainingKey, log: Callable[[str], None],
               evaluate: Callable[[Any, str], dict[str, float]],
               expert: Callable[[str], Any]) -> TrainResult:
    """Train the one run of ``key`` of a shared-policy learner (:mod:`marl.ppo`, or
    :mod:`marl.distill` imitating ``expert(config.expert)``), scored by ``evaluate`` (the
    validation seeds, sampled actions), and write its kept snapshot (``.pt``) and curve
    together (:func:`marl.checkpoint.write_run`)."""
    from marl.checkpoint import checkpoint_payload, write_run
    from marl.selection import TrainResult

    (seed,) = key.seeds
    t0 = time.perf_counter()
    snapshots = key.snapshots(seed)
    if key.family == "distill":
        from marl.distill import distill

        result = distill(key.scenario, expert(key.config.expert), key.n_vehicles, seed,
                         key.config, log=log, evaluate=evaluate, max_steps=key.steps,
                         snapshots=snapshots)
    else:
        from marl.ppo import train

        result = train(key.scenario, key.n_vehicles, seed, key.steps, key.config, log=log,
                       evaluate=evaluate, snapshots=snapshots)
    wall = time.perf_counter() - t0
    summary = {f"best_{k}": v for k, v in result.best.items()}
    summary.update(budget_steps=float(key.steps), env_steps_per_s=result.env_steps_per_s,
                   wall_s=wall)
    summary.update({f"{k}_bits_per_agent": v for k, v in result.bits_per_agent.items()})
    curve = [{"steps": r["steps"], "eval_reward_sampled": r["reward"],
              "eval_collisions_sampled": r["collisions"]} for r in result.curve]
    stem = key.stem(seed)
    write_run(key.out, stem, curve, {".pt": checkpoint_payload(
        algo=key.algo, config=key.stored_config(), scenario=key.scenario.id,
        n_vehicles=key.n_vehicles, seed=seed, steps=result.steps, curve_summary=summary,
        weights=dict(result.actor.state_dict()))})
    snapshots.remove()  # the run's files are written: they are the product
    best = result.best
    log(f"done: {result.steps} steps in {wall:.1f} s ({result.env_steps_per_s:.0f} env steps/s "
        f"while learning); kept the snapshot at {best['steps']:.0f} steps: validation reward "
        f"{best['reward']:.2f}, collisions {best['collisions']:.0f}; checkpoint "
        f"{key.out / f'{stem}.pt'}")
    return TrainResult(key.algo, key.scenario.id, key.n_vehicles, seed, result.steps, 0, wall,
                       result.env_steps_per_s, dict(result.bits_per_agent), curve,
                       checkpoint=key.out / f"{stem}.pt", curve_csv=key.out / f"{stem}.curve.csv")
