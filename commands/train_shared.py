"""``cacc-bench train`` for the shared-policy learners: ``ippo``, ``mappo``, ``ippo-bdc``
(:mod:`marl.ppo`) and ``distill`` (:mod:`marl.distill`, imitating ``mpc``).

Per run (algorithm x scenario x seed) it writes ``<out>/<algo>__<scenario>__n<N>__s<seed>.pt``
(the snapshot kept on the validation seeds, acting weights in float16), ``.curve.csv``
(validation reward and collisions over training) and ``.log``, together and atomically when the
run finishes (:class:`infra.atomic.StagedFiles`): an interrupted run leaves earlier files byte for
byte as they were. A finished run with the same config and budget is skipped with ``--resume``.
"""

from __future__ import annotations

import dataclasses
import io
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from infra.errors import ConfigError
from infra.naming import checkpoint_stem


def shared_config(algo: str, overrides: Sequence[str], tuned: dict[str, Any] | None = None
                  ) -> Any:
    """The config of ``algo`` (:class:`marl.ppo.PPOConfig`, or :class:`marl.distill.
    DistillConfig` for ``distill``) with ``tuned`` options, then ``--set KEY=VALUE`` overrides
    (typed and checked by :func:`controllers.registry.build_config`, the one option rule)."""
    from controllers.registry import build_config
    from marl.distill import DistillConfig
    from marl.ppo_nets import PPOConfig

    values: dict[str, Any] = dict(tuned or {})
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. --set lr=0.0003")
        if key.strip() == "algo":
            raise ConfigError("--set algo: name the learner with --algo")
        values[key.strip()] = value.strip()
    if algo == "distill":
        return build_config(DistillConfig, values, f"{algo} (--set)")
    return build_config(PPOConfig, {**values, "algo": algo}, f"{algo} (--set)")


def model_expert(name: str) -> Callable[[Any], Callable[[Any], Any]]:
    """A registered model-based controller as :func:`marl.distill.distill`'s expert: for a
    reset env, its commands for the env's states (its V2V through its own ideal channels)."""
    from controllers.base import EpisodeContext, check_fits, reset_controller
    from controllers.registry import make_controller

    def make(env: Any) -> Callable[[Any], Any]:
        ctrl = make_controller(name)
        ctx = EpisodeContext(env.scenario, env.n_vehicles, env.seeds, env.params)
        check_fits(ctrl, env.scenario, env.n_vehicles, env.params)
        reset_controller(ctrl, ctx)
        return lambda state: ctrl.act(state, None)

    return make


def stored_config(config: Any) -> dict[str, Any]:
    """The config as a checkpoint records it (a distillation's with its actor's action mode)."""
    out = dataclasses.asdict(config)
    out.setdefault("action_mode", "accel")
    return out


def finished(path: Path, config: Any, steps: int) -> bool:
    """Whether ``path`` holds a finished run of this config and budget (under the shipped
    energy model); a damaged file, or a finished run of another config, budget or energy model,
    is a ConfigError (``--resume`` never trains over a finished run)."""
    if not path.exists():
        return False
    from marl.checkpoint import load_checkpoint, same_energy_model

    data = load_checkpoint(path)
    budget = int(data["curve_summary"].get("budget_steps", -1))
    if data["config"] != stored_config(config) or budget != steps \
            or not same_energy_model(data):
        diff = sorted(k for k, v in stored_config(config).items() if data["config"].get(k) != v)
        why = (f"config fields {', '.join(diff)} differ" if diff else
               f"budget {budget} steps, not {steps}" if budget != steps else
               "trained under another energy model")
        raise ConfigError(f"{path.name} in --out holds a finished run of another setting ({why});"
                          " --resume never trains over it: use another --out, or remove the "
                          "file to train again")
    return True


