"""The models others wrote, run inside SUMO (controllers.sumo_models): Plexe's Ploeg against
our cacc, the disagreement explained (Plexe's forward-Euler filter, reproduced through our own
harness), and the rules that keep them in SUMO. Skipped without the sumo extra."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("libsumo", reason="the SUMO models need the sumo extra: "
                                      "pip install -e '.[sumo]'")

from benchmark.rollout import rollout_batch  # noqa: E402
from controllers.linear import CACCController  # noqa: E402
from controllers.registry import make_controller  # noqa: E402
from envs.params import PlatoonParams  # noqa: E402
from envs.scenarios import make_scenario  # noqa: E402
from infra.errors import ConfigError  # noqa: E402
from studies.sumo_compare import (  # noqa: E402
    PLOEG_REPLICA_TOL,
    UNBOUNDED_SPEED_MPS,
    EulerFilterPloeg,
)


def _diff(a, b) -> float:
    assert a.steps == b.steps
    return float(max(np.max(np.abs(a.gap_m - b.gap_m)), np.max(np.abs(a.speed_mps - b.speed_mps))))


@pytest.mark.parametrize(("scenario", "bound"), [("catchup-v1", 30.0),
                                                 ("slowdown-v1", UNBOUNDED_SPEED_MPS)])
def test_plexe_ploeg_is_our_law_with_plexes_euler_filter(scenario: str, bound: float) -> None:
    sc = dataclasses.replace(make_scenario(scenario), n_steps=200)
    p = PlatoonParams(speed_max_mps=bound)
    plexe = rollout_batch(make_controller("plexe:ploeg"), sc, 8, [2000], p, simulator="sumo")[0]
    replica = rollout_batch(EulerFilterPloeg(standstill_m=2.0), sc, 8, [2000], p,
                            simulator="sumo")[0]
    exact = rollout_batch(CACCController(standstill_m=2.0), sc, 8, [2000], p,
                          simulator="sumo")[0]
    assert _diff(plexe, replica) < PLOEG_REPLICA_TOL
    assert _diff(plexe, exact) > 0.1  # the discretisation's difference is real, and named
    np.testing.assert_allclose(plexe.gap_m[-1], 2.0 + 0.5 * plexe.speed_mps[-1], atol=0.5)


def test_the_sumo_models_run_in_sumo_only_and_never_behind_the_filter() -> None:
    from benchmark.check import check_controller

    sc = dataclasses.replace(make_scenario("catchup-v1"), n_steps=5)
    with pytest.raises(ConfigError, match="--simulator sumo"):
        rollout_batch(make_controller("plexe:ploeg"), sc, 8, [2000])
    with pytest.raises(ConfigError, match="safety filter has none to correct"):
        make_controller("safe:plexe:ploeg")
    with pytest.raises(ConfigError, match="has no option 'kp'"):
        make_controller("plexe:ploeg", kp="1")
    check_controller("plexe:path", "catchup-v1", 4, steps=10)  # runs its check in SUMO


def test_plexe_feed_goes_through_the_v2v_channel() -> None:
    """With 50 % packet loss Plexe's Ploeg holds stale feed-forward: its run changes, and the
    harness counts its bits (2 floats per follower and step)."""
    from envs.channel import ChannelConfig

    sc = dataclasses.replace(make_scenario("catchup-v1"), n_steps=100)
    clean = rollout_batch(make_controller("plexe:ploeg"), sc, 4, [2000], simulator="sumo")[0]
    lossy = rollout_batch(make_controller("plexe:ploeg"), sc, 4, [2000], PlatoonParams(),
                          ChannelConfig(0.0, 0.5), simulator="sumo")[0]
    assert not np.array_equal(clean.speed_mps, lossy.speed_mps)
    assert clean.bits_sent == 100 * 4 * 2 * 32
