"""The figures a platoon paper shows, checked by what they draw (matplotlib artists: line data,
markers, texts, legend and title extents), not by the files existing."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

import analysis.plots as plots
from analysis import platoon_plots
from benchmark.export import positions_m, trajectory_arrays
from benchmark.rollout import rollout
from controllers.base import SpacingPolicy
from controllers.registry import make_controller
from envs.scenarios import make_scenario


@pytest.fixture
def captured(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The figures the plot functions would save (closed by the test's end)."""
    figs: list[Any] = []
    monkeypatch.setattr(plots, "_save", lambda fig, out_dir, stem: figs.append(fig) or [Path(stem)])
    yield figs
    for fig in figs:
        plots._plt().close(fig)


def _run(controller: str, scenario: str, n: int, seed: int = 2000) -> dict[str, np.ndarray]:
    return trajectory_arrays(rollout(make_controller(controller), make_scenario(scenario), n, seed))


@pytest.fixture(scope="module")
def cacc_slowdown() -> dict[str, np.ndarray]:
    return _run("cacc", "slowdown-v1", 4)


def _labelled(ax: Any, text: str) -> list[Any]:
    return [ln for ln in ax.get_lines() if text in ln.get_label()]


def test_time_series_draws_both_gap_targets_and_keeps_the_start_spike_off_the_axis(
        captured: list[Any], cacc_slowdown: dict[str, np.ndarray]) -> None:
    arrays = cacc_slowdown
    policy = make_controller("cacc").spacing_policy(20.0, 15.0)
    assert policy == SpacingPolicy(12.5, 0.5)  # d* - h v* with Ploeg's h = 0.5 s
    plots.plot_time_series(arrays, "t", Path("u"), "s", 20.0, 15.0, spacing=policy,
                           controller="cacc")
    gap_ax, _, accel_ax, _ = captured[0].axes
    published = _labelled(gap_ax, "published reward target 20 m")
    assert len(published) == 1 and set(published[0].get_ydata()) == {20.0}
    own = [ln for ln in gap_ax.get_lines() if ln.get_linestyle() == ":"]
    assert len(own) == 4  # one per follower, from its own speed
    for i, ln in enumerate(own):
        np.testing.assert_allclose(ln.get_ydata(), 12.5 + 0.5 * arrays["speed_mps"][:, i])
    assert "own policy (cacc): 12.5 m + 0.5 s x v" in [ln.get_label() for ln in own]
    # slowdown-v1's published speed clip: -10.6 m/s^2 at step 1, written, not setting the axis
    spike = arrays["accel_mps2"][1].min()
    assert spike < -10.5
    lo, hi = accel_ax.get_ylim()
    assert lo > spike and lo < arrays["accel_mps2"][2:].min()
    texts = [t.get_text() for t in accel_ax.texts]
    assert any(f"{spike:.3g}" in t and "off axis" in t for t in texts)
    # the transient is shaded over its step
    spans = [p for p in accel_ax.patches if "start-up transient" in p.get_label()]
    assert len(spans) == 1


def test_time_series_without_a_policy_or_spike_draws_neither(
        captured: list[Any]) -> None:
    arrays = _run("ovm", "catchup-v1", 3)
    plots.plot_time_series(arrays, "t", Path("u"), "s", 20.0, 15.0)
    gap_ax, _, accel_ax, _ = captured[0].axes
    assert not [ln for ln in gap_ax.get_lines() if ln.get_linestyle() == ":"]
    assert not [t for t in accel_ax.texts if "off axis" in t.get_text()]
    assert not [ln for ax in captured[0].axes for ln in ax.get_lines()
                if ln.get_label() == "collision"]


def _collided() -> tuple[dict[str, np.ndarray], int]:
    """A made-up run that ends in a collision: follower 2's gap closes to 0.5 m at the last row
    (the closed loop stops at a collision, so a collided run ends there)."""
    from benchmark.rollout import Trajectory

    n, t1 = 3, 40
    gap = np.full((t1, n), 20.0)
    gap[:, 1] = np.linspace(20.0, 0.5, t1)
    speed = np.full((t1, n), 15.0)
    z = np.zeros((t1, n))
    traj = Trajectory(gap, speed, z, z, np.full(t1, 15.0), np.zeros(t1), np.zeros(t1 - 1),
                      np.zeros(t1 - 1), np.zeros((t1 - 1, n)), np.zeros(t1 - 1), True, t1 - 1,
                      0, 0, 0.1)
    return trajectory_arrays(traj), 1


