"""Every available registered controller meets the harness's contract (check_controller)."""

from __future__ import annotations

import pytest

from controllers.check import check_controller
from controllers.registry import available_controllers

NOT_CLOSED_LOOP = {"openacc-real"}  # a recorded platoon, scored by the harness


@pytest.mark.parametrize(
    "name", [c.name for c in available_controllers() if c.name not in NOT_CLOSED_LOOP]
)
def test_check_controller(name: str) -> None:
    check_controller(name, "catchup-v1", 8, steps=30)
