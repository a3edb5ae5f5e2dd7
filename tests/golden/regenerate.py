"""Regenerate the golden runs files deliberately: ``python tests/golden/regenerate.py``.

The tests only compare against these files; after running this, read the diff and say in the
commit why the numbers changed.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import pandas as pd

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "test_benchmark"))

from test_harness import GOLDEN_FILES, golden_frame  # noqa: E402
from test_leaderboard_rank import golden_leaderboard  # noqa: E402


def main() -> None:
    """Run every golden sweep and overwrite its file."""
    for name, args in GOLDEN_FILES.items():
        with tempfile.TemporaryDirectory() as tmp:
            frame = golden_frame(args, Path(tmp) / "run")
        frame.to_csv(HERE / name, index=False, float_format="%.10g")
        print(f"wrote {HERE / name} ({len(frame)} rows)")
    lb = golden_leaderboard(pd.read_csv(HERE / "smoke_runs.csv"))
    lb.to_csv(HERE / "smoke_leaderboard.csv", index=False, float_format="%.10g")
    print(f"wrote {HERE / 'smoke_leaderboard.csv'} ({len(lb)} rows)")


if __name__ == "__main__":
    main()