def test_a_collision_is_marked_in_the_time_series_and_the_time_space_diagram(
        captured: list[Any]) -> None:
    arrays, hit = _collided()
    t_end = (arrays["gap_m"].shape[0] - 1) * 0.1
    plots.plot_time_series(arrays, "t", Path("u"), "s", 20.0, 15.0, collided=True)
    platoon_plots.plot_time_space(arrays, "t", Path("u"), "s", collided=True)
    ts, xt = captured
    for ax in ts.axes:
        marks = [ln for ln in ax.get_lines() if ln.get_label() == "collision"]
        assert len(marks) == 1 and marks[0].get_xdata()[0] == pytest.approx(t_end)
        assert any("collision at 3.9 s" in t.get_text() for t in ax.texts)
    cross = _labelled(ts.axes[0], "collision: follower")
    assert cross[0].get_marker() == "X" and cross[0].get_label().endswith(f"{hit + 1}")
    x = positions_m(arrays)
    cross = _labelled(xt.axes[0], "collision: follower 2")
    assert cross[0].get_marker() == "X"
    assert cross[0].get_ydata()[0] == pytest.approx(x[-1, hit + 1])


def test_time_space_draws_each_vehicle_at_its_integrated_position(
        captured: list[Any], cacc_slowdown: dict[str, np.ndarray]) -> None:
    from matplotlib.collections import LineCollection

    arrays = cacc_slowdown
    platoon_plots.plot_time_space(arrays, "t", Path("u"), "s")
    ax, ax_rel = captured[0].axes[:2]
    dt = float(arrays["dt_s"])
    t = np.arange(arrays["gap_m"].shape[0]) * dt
    # reference: each vehicle's own trapezoidal integral of its speed, not the gaps
    v = arrays["speed_mps"]
    own = np.vstack([np.zeros((1, 4)), np.cumsum((v[1:] + v[:-1]) * dt / 2, axis=0)])
    lead = _labelled(ax, "leader")[0]
    np.testing.assert_allclose(lead.get_xdata(), t)
    collections = [c for c in ax.collections if isinstance(c, LineCollection)]
    assert [c.get_label() for c in collections] == [f"follower {i}" for i in range(1, 5)]
    for i, c in enumerate(collections):
        segs = np.array(c.get_segments())
        assert len(segs) == len(t) - 1
        y = np.append(segs[:, 0, 1], segs[-1, 1, 1])
        np.testing.assert_allclose(y - y[0], own[:, i], atol=1e-9)
        assert y[0] == pytest.approx(-20.0 * (i + 1))  # its gaps behind the leader at 0 m
        # coloured by speed: the colour values are the segment's mean speed
        np.testing.assert_allclose(c.get_array(), (v[1:, i] + v[:-1, i]) / 2)
    behind = ax_rel.get_lines()
    np.testing.assert_allclose(behind[3].get_ydata(), arrays["gap_m"].sum(axis=1))


def test_time_space_on_a_ring_folds_positions_onto_the_ring(captured: list[Any]) -> None:
    from matplotlib.collections import LineCollection

    sc = make_scenario("ring-v1")
    traj = rollout(make_controller("idm"), sc, 22, 2000)
    arrays = trajectory_arrays(traj)
    assert bool(arrays["ring"])
    length = float(sc.options["length_m"])
    x = positions_m(arrays)
    # column 0 is follower N one lap ahead: the ring's length from the positions alone
    np.testing.assert_allclose(x[:, 0] - x[:, -1], length, atol=1e-9)
    platoon_plots.plot_time_space(arrays, "t", Path("u"), "s", ring_length_m=length)
    ax = captured[0].axes[0]
    assert not _labelled(ax, "leader")
    for c in (c for c in ax.collections if isinstance(c, LineCollection)):
        segs = np.array(c.get_segments())
        assert segs[..., 1].min() >= 0.0 and segs[..., 1].max() < length
        # no segment jumps across the diagram where a vehicle completes a lap
        assert np.abs(segs[:, 1, 1] - segs[:, 0, 1]).max() < length / 2
    assert ax.get_ylim() == (0.0, length)


def test_per_vehicle_figure_draws_each_seed_against_the_vehicle_index(
        captured: list[Any]) -> None:
    sc = make_scenario("slowdown-v1")
    policy = make_controller("cacc").spacing_policy(sc.target_gap_m, sc.target_speed_mps)
    runs: dict[str, list] = {"cacc": [], "ovm": []}
    for seed in (2000, 2001):
        a = _run("cacc", "slowdown-v1", 4, seed)
        runs["cacc"].append((seed, platoon_plots.vehicle_profile(a, 20.0, policy)))
        runs["ovm"].append((seed, platoon_plots.vehicle_profile(_run("ovm", "slowdown-v1", 4, seed),
                                                               20.0)))
    a = _run("cacc", "slowdown-v1", 4, 2000)
    prof = runs["cacc"][0][1]
    # reference: rows 2.. (after the step-1 speed clip), each follower's own r + h v
    err = a["gap_m"][2:] - (12.5 + 0.5 * a["speed_mps"][2:])
    np.testing.assert_allclose(prof.peak_spacing_error_m, np.abs(err).max(axis=0))
    acc = np.column_stack([a["leader_accel_mps2"][2:], a["accel_mps2"][2:]])
    np.testing.assert_allclose(prof.accel_rms_mps2, np.sqrt((acc ** 2).mean(axis=0)))
    platoon_plots.plot_per_vehicle(runs, "t", Path("u"), "s",
                                   {"cacc": "own policy: 12.5 m + 0.5 s x v"})
    ax_e, ax_a = captured[0].axes[:2]
    lines = ax_e.get_lines()
    assert len(lines) == 4  # two controllers x two seeds
    np.testing.assert_allclose(lines[0].get_xdata(), [1, 2, 3, 4])
    np.testing.assert_allclose(lines[0].get_ydata(), prof.peak_spacing_error_m)
    np.testing.assert_allclose(ax_a.get_lines()[0].get_xdata(), [0, 1, 2, 3, 4])
    assert {ln.get_marker() for ln in lines[:2]} == {"o", "s"}  # the seeds told apart
    legend = [t.get_text() for t in ax_e.get_legend().get_texts()]
    assert legend == ["cacc [own policy: 12.5 m + 0.5 s x v]", "ovm"]
    seeds = [t.get_text() for t in ax_a.get_legend().get_texts()]
    assert seeds == ["seed 2000", "seed 2001"]


