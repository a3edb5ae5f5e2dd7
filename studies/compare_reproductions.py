"""Compare two `cacc-bench reproduce` folders: each claim's verdict, Table II's reward,
collisions and power per row, and then every table cell by cell as the command wrote it.

    .venv/bin/python -m studies.compare_reproductions docs/paper-reproduction results/paper

The cell-by-cell part reads each CSV as text (so "equal" is to the last printed digit) and leaves
out the timing columns (``compute_ms_*``: a controller's compute time is the machine's, not the
result's). The leaderboard is ``leaderboard.csv`` in a published folder and
``runs/leaderboard.csv`` in a command's own. Exit status, as ``diff``'s: 0 when every table is
equal, 1 when one differs, 2 when a folder holds no report.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

from studies import publish_reproduction

#: The tables compared cell by cell, as ``reproduce`` writes them.
TABLES = (*publish_reproduction.TABLES, "leaderboard.csv")
#: Column prefixes left out of the cell-by-cell comparison: the machine's timings.
TIMING = ("compute_ms",)


def _table(folder: Path, name: str) -> Path:
    path = folder / name
    if name == "leaderboard.csv" and not path.exists():
        path = folder / "runs" / name
    return path


def differing_cells(first: Path, second: Path) -> dict[str, int] | None:
    """Per column, how many cells of two CSVs differ as text (timing columns left out);
    ``None`` when their rows or columns differ, so no cell-by-cell comparison is meaningful."""
    a, b = (pd.read_csv(p, dtype=str, keep_default_na=False) for p in (first, second))
    if list(a.columns) != list(b.columns) or len(a) != len(b):
        return None
    counts = {c: int((a[c] != b[c]).sum()) for c in a.columns if not c.startswith(TIMING)}
    return {c: n for c, n in counts.items() if n}


def compare_tables(a: Path, b: Path) -> bool:
    """Print, for each table, whether the two folders agree cell by cell; whether all do."""
    equal = True
    for name in TABLES:
        pa, pb = _table(a, name), _table(b, name)
        if not (pa.exists() and pb.exists()):
            print(f"{name}: missing in {a if not pa.exists() else b}")
            equal = False
            continue
        diff = differing_cells(pa, pb)
        if diff is None:
            print(f"{name}: other rows or columns")
        elif diff:
            print(f"{name}: {sum(diff.values())} cells differ ("
                  + ", ".join(f"{c} {n}" for c, n in diff.items()) + ")")
        else:
            print(f"{name}: equal (timings aside)")
        equal = equal and diff == {}
    return equal


def main(first: str, second: str) -> int:
    """Print the comparison of two reproduce folders; the exit status (module docstring)."""
    a, b = Path(first), Path(second)
    for folder in (a, b):
        if not (folder / "claims.csv").is_file():
            print(f"{folder}: no claims.csv; give two folders written by `cacc-bench reproduce` "
                  "(or published by studies/publish_reproduction.py)", file=sys.stderr)
            return 2
    ca, cb = pd.read_csv(a / "claims.csv"), pd.read_csv(b / "claims.csv")
    if len(ca) != len(cb):
        print(f"the two reports judge {len(ca)} and {len(cb)} claims: made by other versions of "
              "the command, so not comparable claim by claim")
        return 1
    rows = zip(ca["verdict"].tolist(), cb["verdict"].tolist(), ca["claim"].tolist(), strict=True)
    for i, (x, y, claim) in enumerate(rows):
        print(f"{i:2d} {'==' if x == y else '!='} {x:18s} {y:18s} {claim[:70]}")
    print(f"verdicts equal: {int((ca['verdict'] == cb['verdict']).sum())} of {len(ca)}")
    cols = ["reward_mean", "collisions", "power_kw_avg"]
    m = pd.read_csv(a / "table2.csv").merge(pd.read_csv(b / "table2.csv"),
                                            on=["scenario", "name"], suffixes=("_1", "_2"))
    print(m[["scenario", "name"] + [f"{c}_{s}" for c in cols for s in "12"]]
          .to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    equal = compare_tables(a, b)
    print("every table equal (timings aside)" if equal else "the tables differ")
    return 0 if equal else 1


if __name__ == "__main__":
    if len(sys.argv) != 3:
        print("usage: python -m studies.compare_reproductions FIRST_FOLDER SECOND_FOLDER",
              file=sys.stderr)
        sys.exit(2)
    sys.exit(main(sys.argv[1], sys.argv[2]))
