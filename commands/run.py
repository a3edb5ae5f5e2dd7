"""``cacc-bench run``: the main job (sweep, store, CSV files, printed leaderboard)."""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from benchmark.executors import (
    AUTO,
    EXECUTORS,
    POOL_POLICY_EPISODES,
    resolve_executor,
    run_batches,
)
from benchmark.progress import Progress
from benchmark.suite import (
    KEY_COLUMNS,
    MAX_SEED,
    RunKey,
    build_sweep,
    seeds_from_episodes,
    seeds_from_set,
    unique,
)
from commands.cli import check_executor, command_parser, controllers_argument, scenarios_argument
from controllers.registry import default_controllers
from envs.params import SEED_SETS, TEST_SEEDS, VALIDATION_SEEDS, PlatoonParams
from envs.scenarios import (
    DEFAULT_SCENARIOS,
    MAX_VEHICLES,
    MIN_VEHICLES,
    Scenario,
)
from envs.simulators import SIMULATORS, check_simulator
from infra.errors import ConfigError
from infra.interrupt import raise_if_interrupted


def _csv(kind: str, cast: type) -> Any:
    def parse(text: str) -> list:
        out = []
        for item in text.split(","):
            item = item.strip()
            if not item:
                continue
            try:
                value = cast(item)
            except ValueError:
                raise argparse.ArgumentTypeError(f"{kind} must be a comma list of numbers, got {item!r}") from None
            if isinstance(value, float) and not math.isfinite(value):
                raise argparse.ArgumentTypeError(f"{kind} must be finite, got {item!r}")
            out.append(value)
        if not out:
            raise argparse.ArgumentTypeError(f"{kind}: empty list")
        return out

    return parse


def build_parser() -> argparse.ArgumentParser:
    """The options of ``cacc-bench run``."""
    p = command_parser("run", "Run every controller on the same episodes (controllers x "
                       "scenarios x sizes x seeds), store each finished run, and write runs.csv "
                       "and leaderboard.csv.")
    p.add_argument("--controllers", default=",".join(default_controllers()),
                   help="comma list; options as name:key=value,key=value (default: %(default)s)")
    p.add_argument("--scenarios", default=",".join(DEFAULT_SCENARIOS),
                   help="comma list of scenario ids, each with options as id:key=value "
                        "(sine-v1:amplitude_mps=2,frequency_hz=0.5; default: %(default)s)")
    p.add_argument("--vehicles", type=_csv("--vehicles", int), default=None,
                   help="comma list of platoon sizes N, followers (default: each scenario's own, "
                        "8 for the published ones, 4 for OpenACC; see `cacc-bench list`)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--episodes", type=int, default=None,
                   help="first K published evaluation seeds 2000, 2010, ... (default: 10), or "
                        "the first K of --seed-set")
    g.add_argument("--seeds", type=_csv("--seeds", int), default=None, help="explicit seeds")
    p.add_argument("--seed-set", choices=tuple(SEED_SETS), default=None,
                   help="which named seeds --episodes counts from (docs/seed-sets.md): eval "
                        "(default, the published 2000, 2010, ...), test "
                        f"({TEST_SEEDS[0]}..{TEST_SEEDS[-1]}, the final word; default all "
                        f"{len(TEST_SEEDS)}) or validation ({VALIDATION_SEEDS[0]}.."
                        f"{VALIDATION_SEEDS[-1]}, the seeds decisions are made on; default all "
                        f"{len(VALIDATION_SEEDS)}); not with --seeds")
    p.add_argument("--comm-delay", type=_csv("--comm-delay", float), default=[0.0],
                   help="V2V delay in s, whole steps (comma list; default 0)")
    p.add_argument("--packet-loss", type=_csv("--packet-loss", float), default=[0.0],
                   help="probability of losing a V2V message, in [0, 1] (comma list; default 0)")
    p.add_argument("--lag", type=_csv("--lag", float), default=[0.0],
                   help="actuator lag time constant in s (comma list; default 0)")
    p.add_argument("--out", default="results/run", help="results folder (default: %(default)s)")
    p.add_argument("--resume", action="store_true",
                   help="complete the sweep in --out: skip stored runs, retry failed ones")
    p.add_argument("--trajectories", action="store_true",
                   help="also write one trajectory CSV per run into OUT/trajectories/")
    p.add_argument("--executor", choices=(AUTO, *EXECUTORS), default=AUTO,
                   help="auto (default: the process pool when a sweep has several batches and "
                        f"MPC runs or at least {POOL_POLICY_EPISODES} policy episodes, else "
                        "serial), serial, process or ray")
    p.add_argument("--workers", type=int, default=2, help="processes or Ray CPUs (default 2)")
    p.add_argument("--ray-address", default=None,
                   help="attach to this Ray cluster (default: RAY_ADDRESS, else a local instance)")
    p.add_argument("--quiet", action="store_true", help="do not print the leaderboard")
    p.add_argument("--simulator", choices=SIMULATORS, default=SIMULATORS[0],
                   help="builtin (default), sumo (the same controllers, scenarios and metrics "
                        "in SUMO through libsumo, its dynamics matched to the built-in ones) or "
                        "sumo-euler (SUMO's default Euler position update); the sumo extra: "
                        "pip install -e '.[sumo]' (docs/sumo/index.md)")
    p.add_argument("--pool-seeds", action="store_true",
                   help="one leaderboard row per MARL policy over its training seeds "
                        "(--controllers bdc:seed=0,bdc:seed=1,bdc:seed=2): a two-stage bootstrap "
                        "over training seeds, then episodes")
    add_rank_by_option(p)
    return p


