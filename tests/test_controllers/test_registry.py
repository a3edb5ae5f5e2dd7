"""Every available registered controller meets the harness's contract (check_controller)."""

from __future__ import annotations

import pytest

from benchmark.check import check_controller
from controllers.registry import available_controllers

NOT_CLOSED_LOOP = {"openacc-real"}  # a recorded platoon, scored by the harness


@pytest.mark.parametrize(
    "name", [c.name for c in available_controllers() if c.name not in NOT_CLOSED_LOOP]
)
def test_check_controller(name: str) -> None:
    check_controller(name, "catchup-v1", 8, steps=30)


@pytest.mark.parametrize(("defect", "needle"), [
    ("shape", r"act returned shape \(1, 1\), expected \(B, N\) = \(1, 3\)"),
    ("nan", "act returned a non-finite command"),
    ("silent_v2v", r"its channel 'speed' sent 0 times in 1 steps"),
    ("skip_send", r"its channel 'speed' sent 3 times in 4 steps"),
])
def test_the_loop_refuses_a_broken_command_in_check_and_in_the_harness(
        defect: str, needle: str) -> None:
    import re

    from benchmark.suite import build_sweep, execute_run
    from controllers.registry import ControllerSpec, register_controller

    register_controller(ControllerSpec("defective", "linear", "none", "test only",
                                       "failing_controller:DefectiveController"))
    with pytest.raises(AssertionError, match=needle):
        check_controller("defective", "catchup-v1", 3, steps=10, defect=defect)
    rec = execute_run(build_sweep([("defective", {"defect": defect})], ["catchup-v1"], [3],
                                  [2000])[0])
    assert rec["status"] == "failed" and "steps" not in rec
    assert rec["error"].startswith("ControllerContractError") and re.search(needle, rec["error"])
