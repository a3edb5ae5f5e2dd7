"""``cacc-bench heterogeneous``: strings of a bus, a van and cars in three orders, with and
without human drivers, under every controller family, in one report.

Every family of :data:`studies.heterogeneous.DEFAULT_FAMILIES` on every order of
:data:`studies.heterogeneous.ORDERS`, every seat automated and with humans at the seats of
:data:`studies.heterogeneous.HUMANS`, beside the all-human string (``idm``), on the scenarios of
:data:`studies.heterogeneous.SCENARIOS`, through the results store (resumable, ``--resume``);
then the analytic and measured head-to-tail peaks of the linear families. Writes ``README.md``,
``cells.csv``, ``head_to_tail.csv`` and ``figures/`` into ``--out``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmark.executors import add_executor_options
from commands.cli import check_executor, plain, report_command
from infra.errors import ConfigError

#: The figures the study writes, under ``figures/``.
FIGURES: tuple[str, ...] = ("head-to-tail-peaks.png", "energy-by-order.png")


def _parser() -> argparse.ArgumentParser:
    from studies.heterogeneous import DEFAULT_FAMILIES, SCENARIOS

    p = argparse.ArgumentParser(prog="cacc-bench heterogeneous",
                                description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--episodes", type=int, default=1,
                   help="first K test seeds per cell (default: %(default)s)")
    p.add_argument("--scenarios", default=",".join(SCENARIOS),
                   help="comma list of scenario ids (default: %(default)s)")
    p.add_argument("--controllers", default=",".join(DEFAULT_FAMILIES),
                   help="the families (comma list of registered controllers; default: "
                        "%(default)s)")
    p.add_argument("--orders", default=None,
                   help="comma list of the orders to run (default: all of "
                        "studies.heterogeneous.ORDERS: heavy first, heavy last, spread)")
    p.add_argument("--out", default="results/heterogeneous",
                   help="output folder (default: %(default)s)")
    p.add_argument("--resume", action="store_true", help="complete a study in --out")
    add_executor_options(p, default="process")
    return p


def _check_outputs(out: Path, resume: bool) -> None:
    """Refuse, before any run, a folder holding a study unless ``resume``, and output paths
    that cannot be written (a folder where a file goes, a file where a folder goes)."""
    held = [name for name in ("README.md", "cells.csv", "runs/store.sqlite")
            if (out / name).exists()]
    if held and not resume:
        raise ConfigError(f"--out {out} already holds a heterogeneous study ({held[0]}); add "
                          "--resume to complete it (stored runs are kept; the tables, figures "
                          "and report are made again), or choose another --out")
    files = [out / "README.md", out / "cells.csv", out / "head_to_tail.csv",
             *(out / "figures" / f for f in FIGURES)]
    wrong = ([p for p in files if p.is_dir()]
             + [p for p in (out / "runs", out / "figures") if p.exists() and not p.is_dir()])
    if wrong:
        kind = "a folder" if wrong[0].is_dir() else "a file"
        raise ConfigError(f"--out {out}: {wrong[0].relative_to(out)} is {kind}, where the study "
                          "writes the other; move it away, or choose another --out")


def _orders(text: str | None) -> list[str]:
    """The orders named by ``--orders`` (all when it is not given); an unknown one, or a list
    that names none (``--orders ''``), is refused."""
    from studies.heterogeneous import ORDERS

    if text is None:
        return list(ORDERS)
    names = [t.strip() for t in text.split(",") if t.strip()]
    if not names:
        raise ConfigError(f"--orders: no order named; name one or more of {', '.join(ORDERS)} "
                          "(comma list), or leave --orders out for all of them")
    unknown = [n for n in names if n not in ORDERS]
    if unknown:
        raise ConfigError(f"--orders: unknown order {unknown[0]!r}; the orders are "
                          f"{', '.join(ORDERS)}")
    return list(dict.fromkeys(names))


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench heterogeneous``."""
    import pandas as pd

    from benchmark.export import write_csv
    from benchmark.folder_lock import folder_lock
    from benchmark.paths import writable_dir
    from benchmark.suite import build_sweep, seeds_from_set
    from commands.cli import scenarios_argument
    from commands.run import execute_study_sweep, preflight
    from controllers.registry import parse_controller_list
    from studies.heterogeneous import (
        BASELINE,
        Setting,
        cells,
        controllers_for,
        head_to_tail_peaks,
        plot_energy,
        plot_peaks,
        write_report,
    )

    args = _parser().parse_args(argv)
    check_executor(args.workers, args.ray_address)
    seeds = seeds_from_set("test", args.episodes)
    families = parse_controller_list(args.controllers)
    if (BASELINE, {}) in families:
        raise ConfigError(f"--controllers {BASELINE}: {BASELINE} is the study's all-human "
                          "baseline, not a family to compare with it; name the automated "
                          "families")
    orders = _orders(args.orders)
    bases = []
    for given in scenarios_argument(args.scenarios):
        if given.label != given.id:
            raise ConfigError(f"--scenarios {given.label}: the study sets the classes and the "
                              "human seats itself; name the scenario without options")
        bases.append(given.id)
    settings = [Setting(sc, order, h) for sc in dict.fromkeys(bases) for order in orders
                for h in ("none", "mixed", "all")]
    keys = set()
    for setting in settings:
        sc = [setting.build()]
        specs = controllers_for(setting, families)
        n = sc[0].default_vehicles
        preflight(specs, sc, [n], [0.0])  # refused before any run, with exit status 2
        keys.update(build_sweep(specs, sc, [n], seeds, [0.0], [0.0]))
    out = writable_dir(args.out)
    _check_outputs(out, args.resume)
    command = report_command("heterogeneous", argv)
    with folder_lock(out):
        rc = execute_study_sweep(keys, out, args, f"heterogeneous: {len(settings)} scenario "
                                 f"settings x {len(seeds)} test episodes = {len(keys)} runs",
                                 seeds[0])
        table = cells(pd.read_csv(out / "runs" / "runs.csv"), settings)
        write_csv(table, out / "cells.csv")
        peaks = head_to_tail_peaks(orders)
        write_csv(peaks, out / "head_to_tail.csv")
        figures = [plot_peaks(peaks, out / "figures" / FIGURES[0]),
                   plot_energy(table, out / "figures" / FIGURES[1])]
        report = write_report(table, peaks, out, command, len(seeds), figures)
    print(f"wrote {report} and the tables beside it")
    return rc
