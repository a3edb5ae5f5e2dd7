"""Figures stay readable with many controllers: wrapped facets, names on the axes, a legend
only for what is drawn."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

import analysis.plots as plots


def _leaderboard(n_controllers: int, scenarios: list[str]) -> pd.DataFrame:
    rows = []
    for sc in scenarios:
        for i in range(n_controllers):
            row: dict[str, Any] = {"controller": f"ctrl{i:02d}", "scenario": sc, "n_vehicles": 8,
                                   "family": "marl" if i % 2 else "mpc", "rank": i + 1,
                                   "comm_delay_s": 0.0, "packet_loss": 0.0, "lag_s": 0.0}
            for m, _ in plots.BAR_METRICS:
                row.update({f"{m}_mean": -i - 1.0, f"{m}_ci_low": -i - 1.5,
                            f"{m}_ci_high": -i - 0.5})
            rows.append(row)
    return pd.DataFrame(rows)


@pytest.fixture
def captured(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    figs: list[Any] = []
    monkeypatch.setattr(plots, "_save", lambda fig, out_dir, stem: figs.append(fig) or [])
    return figs


def test_twenty_controllers_four_settings(captured: list[Any]) -> None:
    lb = _leaderboard(20, ["catchup-v1", "slowdown-v1", "brake-v1", "sine-v1"])
    plots.plot_leaderboard(lb, Path("unused"))
    fig = captured[0]
    visible = [ax for ax in fig.axes if ax.get_visible()]
    assert len(visible) == len(plots.BAR_METRICS) * 4
    # wrapped: at most FACET_COLUMNS panels per row
    columns = {round(ax.get_position().x0, 2) for ax in visible}
    assert len(columns) == plots.FACET_COLUMNS
    # every controller named on every panel, in rank order from the top
    for ax in visible:
        names = [t.get_text() for t in ax.get_yticklabels()]
        assert sorted(names) == [f"ctrl{i:02d}" for i in range(20)]
        ticks = ax.get_yticks()
        assert names[int(np.argmax(ticks))] == "ctrl00"
    legend_labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend_labels == ["marl", "mpc"]  # only the families drawn
    width, height = fig.get_size_inches()
    assert width <= 15 and height / len(columns) < 80


def test_radar_colours_stay_distinct_for_twenty(captured: list[Any]) -> None:
    lb = _leaderboard(20, ["catchup-v1"])
    for m, _ in plots.RADAR_AXES:
        lb[f"{m}_mean"] = np.linspace(1, 2, 20)
    plots.plot_radar(lb, "catchup-v1", 8, Path("unused"), "radar")
    lines = captured[0].axes[0].get_lines()
    styles = {(tuple(np.round(line.get_color(), 3)), line.get_linestyle()) for line in lines}
    assert len(styles) == 20
