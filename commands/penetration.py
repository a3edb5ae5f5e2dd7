"""``cacc-bench penetration``: which controller family damps waves at what share of automated
vehicles, on the test seeds, in one report.

Every family of :data:`studies.penetration.DEFAULT_FAMILIES` at every share of
:data:`studies.penetration.SHARES` (the mixed ones at ``--placements`` seeded random placements)
on the scenarios of :data:`studies.penetration.SCENARIOS`, beside the all-human string (``idm``
at no automated vehicle), through the results store (resumable, ``--resume``); writes
``report.md``, ``cells.csv`` and ``figures/penetration-<scenario>.png`` into ``--out``.
"""

from __future__ import annotations

import argparse

from commands.cli import add_scenarios_option, add_study_options, command_parser
from infra.errors import ConfigError

#: Most placements a mixed share is drawn at.
MAX_PLACEMENTS = 20


def _parser() -> argparse.ArgumentParser:
    from studies.penetration import DEFAULT_FAMILIES, SCENARIOS

    p = command_parser("penetration", __doc__)
    p.add_argument("--episodes", type=int, default=5,
                   help="first K test seeds per placement (default: %(default)s)")
    p.add_argument("--placements", type=int, default=3,
                   help="seeded random placements of each mixed share (default: %(default)s)")
    add_scenarios_option(p, ",".join(SCENARIOS))
    p.add_argument("--controllers", default=",".join(DEFAULT_FAMILIES),
                   help="the families (comma list of registered controllers; default: "
                        "%(default)s)")
    add_study_options(p, "results/penetration")
    return p


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench penetration``."""
    import pandas as pd

    from benchmark.export import write_csv
    from benchmark.suite import seeds_from_set
    from commands.cli import check_executor, check_study_folder, report_command, scenarios_argument
    from commands.run import study_keys, study_sweep
    from controllers.registry import parse_controller_list
    from envs.scenarios import PLACEMENT_OPTIONS, SEAT_OPTIONS, make_scenario
    from infra.limits import check_range
    from studies import penetration as study

    args = _parser().parse_args(argv)

    check_executor(args.workers, args.ray_address)
    check_range(args.placements, "--placements", 1, MAX_PLACEMENTS)
    seeds = seeds_from_set("test", args.episodes)
    families = parse_controller_list(args.controllers)  # names with their options
    if (study.BASELINE, {}) in families:
        raise ConfigError(f"--controllers {study.BASELINE}: {study.BASELINE} is the study's "
                          "all-human baseline (share 0 of every scenario), not a family to "
                          "compare with it; name the automated families (or an idm with options "
                          "of its own)")
    bases = []
    set_by_study = (*SEAT_OPTIONS, *PLACEMENT_OPTIONS)
    for given in scenarios_argument(args.scenarios):
        plain = make_scenario(given.base_name)  # the id, or a scenario of one's own's reference
        if any(given.options[k] != plain.options[k] for k in set_by_study):
            raise ConfigError(f"--scenarios {given.label}: the study sets which followers are "
                              f"automated itself ({', '.join(set_by_study)}); name the scenario "
                              "without them")
        bases.append(given.label)
    settings = study.design(list(dict.fromkeys(bases)), args.placements)
    keys = study_keys(((study.controllers_for(s.share, families), s.build()) for s in settings),
                      seeds)
    files = ["report.md", "cells.csv", *(f"figures/penetration-{sc}.png" for sc in bases)]
    with study_sweep(keys, args, f"penetration: {len(settings)} scenario settings x "
                     f"{len(seeds)} test episodes = {len(keys)} runs", seeds[0],
                     lambda out: check_study_folder(out, args.resume, "penetration", files,
                                                    "the table, figures and report")
                     ) as (out, rc):
        table = study.cells(pd.read_csv(out / "runs" / "runs.csv"), settings)
        write_csv(table, out / "cells.csv")
        figures = study.plot_shares(table, out / "figures")
        report = study.write_report(table, out, report_command("penetration", argv), len(seeds),
                                    args.placements, figures)
    print(f"wrote {report} and the table beside it")
    return rc
