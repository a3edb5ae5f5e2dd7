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

from commands.cli import add_scenarios_option, add_study_options, command_parser
from infra.errors import ConfigError

#: The figures the study writes, under ``figures/``.
FIGURES: tuple[str, ...] = ("head-to-tail-peaks.png", "energy-by-order.png")


def _parser() -> argparse.ArgumentParser:
    from studies.heterogeneous import DEFAULT_FAMILIES, SCENARIOS

    p = command_parser("heterogeneous", __doc__)
    p.add_argument("--episodes", type=int, default=1,
                   help="first K test seeds per cell (default: %(default)s)")
    add_scenarios_option(p, ",".join(SCENARIOS))
    p.add_argument("--controllers", default=",".join(DEFAULT_FAMILIES),
                   help="the families (comma list of registered controllers; default: "
                        "%(default)s)")
    p.add_argument("--orders", default=None,
                   help="comma list of the orders to run (default: all of "
                        "studies.heterogeneous.ORDERS: heavy first, heavy last, spread)")
    add_study_options(p, "results/heterogeneous")
    return p


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
    from benchmark.suite import seeds_from_set
    from commands.cli import check_executor, check_study_folder, report_command, scenarios_argument
    from commands.run import study_keys, study_sweep
    from controllers.registry import parse_controller_list
    from studies import heterogeneous as study

    args = _parser().parse_args(argv)
    check_executor(args.workers, args.ray_address)
    seeds = seeds_from_set("test", args.episodes)
    families = parse_controller_list(args.controllers)
    if (study.BASELINE, {}) in families:
        raise ConfigError(f"--controllers {study.BASELINE}: {study.BASELINE} is the study's "
                          "all-human baseline, not a family to compare with it; name the "
                          "automated families")
    orders = _orders(args.orders)
    bases = []
    for given in scenarios_argument(args.scenarios):
        if given.label != given.id:
            raise ConfigError(f"--scenarios {given.label}: the study sets the classes and the "
                              "human seats itself; name the scenario without options")
        bases.append(given.id)
    settings = [study.Setting(sc, order, h) for sc in dict.fromkeys(bases) for order in orders
                for h in ("none", "mixed", "all")]
    keys = study_keys(((study.controllers_for(s, families), s.build()) for s in settings), seeds)
    files = ["README.md", "cells.csv", "head_to_tail.csv", *(f"figures/{f}" for f in FIGURES)]
    with study_sweep(keys, args, f"heterogeneous: {len(settings)} scenario settings x "
                     f"{len(seeds)} test episodes = {len(keys)} runs", seeds[0],
                     lambda out: check_study_folder(out, args.resume, "heterogeneous", files,
                                                    "the tables, figures and report")
                     ) as (out, rc):
        table = study.cells(pd.read_csv(out / "runs" / "runs.csv"), settings)
        write_csv(table, out / "cells.csv")
        peaks = study.head_to_tail_peaks(orders)
        write_csv(peaks, out / "head_to_tail.csv")
        figures = [study.plot_peaks(peaks, out / "figures" / FIGURES[0]),
                   study.plot_energy(table, out / "figures" / FIGURES[1])]
        report = study.write_report(table, peaks, out, report_command("heterogeneous", argv),
                                    len(seeds), figures)
    print(f"wrote {report} and the tables beside it")
    return rc