def train_shared(
    algo: str, scenario: str, n_vehicles: int, seed: int, steps: int, out: Path,
    config: Any, resume: bool = False, log: Callable[[str], None] = print,
) -> Path:
    """Train one run and write its files; returns the checkpoint's path."""
    import torch

    from infra.atomic import StagedFiles
    from marl.ppo import train

    stem = checkpoint_stem(algo, scenario, n_vehicles, seed)
    path = out / f"{stem}.pt"
    if resume and finished(path, config, steps):
        log(f"{stem}: finished before, skipped (--resume)")
        return path
    torch.set_num_threads(1)
    lines: list[str] = []

    def both(line: str) -> None:
        lines.append(line)
        log(line)

    t0 = time.perf_counter()
    if algo == "distill":
        from marl.distill import distill

        result = distill(scenario, model_expert(config.expert), n_vehicles, seed, config,
                         log=both)
    else:
        result = train(scenario, n_vehicles, seed, steps, config, log=both)
    wall = time.perf_counter() - t0
    both(f"{stem}: {result.steps} steps in {wall:.1f} s ({result.env_steps_per_s:.0f} env "
         f"steps/s while learning); kept the snapshot at {result.best['steps']:.0f} steps: "
         f"validation reward {result.best['reward']:.2f}, collisions "
         f"{result.best['collisions']:.0f}")
    curve = io.StringIO()
    curve.write("steps,validation_reward,validation_collisions\n")
    for row in result.curve:
        curve.write(f"{row['steps']:.0f},{row['reward']:.6f},{row['collisions']:.0f}\n")
    from marl.checkpoint import checkpoint_payload, save_to_file

    summary = {f"best_{k}": v for k, v in result.best.items()}
    summary.update(budget_steps=float(steps), env_steps_per_s=result.env_steps_per_s,
                   wall_s=wall)
    summary.update({f"{k}_bits_per_agent": v for k, v in result.bits_per_agent.items()})
    payload = checkpoint_payload(
        algo=algo, config=stored_config(config), scenario=scenario, n_vehicles=n_vehicles,
        seed=seed, steps=result.steps, curve_summary=summary,
        weights=dict(result.actor.state_dict()))
    out.mkdir(parents=True, exist_ok=True)
    with StagedFiles() as staged:
        staged.write_with(path, lambda tmp: save_to_file(payload, tmp))
        staged.write_text(out / f"{stem}.curve.csv", curve.getvalue())
        staged.write_text(out / f"{stem}.log", "\n".join(lines) + "\n")
        staged.commit()
    return path


def main_shared(args: Any, algos: list[str], scenarios: list[str], seeds: list[int]) -> int:
    """``cacc-bench train`` for shared-policy learners: the checks, then one run after another
    in this process, holding ``--out``'s lock."""
    import sys

    from benchmark.folder_lock import folder_lock
    from benchmark.paths import writable_dir
    from envs.scenarios import check_vehicles

    check_vehicles(args.vehicles)
    if args.device not in (None, "cpu"):
        raise ConfigError(f"--device {args.device}: the shared-policy learners train on the CPU")
    if args.population not in (None, 1) or args.executor != "serial":
        raise ConfigError("--population and --executor are options of the paper's learners; "
                          "the shared-policy learners train one run after another")
    overrides = list(args.overrides)
    if args.episodes_parallel is not None:
        from infra.limits import MAX_EPISODES_PARALLEL, check_range

        check_range(args.episodes_parallel, "--episodes-parallel", 1, MAX_EPISODES_PARALLEL)
        overrides.append(f"n_envs={args.episodes_parallel}")
    configs = {}
    for a in algos:
        for sc in scenarios:
            tuned = None
            if args.tuned:
                from marl.config import tuned_options

                tuned = tuned_options(a, sc)
            configs[(a, sc)] = shared_config(a, overrides, tuned)
    writable_dir(args.out)
    out = Path(args.out)
    with folder_lock(out):
        if args.resume:  # every finished run checked before any training
            for seed in seeds:
                for sc in scenarios:
                    for a in algos:
                        stem = checkpoint_stem(a, sc, args.vehicles, seed)
                        finished(out / f"{stem}.pt", configs[(a, sc)], args.steps)
        for seed in seeds:
            for sc in scenarios:
                for a in algos:
                    path = train_shared(a, sc, args.vehicles, seed, args.steps, out,
                                        configs[(a, sc)], resume=args.resume,
                                        log=lambda line: print(line, file=sys.stderr))
                    print(f"{a} {sc} seed {seed}: checkpoint {path.name} in {args.out}")
    return 0
