"""The time left of a sweep (benchmark.progress): reckoned per controller and per vehicle-step
from what finished, none while a controller with runs left has none finished, shared among the
workers; nothing is written when the output is not a terminal."""

from __future__ import annotations

import io

import pytest

from benchmark.progress import Progress


def test_the_time_left_counts_each_controller_at_its_own_cost() -> None:
    stream = io.StringIO()  # not a terminal: silent
    # two cheap runs of N = 8, two slow ones of N = 8 and one slow one of N = 16 (twice the work)
    p = Progress(5, stream=stream, groups=["cacc", "cacc", "mpc", "mpc", "mpc"],
                 weights=[8, 8, 8, 8, 16])
    assert p.eta_s() is None and p.eta_text() == "left ? (2 not timed yet)"
    p.advance(group="cacc", seconds=0.5, weight=8)
    assert p.eta_s() is None  # the MPC runs left are not timed: no guess from cacc's
    assert p.eta_text() == "left ? (1 not timed yet)"
    p.advance(group="mpc", seconds=40.0, weight=8)
    # cacc: 8 units left at 0.5 s / 8; mpc: 8 + 16 units left at 40 s / 8
    assert p.eta_s() == pytest.approx(0.5 + 40.0 * 3)
    assert p.eta_text() == "left ~2:00"
    p.advance(group="cacc", seconds=0.5, weight=8)
    p.advance(group="mpc", seconds=40.0, weight=8)
    assert p.eta_s() == pytest.approx(80.0)
    p.advance(group="mpc", seconds=80.0, weight=16)
    assert p.eta_s() == 0.0 and p.done == 5
    p.close()
    assert stream.getvalue() == ""


def test_workers_share_the_time_left_and_no_groups_means_no_estimate_of_ours() -> None:
    p = Progress(4, stream=io.StringIO(), groups=["a"] * 4, parallel=2)
    p.advance(group="a", seconds=3.0)
    assert p.eta_s() == pytest.approx(3 * 3.0 / 2)
    assert Progress(3, stream=io.StringIO()).eta_s() is None  # tqdm's own estimate then
