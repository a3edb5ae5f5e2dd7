"""Compare two `cacc-bench reproduce` folders: each claim's verdict, and Table II's reward,
collisions and power per row.

    .venv/bin/python docs/scripts/compare_reproductions.py docs/paper-reproduction results/paper
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd


def main(first: str, second: str) -> int:
    a, b = Path(first), Path(second)
    ca, cb = pd.read_csv(a / "claims.csv"), pd.read_csv(b / "claims.csv")
    same = 0
    for i, (x, y) in enumerate(zip(ca.itertuples(), cb.itertuples(), strict=True)):
        ok = x.verdict == y.verdict
        same += ok
        print(f"{i:2d} {'==' if ok else '!='} {x.verdict:18s} {y.verdict:18s} {x.claim[:70]}")
    print(f"verdicts equal: {same} of {len(ca)}")
    cols = ["reward_mean", "collisions", "power_kw_avg"]
    m = pd.read_csv(a / "table2.csv").merge(pd.read_csv(b / "table2.csv"),
                                            on=["scenario", "name"], suffixes=("_1", "_2"))
    print(m[["scenario", "name"] + [f"{c}_{s}" for c in cols for s in "12"]]
          .to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: compare_reproductions.py FIRST_FOLDER SECOND_FOLDER")
    sys.exit(main(sys.argv[1], sys.argv[2]))
