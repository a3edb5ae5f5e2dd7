"""``cacc-bench leaderboard DIR``: rebuild runs.csv and leaderboard.csv from the store (each row
with its configuration's frequency sweep, read from the folder's ``string_sweeps.json`` or
measured and added to it)."""

from __future__ import annotations

from pathlib import Path

from benchmark.store import ResultStore
from commands.cli import check_executor, command_parser
from commands.run import add_rank_by_option


def main(argv: list[str]) -> int:
    """Rebuild the CSV files of one or more results folders from their stores."""
    from analysis.tables import format_leaderboard
    from benchmark.export import write_csvs

    p = command_parser("leaderboard", __doc__)
    p.add_argument("results_dir", nargs="+", help="results folder(s) written by `cacc-bench run`")
    p.add_argument("--quiet", action="store_true", help="do not print the table")
    p.add_argument("--pool-seeds", action="store_true",
                   help="one row per MARL policy over its training seeds (bdc:seed=0, "
                        "bdc:seed=1, ...): a two-stage bootstrap over seeds, then episodes")
    add_rank_by_option(p)
    p.add_argument("--executor", choices=("serial", "process"), default="serial",
                   help="where the frequency sweeps not yet in a folder's cache run "
                        "(default: serial)")
    p.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    args = p.parse_args(argv)
    check_executor(args.workers)
    for folder in args.results_dir:
        with ResultStore(Path(folder), create=False, writer=True) as store:
            records = store.records()
            runs_path, lb_path, lb = write_csvs(Path(folder), records, args.pool_seeds,
                                                rank_by=args.rank_by, executor=args.executor,
                                                workers=args.workers)
        if not args.quiet:
            print(format_leaderboard(lb))
        print(f"wrote {runs_path} ({len(records)} runs) and {lb_path}")
    return 0
