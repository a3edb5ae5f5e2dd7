"""``duty``: the fixed schedule of MARL actions against ``ovm``, and its choice of k."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.rollout import rollout
from controllers.duty import DutyController, best_k, duty_scores
from controllers.ovm import OVMController
from controllers.registry import make_controller
from envs.errors import ConfigError
from envs.scenarios import make_scenario


@pytest.mark.parametrize("scenario", ["catchup-v1", "slowdown-v1"])
def test_duty_k1_equals_ovm(scenario) -> None:
    sc = make_scenario(scenario)
    a = rollout(DutyController(k=1), sc, 8, 2000)
    b = rollout(OVMController(), sc, 8, 2000)
    np.testing.assert_array_equal(a.accel_mps2, b.accel_mps2)
    np.testing.assert_array_equal(a.reward, b.reward)


def test_duty_schedule_and_choice() -> None:
    """Action 3 at steps 0, k, 2k, ...; the batched search's score of a k equals the harness's
    rollouts of duty:k on the validation seeds; the best k is the argmax among the collision-free."""
    from envs.params import VALIDATION_SEEDS

    sc = make_scenario("catchup-v1")
    ctrl = make_controller("duty", k="3")
    traj = rollout(ctrl, sc, 4, 2000)
    ovm = rollout(OVMController(), sc, 4, 2000)
    assert traj.accel_mps2[1, 0] == ovm.accel_mps2[1, 0]  # step 0: action 3, same state
    assert traj.accel_mps2[2, 0] != ovm.accel_mps2[2, 0]
    scores = duty_scores("catchup-v1", 4, 6)
    k3 = next(r for r in scores if r[0] == 3)
    want = np.mean([rollout(make_controller("duty", k="3"), sc, 4, s).reward.mean()
                    for s in VALIDATION_SEEDS])
    assert k3[2] == pytest.approx(want, rel=1e-12)
    best = best_k("catchup-v1", 4, 6)
    safe = [r for r in scores if r[1] == min(x[1] for x in scores)]
    assert best == max(safe, key=lambda r: r[2])[0]
    auto = make_controller("duty")
    rollout(auto, sc, 4, 2000)
    assert auto.chosen_k == best_k("catchup-v1", 4, 20)


def test_duty_bad_options() -> None:
    with pytest.raises(ConfigError, match="k must be >= 1"):
        make_controller("duty", k="0")
    with pytest.raises(ConfigError, match="no option"):
        make_controller("duty", period="3")
