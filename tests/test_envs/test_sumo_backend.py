"""The SUMO backend (envs.sumo): the same episodes as the built-in simulator, to the stated
tolerance, with the matched settings; SUMO's Euler update measurably not; SUMO's IDM humans as
ours; batches as single episodes; settings SUMO does not simulate refused. Small episodes: CI
installs the sumo extra and runs these; without it they are skipped with the reason."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("libsumo", reason="the SUMO backend needs the sumo extra: "
                                      "pip install -e '.[sumo]'")

from benchmark.rollout import rollout_batch  # noqa: E402
from controllers.registry import make_controller  # noqa: E402
from envs.scenarios import make_scenario  # noqa: E402
from infra.errors import ConfigError  # noqa: E402
from studies.sumo_compare import (  # noqa: E402
    HUMAN_TOL,
    MATCHED_GAP_TOL_M,
    MATCHED_MPC_TOL,
    MATCHED_SPEED_TOL_MPS,
    wave_measures,
)


def _short(label: str, steps: int):
    sc = make_scenario(label)
    return dataclasses.replace(sc, n_steps=steps)


def _both(name: str, sc, seeds, simulator: str = "sumo"):
    ref = rollout_batch(make_controller(name), sc, sc.default_vehicles, seeds)
    got = rollout_batch(make_controller(name), sc, sc.default_vehicles, seeds,
                        simulator=simulator)
    return ref, got


@pytest.mark.parametrize("scenario", ["catchup-v1", "slowdown-v1"])
@pytest.mark.parametrize("name", ["acc", "cacc", "mpc-qp", "bdc"])
def test_matched_sumo_runs_the_builtin_episodes(name: str, scenario: str) -> None:
    sc = _short(scenario, 120)
    ref, got = _both(name, sc, [2000])
    for a, b in zip(ref, got, strict=True):
        assert a.steps == b.steps and a.collided == b.collided
        tol = (MATCHED_MPC_TOL, MATCHED_MPC_TOL) if name == "mpc-qp" else (
            MATCHED_GAP_TOL_M, MATCHED_SPEED_TOL_MPS)
        assert np.max(np.abs(a.gap_m - b.gap_m)) < tol[0]
        assert np.max(np.abs(a.speed_mps - b.speed_mps)) < tol[1]
        np.testing.assert_allclose(a.reward, b.reward, rtol=1e-6)


def test_sumo_default_euler_update_moves_the_gaps_by_dt2_a_over_2() -> None:
    """SUMO's default update moves a vehicle ``dt^2 a / 2`` otherwise per step than the
    trapezoid: the first step of a platoon whose follower 1 alone accelerates changes its gap
    by exactly that."""
    sc = _short("catchup-v1", 1)
    ref, got = _both("cacc", sc, [2000], "sumo-euler")
    a1 = ref[0].accel_mps2[1, 0]
    assert abs(a1) > 0.1
    dgap = got[0].gap_m[1, 0] - ref[0].gap_m[1, 0]
    # x' = x + dt v' (Euler) against x + dt (v + v')/2: follower 1 moves dt^2 a / 2 further
    assert dgap == pytest.approx(-0.1 ** 2 * a1 / 2, rel=1e-9)


@pytest.mark.parametrize(("scenario", "name"), [
    ("catchup-v1:humans=2+5,human_noise_mps2=0", "cacc"),
    ("ring-v1:human_noise_mps2=0,cavs=0", "idm"),
])
def test_sumo_idm_humans_drive_as_ours(scenario: str, name: str) -> None:
    sc = _short(scenario, 1500)
    ref, got = _both(name, sc, [2000])
    assert np.max(np.abs(ref[0].gap_m - got[0].gap_m)) < HUMAN_TOL
    assert np.max(np.abs(ref[0].speed_mps - got[0].speed_mps)) < HUMAN_TOL
    if sc.ring:  # the ring keeps its length in SUMO: the gaps sum to L - N x 5 m
        np.testing.assert_allclose(got[0].gap_m.sum(axis=1), 260.0 - 22 * 5.0, atol=1e-9)
        w_ref = wave_measures(ref[0], 260.0)
        w_got = wave_measures(got[0], 260.0)
        assert w_ref == pytest.approx(w_got, rel=1e-9)
        assert w_got["amplitude_mps"] > 0.5  # the waves are growing by 150 s (9 m/s by 300 s)


def test_a_sumo_batch_runs_each_episode_as_alone() -> None:
    sc = _short("slowdown-v1", 80)
    batch = rollout_batch(make_controller("cacc"), sc, 8, [2000, 2010], simulator="sumo")
    for seed, traj in zip([2000, 2010], batch, strict=True):
        alone = rollout_batch(make_controller("cacc"), sc, 8, [seed], simulator="sumo")[0]
        np.testing.assert_array_equal(traj.gap_m, alone.gap_m)
        np.testing.assert_array_equal(traj.speed_mps, alone.speed_mps)


def test_a_collision_ends_the_episode_in_sumo_as_in_the_builtin_env() -> None:
    sc = _short("catchup-v1", 200)
    ref, got = _both("ovm", sc, [2000])  # the human baseline: it does not collide here
    assert ref[0].steps == got[0].steps
    from controllers.registry import ControllerSpec, register_controller

    register_controller(ControllerSpec("full-throttle", "linear", "none", "test",
                                       "tests.envs.test_sumo_backend:FullThrottle"))
    ref = rollout_batch(FullThrottle(), sc, 8, [2000])
    got = rollout_batch(FullThrottle(), sc, 8, [2000], simulator="sumo")
    assert ref[0].collided and got[0].collided and ref[0].steps == got[0].steps


class FullThrottle:
    """Followers 2..N accelerate flat out into follower 1 (a collision within seconds)."""

    name, family, deterministic, needs_observation = "full-throttle", "linear", True, False

    def messages(self, ctx):
        return ()

    def reset(self, ctx):
        self.n = ctx.n_vehicles

    def act(self, state, observation):
        u = np.full(state.speed_mps.shape, 2.5)
        u[:, 0] = -2.5
        return u


@pytest.mark.parametrize(("label", "needle"), [
    ("catchup-v1:humans=2", "human_noise_mps2=0"),
    ("catchup-v1:humans=2,human_noise_mps2=0,human_model=ovm", "human_model=idm"),
    ("catchup-v1:humans=2,human_noise_mps2=0,reaction_delay_s=0.5", "reaction delay"),
])
def test_settings_sumo_does_not_simulate_are_refused(label: str, needle: str) -> None:
    from envs.params import PlatoonParams
    from envs.simulators import check_setting

    with pytest.raises(ConfigError, match=needle):
        check_setting("sumo", make_scenario(label), 8, PlatoonParams())
