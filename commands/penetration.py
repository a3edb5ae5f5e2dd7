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
from pathlib import Path

from benchmark.executors import add_executor_options
from commands.cli import check_executor, plain, report_command
from infra.errors import ConfigError

#: Most placements a mixed share is drawn at.
MAX_PLACEMENTS = 20


def _parser() -> argparse.ArgumentParser:
    from studies.penetration import DEFAULT_FAMILIES, SCENARIOS

    p = argparse.ArgumentParser(prog="cacc-bench penetration",
                                description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--episodes", type=int, default=5,
                   help="first K test seeds per placement (default: %(default)s)")
    p.add_argument("--placements", type=int, default=3,
                   help="seeded random placements of each mixed share (default: %(default)s)")
    p.add_argument("--scenarios", default=",".join(SCENARIOS),
                   help="comma list of scenario ids (default: %(default)s)")
    p.add_argument("--controllers", default=",".join(DEFAULT_FAMILIES),
                   help="the families (comma list of registered controllers; default: "
                        "%(default)s)")
    p.add_argument("--out", default="results/penetration",
                   help="output folder (default: %(default)s)")
    p.add_argument("--resume", action="store_true", help="complete a study in --out")
    add_executor_options(p, default="process")
    return p


def _check_outputs(out: Path, resume: bool, scenarios: list[str]) -> None:
    """Refuse, before any run, a folder holding a study unless ``resume`` (a finished file
    changes only when asked), and output paths that cannot be written (a folder where a file
    goes, a file where a folder goes)."""
    held = [name for name in ("report.md", "cells.csv", "runs/store.sqlite")
            if (out / name).exists()]
    if held and not resume:
        raise ConfigError(f"--out {out} already holds a penetration study ({held[0]}); add "
                          "--resume to complete it (stored runs are kept; the table, figures "
                          "and report are made again), or choose another --out")
    files = [out / "report.md", out / "cells.csv",
             *(out / "figures" / f"penetration-{sc}.png" for sc in scenarios)]
    wrong = ([p for p in files if p.is_dir()]
             + [p for p in (out / "runs", out / "figures") if p.exists() and not p.is_dir()])
    if wrong:
        kind = "a folder" if wrong[0].is_dir() else "a file"
        raise ConfigError(f"--out {out}: {wrong[0].relative_to(out)} is {kind}, where the study "
                          "writes the other; move it away, or choose another --out")


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench penetration``."""
    import pandas as pd

    from benchmark.export import write_csv
    from benchmark.folder_lock import folder_lock
    from benchmark.paths import writable_dir
    from benchmark.suite import build_sweep, seeds_from_set
    from commands.cli import scenarios_argument
    from commands.run import execute_study_sweep, preflight
    from controllers.registry import parse_controller_list
    from envs.scenarios import PLACEMENT_OPTIONS, SEAT_OPTIONS, make_scenario
    from infra.limits import check_range
    from studies.penetration import (
        BASELINE,
        cells,
        controllers_for,
        design,
        plot_shares,
        write_report,
    )

    args = _parser().parse_args(argv)

    check_executor(args.workers, args.ray_address)
    check_range(args.placements, "--placements", 1, MAX_PLACEMENTS)
    seeds = seeds_from_set("test", args.episodes)
    families = parse_controller_list(args.controllers)  # names with their options
    if (BASELINE, {}) in families:
        raise ConfigError(f"--controllers {BASELINE}: {BASELINE} is the study's all-human "
                          "baseline (share 0 of every scenario), not a family to compare with "
                          "it; name the automated families (or an idm with options of its own)")
    bases = []
    set_by_study = (*SEAT_OPTIONS, *PLACEMENT_OPTIONS)
    for given in scenarios_argument(args.scenarios):
        plain = make_scenario(given.base_name)  # the id, or a scenario of one's own's reference
        if any(given.options[k] != plain.options[k] for k in set_by_study):
            raise ConfigError(f"--scenarios {given.label}: the study sets which followers are "
                              f"automated itself ({', '.join(set_by_study)}); name the scenario "
                              "without them")
        bases.append(given.label)
    settings = design(list(dict.fromkeys(bases)), args.placements)
    keys = set()
    for setting in settings:
        sc = [setting.build()]
        specs = controllers_for(setting.share, families)
        n = sc[0].default_vehicles
        preflight(specs, sc, [n], [0.0])  # refused before any run, with exit status 2
        keys.update(build_sweep(specs, sc, [n], seeds, [0.0], [0.0]))
    out = writable_dir(args.out)
    _check_outputs(out, args.resume, bases)
    command = report_command("penetration", argv)
    with folder_lock(out):
        rc = execute_study_sweep(keys, out, args, f"penetration: {len(settings)} scenario "
                                 f"settings x {len(seeds)} test episodes = {len(keys)} runs",
                                 seeds[0])
        table = cells(pd.read_csv(out / "runs" / "runs.csv"), settings)
        write_csv(table, out / "cells.csv")
        figures = plot_shares(table, out / "figures")
        report = write_report(table, out, command, len(seeds), args.placements, figures)
    print(f"wrote {report} and the table beside it")
    return rc