def test_gain_frequency_draws_each_given_point_with_a_marker(captured: list[Any]) -> None:
    from analysis.stability import PloegLoop, gamma_response

    omega = np.array([0.1, 0.5, 1.0, 3.0])
    loop = PloegLoop()
    gain = np.abs(gamma_response(omega, loop))
    platoon_plots.plot_gain_frequency({"cacc": (omega[::-1], gain[::-1])}, "t", Path("u"), "s",
                                      tolerance=0.01)
    ax = captured[0].axes[0]
    line = _labelled(ax, "cacc")[0]
    np.testing.assert_allclose(line.get_xdata(), omega)
    np.testing.assert_allclose(line.get_ydata(), gain)
    assert line.get_marker() == "o"
    limit = _labelled(ax, "string stable below 1.01")[0]
    assert set(limit.get_ydata()) == {1.01}
    assert ax.get_xscale() == "log"


def _leaderboard(controllers: list[str], scenarios: list[str]) -> pd.DataFrame:
    rows = []
    for sc in scenarios:
        for i, c in enumerate(controllers):
            row: dict[str, Any] = {"controller": c, "scenario": sc, "n_vehicles": 8,
                                   "family": "linear", "rank": i + 1, "comm_delay_s": 0.0,
                                   "packet_loss": 0.0, "lag_s": 0.0}
            for m, _ in plots.BAR_METRICS:
                row.update({f"{m}_mean": 1.0 + i, f"{m}_ci_low": 0.5 + i, f"{m}_ci_high": 1.5 + i})
            for m, _ in plots.RADAR_AXES:
                row[f"{m}_mean"] = 1.0 + i
            rows.append(row)
    return pd.DataFrame(rows)


@pytest.mark.parametrize("scenarios", [["catchup-v1"], ["catchup-v1", "slowdown-v1"]])
def test_the_leaderboard_legend_covers_no_panel_title(captured: list[Any],
                                                      scenarios: list[str]) -> None:
    plots.plot_leaderboard(_leaderboard(["acc", "cacc"], scenarios), Path("u"))
    fig = captured[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legend = fig.legends[0].get_window_extent(renderer)
    titles = [ax.title.get_window_extent(renderer) for ax in fig.axes if ax.get_visible()]
    assert titles and not any(legend.overlaps(t) for t in titles)
    panels = [ax.get_window_extent(renderer) for ax in fig.axes if ax.get_visible()]
    assert not any(legend.overlaps(p) for p in panels)


def test_the_time_series_legend_covers_neither_panels_nor_title(
        captured: list[Any]) -> None:
    plots.plot_time_series(_run("acc", "catchup-v1", 8), "a title", Path("u"), "s", 20.0, 15.0)
    fig = captured[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legend = fig.legends[0].get_window_extent(renderer)
    boxes = [ax.get_tightbbox(renderer) for ax in fig.axes] + [
        fig._suptitle.get_window_extent(renderer)]
    assert not any(legend.overlaps(b) for b in boxes)


def test_a_one_controller_radar_is_not_drawn(captured: list[Any]) -> None:
    assert plots.plot_radar(_leaderboard(["cacc"], ["catchup-v1"]), "catchup-v1", 8,
                            Path("u"), "r") == []
    assert not captured
    assert plots.plot_radar(_leaderboard(["acc", "cacc"], ["catchup-v1"]), "catchup-v1", 8,
                            Path("u"), "r")
    lines = captured[0].axes[0].get_lines()
    # two controllers: the smaller is drawn at half the larger on every axis
    np.testing.assert_allclose(sorted(ln.get_ydata()[0] for ln in lines), [0.5, 1.0])


def test_a_one_point_learning_curve_is_visible(captured: list[Any]) -> None:
    from studies import reproduction

    curve = pd.DataFrame({"steps": [1000], "eval_reward_sampled": [-120.0]})
    reproduction.learning_curve_figure({("bdc", "catchup-v1", 0): curve}, ["bdc"], "catchup-v1",
                                       Path("u"), "c", "t")
    line = _labelled(captured[0].axes[0], "bdc")[0]
    assert list(line.get_xdata()) == [1000.0] and list(line.get_ydata()) == [-120.0]
    assert line.get_marker() not in (None, "None", "", " ")