def add_rank_by_option(p: argparse.ArgumentParser) -> None:
    """``--rank-by`` (``run`` and ``leaderboard``): how ``rank`` orders a setting's rows."""
    from benchmark.export import RANK_BY

    p.add_argument("--rank-by", choices=RANK_BY, default=RANK_BY[0],
                   help="how rank orders the rows of a setting, after putting those without a "
                        "collision or failed run first: reward (default: by mean reward) or "
                        "string-stability (the rows whose frequency sweep peaks at most 1 + "
                        "tolerance first, then by reward)")


def _validate(args: argparse.Namespace
              ) -> tuple[list[tuple[str, dict[str, str]]], list[Scenario], list[int]]:
    controllers = controllers_argument(args.controllers)
    scenarios = scenarios_argument(args.scenarios)  # each built and checked once, here
    for n in args.vehicles or ():
        if not MIN_VEHICLES <= n <= MAX_VEHICLES:
            raise ConfigError(
                f"--vehicles: a platoon needs {MIN_VEHICLES} to {MAX_VEHICLES} followers, got {n}"
            )
    from infra.limits import check_delay, check_packet_loss, check_whole_steps

    for d in args.comm_delay:
        check_delay(d, "--comm-delay")  # one rule with stability's --delay
        check_whole_steps(d, "--comm-delay", PlatoonParams().dt_s)
    for loss in args.packet_loss:
        check_packet_loss(loss, "--packet-loss")  # one rule with the channel's
    for lag in args.lag:
        if lag < 0:
            raise ConfigError(f"--lag must be >= 0 s, got {lag}")
    check_executor(args.workers)  # the Ray address (or RAY_ADDRESS) in main, for --executor ray
    check_simulator(args.simulator)  # sumo without the extra: the install command
    if args.pool_seeds and args.simulator != SIMULATORS[0]:
        raise ConfigError("--pool-seeds pools the built-in simulator's policies; leave it out "
                          f"with --simulator {args.simulator}")
    if args.seeds is not None and args.seed_set is not None:
        raise ConfigError("--seed-set and --seeds exclude each other: --seeds names the seeds "
                          "itself, --seed-set picks a named set (with --episodes K, its first K)")
    if args.seeds is not None:
        seeds = unique(str(s) for s in args.seeds)
        seed_list = [int(s) for s in seeds]
        if any(not 0 <= s <= MAX_SEED for s in seed_list):
            raise ConfigError(f"--seeds must lie in 0..{MAX_SEED}")
    elif args.seed_set not in (None, "eval"):
        seed_list = seeds_from_set(args.seed_set, args.episodes)
    else:
        episodes = 10 if args.episodes is None else args.episodes
        if episodes < 1:
            raise ConfigError(f"--episodes must be >= 1, got {episodes}")
        seed_list = seeds_from_episodes(episodes)
    return controllers, scenarios, seed_list


