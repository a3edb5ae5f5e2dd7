"""Make the trimmed OpenACC window files shipped with cacc-bench.

Reads the original JRC OpenACC ZalaZONE files from a folder given on the command line and
writes, next to this script (or to ``--out``), one trimmed copy per benchmark window
(:data:`envs.openacc.WINDOWS`, which names the files and the windows). The copy
keeps the original format byte for byte: the 5 metadata header lines, the column-name line and
the data rows whose ``Time`` lies in the window widened by a margin (5 s on each side), with
every column and value unchanged and the original line endings (CRLF). Nothing else changes.

Usage::

    python envs/data/openacc/make_windows.py /path/to/openacc/folder [--out DIR]

This is a maintenance script (it needs cacc-bench installed); the package and its tests never
run it.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from envs.openacc import WINDOWS

MARGIN_S = 5.0
N_HEADER_LINES = 6  # 5 metadata lines + the column-name line
TIME_TOL_S = 0.01
LICENCE_FILE = "JRC_copyright.txt"


def trim_bytes(raw: bytes, t_start_s: float, t_end_s: float, margin_s: float = MARGIN_S) -> bytes:
    """Keep the header lines and the data rows with ``Time`` in the widened window.

    Parameters
    ----------
    raw : bytes
        Whole original file.
    t_start_s, t_end_s : float
        Window bounds [s].
    margin_s : float
        Extra time kept on each side [s].

    Returns
    -------
    bytes
        The trimmed file; every kept line is byte-identical to the original line.
    """
    lines = raw.splitlines(keepends=True)
    header, rows = lines[:N_HEADER_LINES], lines[N_HEADER_LINES:]
    if not header[-1].startswith(b"Time,"):
        raise ValueError("line 6 is not the column-name line starting with 'Time,'")
    lo = t_start_s - margin_s - TIME_TOL_S
    hi = t_end_s + margin_s + TIME_TOL_S
    kept = [row for row in rows if row.strip() and lo <= float(row.split(b",", 1)[0]) <= hi]
    if not kept:
        raise ValueError(f"no rows with Time in [{lo}, {hi}] s")
    return b"".join(header + kept)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source_dir", type=Path, help="folder with the original OpenACC files")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for name, spec in WINDOWS.items():
        raw = (args.source_dir / spec.source_file_name).read_bytes()
        trimmed = trim_bytes(raw, spec.t_start_s, spec.t_end_s)
        target = args.out / spec.file_name
        target.write_bytes(trimmed)
        n_rows = len(trimmed.splitlines()) - N_HEADER_LINES
        print(f"{name}: {target.name}: {n_rows} rows, {len(trimmed)} bytes")
    licence = args.source_dir / LICENCE_FILE
    if licence.exists():
        shutil.copyfile(licence, args.out / LICENCE_FILE)
        print(f"copied {LICENCE_FILE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
