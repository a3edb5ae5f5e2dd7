"""``cacc-bench compare-learned``: learned control against MPC on equal terms, in one report.

Runs the shipped policies of :data:`studies.learned_report.POLICIES` (learned ones with their
three training seeds) on the published evaluation seeds under ideal V2V and under a 0.2 s delay
with 30 % loss, through the results store (resumable, ``--resume``), then writes
``report.md`` (the three questions: action set and information, learning, communication),
``policies.csv``, ``comparisons.csv`` and ``episodes.csv`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys

from benchmark.executors import add_executor_options
from commands.cli import check_executor, plain, report_command

#: Training seeds of the shipped learned policies.
TRAIN_SEEDS: tuple[int, ...] = (0, 1, 2)
#: Platoon size of the shipped shared policies (they act at any N).
SHARED_N = 8


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cacc-bench compare-learned",
                                description=plain(__doc__.split("\n")[0]))
    p.add_argument("--scenarios", default="catchup-v1,slowdown-v1",
                   help="comma list of scenario ids (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=50,
                   help="first K published evaluation seeds (default: %(default)s)")
    p.add_argument("--vehicles", type=int, default=8, help="followers N (default: 8)")
    p.add_argument("--out", default="results/compare-learned",
                   help="output folder (default: %(default)s)")
    p.add_argument("--resume", action="store_true", help="complete a comparison in --out")
    add_executor_options(p, default="process")
    return p


def controller_specs(scenarios: list[str], n_vehicles: int) -> list[tuple[str, dict[str, str]]]:
    """The controllers to run: model-based ones once, learned ones per training seed, those
    with no shipped checkpoint for every scenario left out (said on stderr)."""
    from controllers.policy import VARIANT_DIR, checkpoint_path
    from controllers.registry import resolve
    from marl.learners import PER_AGENT_SHARED, SHARED_LEARNERS
    from studies.learned_report import POLICIES

    specs: list[tuple[str, dict[str, str]]] = []
    for name, (ctrl, opts) in POLICIES.items():
        if resolve(ctrl).family != "marl":
            specs.append((ctrl, dict(opts)))
            continue
        folder = VARIANT_DIR / opts["variant"] if "variant" in opts else None
        shared = ctrl in SHARED_LEARNERS and ctrl not in PER_AGENT_SHARED
        trained_n = SHARED_N if shared else n_vehicles  # a shared policy acts at any N
        missing = [(sc, s) for sc in scenarios for s in TRAIN_SEEDS
                   if not checkpoint_path(ctrl, sc, trained_n, s, folder).exists()]
        if missing:
            print(f"compare-learned: {name} left out (no shipped checkpoint for "
                  f"{missing[0][0]}, N = {trained_n}, seed {missing[0][1]})", file=sys.stderr)
            continue
        specs += [(ctrl, {**opts, "seed": str(s)}) for s in TRAIN_SEEDS]
    return specs


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench compare-learned``."""
    from benchmark.export import write_csv
    from benchmark.folder_lock import folder_lock
    from benchmark.paths import writable_dir
    from benchmark.suite import build_sweep, seeds_from_episodes
    from commands.cli import scenarios_argument
    from commands.run import execute_sweep
    from envs.scenarios import check_vehicles
    from infra.files import read_csv
    from studies.learned_report import (
        DEGRADED,
        IDEAL,
        comparisons_frame,
        episodes_frame,
        policy_sweeps,
        policy_table,
        write_report,
    )

    args = _parser().parse_args(argv)

    scenarios = scenarios_argument(args.scenarios)
    check_vehicles(args.vehicles)
    check_executor(args.workers, args.ray_address)
    seeds = seeds_from_episodes(args.episodes)
    specs = controller_specs([sc.label for sc in scenarios], args.vehicles)
    keys = sorted({k for delay, loss in (IDEAL, DEGRADED)
                   for k in build_sweep(specs, scenarios, [args.vehicles], seeds, [delay], [loss])})
    out = writable_dir(args.out)
    command = report_command("compare-learned", argv)
    with folder_lock(out):
        print(f"compare-learned: {len(specs)} controllers x {len(scenarios)} scenarios x 2 V2V "
              f"settings x {len(seeds)} episodes = {len(keys)} runs", file=sys.stderr)
        rc = execute_sweep(keys, out / "runs", resume=args.resume, executor=args.executor,
                           workers=args.workers, ray_address=args.ray_address, quiet=True,
                           first_seed=seeds[0], sweeps=True)
        ep = episodes_frame(read_csv(out / "runs" / "runs.csv", "the runs table"))
        ep = ep[ep["n_vehicles"] == args.vehicles]
        comp = comparisons_frame(ep)
        from benchmark.sweep import SweepCache

        cache = SweepCache(out / "runs")  # the runs' leaderboard measured them: read back
        sweeps = policy_sweeps(ep, cache)
        cache.save()
        write_csv(ep, out / "episodes.csv")
        write_csv(policy_table(ep), out / "policies.csv")
        write_csv(comp, out / "comparisons.csv")
        write_csv(sweeps, out / "sweeps.csv")
        report = write_report(ep, comp, out, command, sweeps)
    print(f"wrote {report} and the tables beside it")
    return rc
