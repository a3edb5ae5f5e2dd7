"""The leaderboard as ``run`` and ``leaderboard`` print it: within 100 columns (a label too long
for its row takes a line of its own, never cut), units under the column names, one block per
scenario, size and V2V setting, a failed column only where a run failed."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from analysis.tables import TERMINAL_WIDTH, format_leaderboard
from benchmark.export import leaderboard_frame

GOLDEN = Path(__file__).resolve().parents[1] / "golden"


def test_the_printed_leaderboard_fits_100_columns_with_units() -> None:
    runs = pd.read_csv(GOLDEN / "smoke_runs.csv")
    runs = runs.astype({"controller": object})
    first = runs["controller"].iloc[0]
    long = "ippo[scenario=mixed-v1,seeds=0+1+2,variant=residual-timed]"
    lb = leaderboard_frame(pd.concat([runs, runs[runs["controller"] == first]
                                      .assign(controller=long)]))
    text = format_leaderboard(lb)
    lines = text.splitlines()
    assert TERMINAL_WIDTH == 100 and max(map(len, lines)) <= 100
    assert any(line.strip().endswith(long) for line in lines)  # on a line of its own, whole
    head = next(i for i, line in enumerate(lines) if line.startswith("rank controller"))
    names, units = lines[head].split(), lines[head + 1].split()
    for name in ("coll.", "reward", "[95%", "CI]", "energy", "gap", "RMSE", "compute"):
        assert name in names
    for unit in ("/eps", "kWh", "m", "ms/veh/step"):
        assert unit in units
    blocks = lb.groupby(["scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s"])
    assert sum(line.startswith("rank controller") for line in lines) == blocks.ngroups
    assert "failed" not in lines[head]
    assert "leaderboard.csv" in text  # where the other columns are
    # with the frequency sweep's column (benchmark.sweep), a collided sweep included
    swept = lb.assign(sweep_peak_gain=1.5, sweep_string_stable=False)
    swept.loc[swept.index[0], "sweep_peak_gain"] = float("inf")
    assert max(map(len, format_leaderboard(swept).splitlines())) <= 100


def test_a_failed_column_appears_where_runs_failed() -> None:
    runs = pd.read_csv(GOLDEN / "smoke_runs.csv")
    runs = runs.astype({"error": object})
    runs.loc[runs.index[0], ["status", "error"]] = ["failed", "boom"]
    text = format_leaderboard(leaderboard_frame(runs))
    assert "failed" in next(ln for ln in text.splitlines() if ln.startswith("rank controller"))
    assert max(map(len, text.splitlines())) <= 100
