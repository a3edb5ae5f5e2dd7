"""``cacc-bench generalise``: the generalisation matrix on the test seeds, in one report.

Every shipped learned policy (per training scenario or family, three training seeds pooled, or
the one seed shipped of a per-agent policy trained at N = 4), with and without the safety filter,
and the model-based controllers, on the columns of :data:`studies.generalisation.COLUMNS` (other
scenarios, the OpenACC windows, N = 4 and 12, degraded V2V), through the results store
(resumable, ``--resume``); writes ``report.md``, ``matrix.csv``, ``filter_cost.csv``,
``rows.json`` and ``figures/generalisation.{png,pdf}`` into ``--out``; the report lists the
shipped checkpoints no row runs, with why (:data:`studies.generalisation.NOT_IN_MATRIX`).
"""

from __future__ import annotations

import argparse

from commands.cli import add_study_options, command_parser
from infra.errors import ConfigError


def _parser() -> argparse.ArgumentParser:
    p = command_parser("generalise", __doc__)
    p.add_argument("--episodes", type=int, default=10,
                   help="first K test seeds per cell and training seed (default: %(default)s)")
    p.add_argument("--no-safety-filter", action="store_true",
                   help="leave out the learned rows behind the safety filter")
    p.add_argument("--controllers", default=None,
                   help="only the rows of these controllers (comma list, e.g. cacc,ippo,safe:ippo;"
                        " default: every row); a controller with no row of its own (idm, "
                        "my_module:MyController, mpc:horizon=30) is one more row")
    p.add_argument("--columns", default=None,
                   help="only these columns (comma list of their names; default: all)")
    add_study_options(p, "results/generalise", "matrix")
    return p


def _available(controller: str, options: dict[str, str], n_vehicles: int) -> bool:
    """Whether the shipped checkpoint of a learned spec, trained at ``n_vehicles``, exists."""
    from controllers.policy import VARIANT_DIR, checkpoint_path

    folder = VARIANT_DIR / options["variant"] if "variant" in options else None
    return checkpoint_path(controller, options["scenario"], n_vehicles, int(options["seed"]),
                           folder).exists()


def _select_rows(rows: list, text: str) -> list:
    """The rows of ``--controllers``: a name with rows (``cacc``, ``ippo``, ``safe:ippo``) keeps
    them; any other controller that is not a learned policy (a registered one with no row, one
    with options, a ``package.module:Class`` of the user's) is one more row, labelled as in the
    leaderboard. Repeats are said on standard error."""
    from commands.cli import controllers_argument
    from controllers.registry import controller_label, resolve
    from studies.generalisation import Row

    out = []
    for name, options in controllers_argument(text):
        mine = [r for r in rows if r.controller == name] if not options else []
        if not mine and resolve(name).family == "marl":
            raise ConfigError(f"--controllers: no row of {name}"
                              f"{'' if not options else ' with options'}; rows are of "
                              f"{', '.join(sorted({r.controller for r in rows}))}")
        label = controller_label(name, options)
        out += mine or [Row(label, name, tuple(sorted(options.items())), False)]
    return out


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench generalise``."""
    import pandas as pd

    from benchmark.export import write_csv
    from benchmark.suite import build_sweep, seeds_from_set
    from commands.cli import check_executor, named_once, report_command
    from commands.run import study_sweep
    from controllers.policy import CHECKPOINT_DIR
    from infra.atomic import write_text
    from studies import generalisation as study

    args = _parser().parse_args(argv)

    check_executor(args.workers, args.ray_address)
    seeds = seeds_from_set("test", args.episodes)
    learned = study.learned_rows(_available)
    rows = [*learned, *([] if args.no_safety_filter else map(study.with_safety_filter, learned)),
            *(study.Row(name, name, (), False) for name in study.MODEL_BASED)]
    if args.controllers is not None:
        rows = _select_rows(rows, args.controllers)
    columns = list(study.COLUMNS)
    if args.columns is not None:
        names = [c.strip() for c in args.columns.split(",") if c.strip()]
        names = named_once(names, names, "--columns")
        known = {c.name: c for c in study.COLUMNS}
        bad = [c for c in names if c not in known]
        if bad or not names:
            raise ConfigError(f"--columns: unknown {', '.join(bad) or 'nothing named'}; the "
                              f"columns are {', '.join(known)}")
        columns = [known[c] for c in names]
    keys = set()
    for row in rows:
        for col in columns:
            if row.applies(col):
                keys.update(build_sweep(row.specs(), [col.built],
                                        [col.n_vehicles], seeds, [col.comm_delay_s],
                                        [col.packet_loss]))
    with study_sweep(keys, args, f"generalise: {len(rows)} rows x {len(columns)} columns x "
                     f"{len(seeds)} test episodes = {len(keys)} runs", seeds[0]) as (out, rc):
        cells = study.cell_frame(pd.read_csv(out / "runs" / "runs.csv"), rows, columns)
        write_csv(cells, out / "matrix.csv")
        write_csv(study.filter_cost(cells), out / "filter_cost.csv")
        write_text(out / "rows.json", study.rows_json(rows) + "\n")
        study.plot_heatmap(cells, out / "figures", columns)
        report = study.write_report(cells, out, report_command("generalise", argv), len(seeds),
                                    columns, study.unrun_checkpoints(CHECKPOINT_DIR, learned))
    print(f"wrote {report} and the matrix beside it")
    return rc
