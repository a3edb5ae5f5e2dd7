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

from commands.cli import add_scenarios_option, add_study_options, command_parser

#: Training seeds of the shipped learned policies.
TRAIN_SEEDS: tuple[int, ...] = (0, 1, 2)
#: Platoon size of the shipped shared policies (they act at any N).
SHARED_N = 8


def _parser() -> argparse.ArgumentParser:
    p = command_parser("compare-learned", __doc__)
    add_scenarios_option(p, "catchup-v1,slowdown-v1")
    p.add_argument("--episodes", type=int, default=50,
                   help="first K published evaluation seeds (default: %(default)s)")
    p.add_argument("--vehicles", type=int, default=8, help="followers N (default: 8)")
    add_study_options(p, "results/compare-learned", "comparison")
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
    from benchmark.suite import build_sweep, seeds_from_episodes
    from benchmark.sweep import SweepCache
    from commands.cli import check_executor, report_command, scenarios_argument
    from commands.run import study_sweep
    from envs.scenarios import check_vehicles
    from infra.files import read_csv
    from studies import learned_report as study

    args = _parser().parse_args(argv)

    scenarios = scenarios_argument(args.scenarios)
    check_vehicles(args.vehicles)
    check_executor(args.workers, args.ray_address)
    seeds = seeds_from_episodes(args.episodes)
    specs = controller_specs([sc.label for sc in scenarios], args.vehicles)
    keys = {k for delay, loss in (study.IDEAL, study.DEGRADED)
            for k in build_sweep(specs, scenarios, [args.vehicles], seeds, [delay], [loss])}
    with study_sweep(keys, args, f"compare-learned: {len(specs)} controllers x {len(scenarios)} "
                     f"scenarios x 2 V2V settings x {len(seeds)} episodes = {len(keys)} runs",
                     seeds[0], sweeps=True) as (out, rc):
        ep = study.episodes_frame(read_csv(out / "runs" / "runs.csv", "the runs table"))
        ep = ep[ep["n_vehicles"] == args.vehicles]
        comp = study.comparisons_frame(ep)
        cache = SweepCache(out / "runs")  # the runs' leaderboard measured them: read back
        sweeps = study.policy_sweeps(ep, cache)
        cache.save()
        write_csv(ep, out / "episodes.csv")
        write_csv(study.policy_table(ep), out / "policies.csv")
        write_csv(comp, out / "comparisons.csv")
        write_csv(sweeps, out / "sweeps.csv")
        report = study.write_report(ep, comp, out, report_command("compare-learned", argv), sweeps)
    print(f"wrote {report} and the tables beside it")
    return rc
