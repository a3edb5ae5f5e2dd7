"""``cacc-bench string-stability``: string stability against reward for every controller.

One report. Runs the controllers of :func:`studies.string_stability.default_entries` (learned ones with
their three shipped training seeds) on the test seeds under ideal, no and degraded V2V through
the results store (resumable, ``--resume``), measures each one's standard frequency sweep at
N = 4, 8 and 12 (cached in the folder), certifies the segment of every ``ippo-gains`` policy,
reads the design grid of fixed ``cacc`` gains on the validation seeds, and writes
``report.md`` with ``rewards.csv``, ``sweeps.csv``, ``goal.csv``, ``v2v.csv``,
``certificate.csv``, ``segments.csv``, ``design.csv``, ``tradeoff.csv`` and ``episodes.csv``
into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from commands.cli import add_scenarios_option, add_study_options, command_parser
from infra.errors import ConfigError


def _parser() -> argparse.ArgumentParser:
    from studies.string_stability import SWEEP_SIZES

    p = command_parser("string-stability", __doc__)
    add_scenarios_option(p, "catchup-v1,slowdown-v1")
    p.add_argument("--episodes", type=int, default=None,
                   help="first K test seeds per controller and training seed (default: all 100)")
    p.add_argument("--validation-episodes", type=int, default=None,
                   help="first K validation seeds of the design grid (default: all 32)")
    p.add_argument("--design", default="full", choices=("full", "small"),
                   help="the design grid of fixed cacc gains (default: %(default)s)")
    p.add_argument("--sizes", default=",".join(map(str, SWEEP_SIZES)),
                   help="platoon sizes of the frequency sweeps (default: %(default)s)")
    p.add_argument("--controllers", default=None,
                   help="only these entries of the report, by their controller name (comma "
                        "list, e.g. cacc,ippo-gains; default: all; cacc is always kept, the "
                        "reference of the goal)")
    add_study_options(p, "results/string-stability", "report")
    return p


def _sizes(text: str) -> list[int]:
    from envs.scenarios import check_vehicles

    try:
        sizes = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--sizes takes a comma list of platoon sizes, got {text!r}") from None
    if not sizes:
        raise ConfigError("--sizes: no platoon size given")
    return sorted({check_vehicles(n) for n in sizes})


def _entries(text: str | None, scenarios: list[str]) -> list:
    from studies.string_stability import available, default_entries

    entries = list(default_entries())
    if text is not None:
        names = {c.strip() for c in text.split(",") if c.strip()}
        known = {e.controller for e in entries}
        if not names:
            raise ConfigError(f"--controllers names no controller; give some of "
                              f"{', '.join(sorted(known))}, or leave the option out for all")
        unknown = sorted(names - known)
        if unknown:
            raise ConfigError(f"--controllers: {', '.join(unknown)} is no entry of the report; "
                              f"its controllers are {', '.join(sorted(known))}")
        entries = [e for e in entries if e.controller in names or e.name == "cacc"]
    kept, notes = available(entries, scenarios)
    for line in notes:
        print(f"string-stability: {line}", file=sys.stderr)
    return kept


def _design(out: Path, args: argparse.Namespace, scenarios: list[str],
            seeds: list[int]) -> Any:
    """The design grid: with ``--resume``, the folder's ``design.csv`` when it holds this grid
    on these scenarios and validation seeds, else measured."""
    from studies import string_stability as st

    path = out / "design.csv"
    if args.resume and path.exists():
        from infra.files import read_csv

        held = read_csv(path, "the design table")
        kps, kds, hs = st.DESIGN_GRIDS[args.design]
        same = (len(held) == len(kps) * len(kds) * len(hs)
                and "validation_episodes" in held and set(held["validation_episodes"]) == {
                    len(seeds)}
                and all(f"reward_{sc}" in held for sc in scenarios)
                and sorted(zip(held["kp"], held["kd"], held["time_gap_s"], strict=True))
                == sorted((kp, kd, h) for kp in kps for kd in kds for h in hs))
        if same:
            return held
    return st.design_grid(args.design, scenarios, seeds)


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench string-stability``."""
    from benchmark.suite import build_sweep, seeds_from_set
    from benchmark.sweep import SweepCache
    from commands.cli import check_executor, report_command, scenarios_argument
    from commands.run import study_sweep
    from envs.params import VALIDATION_SEEDS
    from infra.files import read_csv
    from infra.limits import check_range
    from studies import string_stability as st

    args = _parser().parse_args(argv)
    scenarios = scenarios_argument(args.scenarios)
    labels = [sc.label for sc in scenarios]
    check_executor(args.workers, args.ray_address)
    test_seeds = seeds_from_set("test", args.episodes)
    if args.validation_episodes is not None:
        check_range(args.validation_episodes, "--validation-episodes", 1, len(VALIDATION_SEEDS))
    val_seeds = list(VALIDATION_SEEDS)[: args.validation_episodes or len(VALIDATION_SEEDS)]
    sizes = _sizes(args.sizes)
    entries = _entries(args.controllers, labels)
    specs = st.run_specs(entries)
    keys = {k for delay, loss in st.CHANNELS.values()
            for k in build_sweep(specs, scenarios, [st.REWARD_N], test_seeds, [delay], [loss])}
    with study_sweep(keys, args, f"string-stability: {len(specs)} controllers x "
                     f"{len(scenarios)} scenarios x {len(st.CHANNELS)} V2V settings x "
                     f"{len(test_seeds)} test episodes = {len(keys)} runs",
                     test_seeds[0]) as (out, rc):
        episodes = st.episodes_frame(read_csv(out / "runs" / "runs.csv", "the runs table"),
                                     entries)
        rewards = st.reward_table(episodes, entries)
        print("string-stability: frequency sweeps", file=sys.stderr)
        cache = SweepCache(out)
        try:
            sweeps = st.sweeps_frame(entries, labels, sizes, cache)
        finally:
            cache.save()
        print("string-stability: certificates and the design grid (validation seeds)",
              file=sys.stderr)
        from marl.ippo_gains import GainScheduleConfig

        design = _design(out, args, labels, val_seeds)
        tables = {
            "rewards": rewards, "sweeps": sweeps,
            "goal": st.goal_frame(episodes, sweeps, entries),
            "v2v": st.v2v_worth(rewards),
            "certificate": st.certificate(GainScheduleConfig().segment),
            "segments": st.checkpoint_segments(labels),
            "design": design, "tradeoff": st.tradeoff(design, labels),
        }
        report = st.write_tables(tables, episodes, out, report_command("string-stability", argv))
    print(f"wrote {report} and the tables beside it")
    return rc