def preflight(controllers: list[tuple[str, dict[str, str]]], scenarios: list[Scenario],
               vehicles: list[int], lags_s: list[float], simulator: str = "builtin") -> None:
    """Build each controller once and check it against every setting, so bad options, missing
    checkpoints, a loop unstable with the lag, a setting ``simulator`` does not run or a
    scenario of one's own whose builder fails (:func:`envs.scenarios.check_episode`) fail
    before any run."""
    from controllers.registry import check_fits, make_controller
    from envs.params import PlatoonParams
    from envs.scenarios import check_episode
    from envs.simulators import check_runs_in, check_setting

    for sc in scenarios:  # a scenario of one's own whose builder fails: refused here
        for n in vehicles:
            check_episode(sc, n)
    for name, opts in controllers:
        ctrl = make_controller(name, **opts)
        check_runs_in(ctrl, simulator)
        for sc in scenarios:
            for n in vehicles:
                for lag in lags_s:
                    check_fits(ctrl, sc, n, PlatoonParams(lag_s=lag))
                    check_setting(simulator, sc, n, PlatoonParams(lag_s=lag))


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench run``."""
    args = build_parser().parse_args(argv)
    controllers, scenarios, seeds = _validate(args)
    if args.executor == "ray":  # a cluster that does not answer is refused before any file
        import os

        from benchmark.executors import check_ray_address, ensure_ray

        address = args.ray_address or os.environ.get("RAY_ADDRESS")
        check_ray_address(address)
        if address:
            ensure_ray(args.workers, address)
    from benchmark.paths import writable_dir

    writable_dir(args.out)
    keys: list[RunKey] = []
    for sc in scenarios:
        vehicles = args.vehicles or [sc.default_vehicles]
        keys += build_sweep(controllers, [sc], vehicles, seeds, args.comm_delay,
                            args.packet_loss, args.lag, args.simulator)
        preflight(controllers, [sc], vehicles, args.lag, args.simulator)
    keys = sorted(set(keys))
    return execute_sweep(keys, Path(args.out), resume=args.resume, trajectories=args.trajectories,
                         executor=args.executor, workers=args.workers,
                         ray_address=args.ray_address, quiet=args.quiet, first_seed=seeds[0],
                         pool_seeds=args.pool_seeds, suggest=True,
                         rank_by=args.rank_by, sweeps=True)


def _refuse_changed_policies(keys: list[RunKey], stored: list[dict], out: Path) -> None:
    """Refuse (ConfigError) to resume over stored runs of a learned policy that has changed
    since they ran (retrained to other weights, or replaced): they would stand for the new
    weights. Runs stored before records held ``policy_sha256`` cannot be checked."""
    from benchmark.suite import current_policies

    ran = {r["id"]: r["policy_sha256"] for r in stored
           if r["status"] == "ok" and r.get("policy_sha256")}
    held = [k for k in keys if k.id in ran]
    now = current_policies(held) if held else {}
    changed = [k for k in held if now[k] != ran[k.id]]
    if not changed:
        return
    k = changed[0]
    settings = sorted({(c.controller, c.scenario, c.n_vehicles) for c in changed})
    extra = len(settings) - 1
    more = f", and {extra} more setting{'s' * (extra > 1)}" if extra else ""
    raise ConfigError(
        f"{out.resolve()} holds {len(changed)} runs of learned policies that have changed since "
        f"they ran ({k.controller} on {k.scenario}, N = {k.n_vehicles}: policy "
        f"{ran[k.id][:12]} then, {now[k][:12] or 'none'} now{more}); stored runs are never "
        "replaced: move that folder aside and run the command again with --resume (its runs "
        "are evaluated again, with the policies as they are now), or put back the checkpoints "
        "those runs used")


def study_keys(settings: Iterable[tuple[list[tuple[str, dict[str, str]]], Scenario]],
               seeds: list[int]) -> set[RunKey]:
    """The runs of a study's settings, each (controllers, built scenario) at the scenario's
    default N with ideal V2V and no lag, each setting checked by :func:`preflight` first
    (refused before any run)."""
    keys: set[RunKey] = set()
    for controllers, sc in settings:
        n = sc.default_vehicles
        preflight(controllers, [sc], [n], [0.0])
        keys.update(build_sweep(controllers, [sc], [n], seeds))
    return keys


@contextmanager
def study_sweep(keys: Iterable[RunKey], args: argparse.Namespace, banner: str, first_seed: int,
                check: Callable[[Path], None] | None = None, sweeps: bool = False
                ) -> Iterator[tuple[Path, int]]:
    """A study command's folder and sweep: ``--out`` checked (``check(out)`` too) and held by
    the command (:func:`commands.cli.out_folder`) while the block writes the study's tables;
    before it, :func:`execute_sweep` of ``keys`` into ``out/runs`` with the command's
    ``--resume`` and executor options, quietly, ``banner`` on standard error once the store is
    checked (a refusal stays one line). Yields ``--out`` and the sweep's exit status."""
    from commands.cli import out_folder

    with out_folder(args.out, check) as out:
        yield out, execute_sweep(sorted(keys), out / "runs", resume=args.resume,
                                 executor=args.executor, workers=args.workers,
                                 ray_address=args.ray_address, quiet=True,
                                 first_seed=first_seed, banner=banner, sweeps=sweeps)


