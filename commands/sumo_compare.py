"""``cacc-bench sumo-compare``: the built-in simulator and SUMO side by side, one report.

Writes ``OUT/report.md`` and one CSV per table (:func:`studies.sumo_compare.write_report`): the
same controllers' trajectories in both simulators, every family's metrics, our ``cacc`` against
Plexe's Ploeg controller, our energy against SUMO's MMPEVEM, our IDM humans and the ring's waves
against SUMO's IDM, and the speeds. Needs the sumo extra (``pip install -e '.[sumo]'``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from commands.cli import command_parser, out_folder
from infra.errors import ConfigError


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench sumo-compare``."""
    from benchmark.suite import seeds_from_episodes
    from envs.simulators import check_simulator
    from infra.limits import check_range

    p = command_parser("sumo-compare", __doc__, raw=True)
    p.add_argument("--out", default="docs/sumo", help="report folder (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=3,
                   help="the first K published evaluation seeds of every comparison "
                        "(default 3, at most 50)")
    p.add_argument("--overwrite", action="store_true",
                   help="make the report in --out again when it holds one (its files are "
                        "replaced together once the new report is whole)")
    args = p.parse_args(argv)
    check_range(args.episodes, "--episodes", 1, 50)
    check_simulator("sumo")  # without the extra: the install command, exit 2
    from studies.sumo_compare import write_report

    with out_folder(args.out) as out:  # a second writer of the folder is refused, naming the first
        _check_outputs(out, args.overwrite)
        path = write_report(out, seeds_from_episodes(args.episodes))
    print(f"wrote {path}")
    return 0


def _check_outputs(out: Path, overwrite: bool) -> None:
    """Refuse, before any work, a folder that holds a report unless ``overwrite`` (a finished
    file changes only when asked; then say so in one line), and a folder where a file goes."""
    from studies.sumo_compare import REPORT_FILES

    wrong = [name for name in REPORT_FILES if (out / name).is_dir()]
    if wrong:
        raise ConfigError(f"--out {out}: {wrong[0]} is a folder, where the report writes a "
                          "file; move it away, or choose another --out")
    held = [name for name in REPORT_FILES if (out / name).exists()]
    if held and not overwrite:
        raise ConfigError(f"--out {out} already holds a SUMO report ({held[0]}); add "
                          "--overwrite to make it again (its files are replaced together once "
                          "the new report is whole), or choose another --out")
    if held:
        print(f"--overwrite: {out} holds a SUMO report ({held[0]}); making it again: "
              "its files are replaced together once the new report is whole", file=sys.stderr)