def execute_sweep(
    keys: list[RunKey],
    out: Path,
    *,
    resume: bool = False,
    trajectories: bool = False,
    executor: str = "serial",
    workers: int = 1,
    ray_address: str | None = None,
    quiet: bool = False,
    first_seed: int | None = None,
    pool_seeds: bool = False,
    env: dict[str, str] | None = None,
    banner: str = "",
    suggest: bool = False,
    rank_by: str = "reward",
    sweeps: bool = False,
) -> int:
    """Run the keys not yet stored in ``out``, store each as it finishes, write the CSVs;
    ``env``: what the processes that run them hold from their start (the training arithmetic,
    :func:`marl.arithmetic.process_env`); ``banner``: a line for standard error once the store
    and its records are checked (a refusal stays one line); ``suggest``: end with the commands
    that read the folder next (``cacc-bench run``); ``rank_by``: the leaderboard's order
    (:data:`benchmark.export.RANK_BY`); ``sweeps``: the leaderboard carries each row's frequency
    sweep (:mod:`benchmark.sweep`, measured on the same executor and cached in ``out``; ``run``
    and ``compare-learned`` ask for it, the other studies' sweeps leave it out and
    ``cacc-bench leaderboard`` on their folders adds it). Paths are printed as the user can open
    them (:func:`benchmark.work_folder.shown_path`)."""
    from benchmark.export import (
        check_csv_targets,
        trajectory_arrays,
        write_csvs,
        write_trajectory_csv,
    )
    from benchmark.store import ResultStore

    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a folder")
    check_csv_targets(out)  # a CSV path that is a folder is refused before any run
    store = ResultStore(out, writer=True)
    try:
        # every stored record is checked before any run: an invalid one refuses the sweep
        before = store.records()
        done_ok = {r["id"] for r in before if r["status"] == "ok"}
        stored = {r["id"] for r in before}
        if stored and not resume:
            raise ConfigError(
                f"{out} already holds {len(stored)} stored runs; add --resume to complete that "
                "sweep (stored runs are kept), or choose another --out"
            )
        _refuse_changed_policies(keys, before, out)
        if banner:
            print(banner, file=sys.stderr)
        pending = [k for k in keys if k.id not in done_ok]
        if first_seed is None:
            first_seed = min(k.seed for k in keys) if keys else 0
        todo = pending
        skipped = len(keys) - len(pending)
        if skipped:
            print(f"resuming: {skipped} of {len(keys)} runs already stored, {len(pending)} to run",
                  file=sys.stderr)
        executor = resolve_executor(todo, executor, workers)
        store.set_meta("last_sweep", {"n_runs": len(keys), "executor": executor})
        work = {k.id: k.n_vehicles * (k.built.n_steps if k.built is not None else 1)
                for k in todo}  # vehicle-steps: what a run's time scales with
        progress = Progress(len(todo), parallel=1 if executor == "serial" else workers,
                            groups=[k.controller for k in todo], weights=list(work.values()))
        for batch in run_batches(todo, executor, workers, ray_address, keep_trajectory=True,
                                 env=env):
            finished = []
            for rec in batch:
                traj = rec.pop("_trajectory", None)
                arrays = trajectory_arrays(traj) if traj is not None else None
                if arrays is not None and trajectories:
                    stem = RunKey(**{f: rec[f] for f in KEY_COLUMNS}).file_stem
                    write_trajectory_csv(out / "trajectories" / f"{stem}.csv", arrays)
                keep = arrays if (arrays is not None and rec["seed"] == first_seed) else None
                finished.append((rec, keep))
            store.add_batch(finished)  # one transaction per finished batch
            raise_if_interrupted()  # a signal a library swallowed: stop after what is stored
            for rec, _ in finished:
                progress.advance(note=f"{rec['controller']} {rec['scenario']} s{rec['seed']}",
                                 group=rec["controller"], seconds=rec.get("wall_s"),
                                 weight=work.get(rec["id"], 1))
        progress.close()
        records = store.records()
        runs_path, lb_path, lb = write_csvs(out, records, pool_seeds, rank_by=rank_by,
                                            sweeps=sweeps, executor=executor, workers=workers,
                                            ray_address=ray_address)
    finally:
        store.close()
    if not quiet:
        from analysis.tables import format_leaderboard

        print(format_leaderboard(lb))
    from benchmark.store import STORE_NAME
    from benchmark.work_folder import shown_path

    print(f"wrote {shown_path(runs_path)} ({len(records)} runs), {shown_path(lb_path)} and the "
          f"store {shown_path(out / STORE_NAME)}")
    if suggest:
        folder = shlex.quote(shown_path(out))
        print(f"next: `cacc-bench plot {folder}` for its figures, `cacc-bench leaderboard "
              f"{folder}` for this table again")
    failed = [r for r in records if r["status"] != "ok"]
    if failed:
        print(f"{len(failed)} run(s) failed:", file=sys.stderr)
        for r in failed[:20]:
            print(f"  {r['id']}: {r['error']}", file=sys.stderr)
        return 1
    return 0
