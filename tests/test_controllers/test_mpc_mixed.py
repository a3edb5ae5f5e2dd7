"""The MPC family on strings with human drivers (``mpc``, ``mpc-qp``, ``cmpc``): human seats are
not solved, a follower behind a human gets no plan and predicts it by the stated model from its
own sensors, cmpc plans the automated seats only and learns of a human only what an automated
follower senses. The homogeneous pin is ``tests/test_controllers/test_mpc.py``, unchanged."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from benchmark.rollout import rollout_batch
from controllers.base import EpisodeContext, reset_controller
from controllers.cmpc import human_watchers
from controllers.mpc_model import (
    human_predecessor_mask,
    idm_prediction_mps,
)
from controllers.registry import check_fits, make_controller
from envs.humans import IDMParams, idm_accel_mps2
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv, PlatoonState
from envs.scenarios import Scenario, make_scenario
from infra.errors import ConfigError

SEEDS = [2000, 2001]


def short(scenario_id: str, n_steps: int) -> Scenario:
    """A registered scenario cut to ``n_steps`` steps."""
    return dataclasses.replace(make_scenario(scenario_id), n_steps=n_steps)


def first_commands(name: str, scenario: Scenario, n: int, state_edit: Any = None,
                   **options: Any) -> np.ndarray:
    """The commands ``(B, N)`` of a fresh controller at the first step (optionally on an edited
    copy of the state)."""
    ctrl = make_controller(name, **options)
    env = PlatoonEnv(scenario, n)
    reset_controller(ctrl, EpisodeContext(scenario, n, np.asarray(SEEDS)))
    env.reset(np.asarray(SEEDS))
    state = env.state
    assert state is not None
    if state_edit is not None:
        state = state_edit(state)
    return np.asarray(ctrl.act(state, None))


# --------------------------------------------------------------------------- distributed MPC


@pytest.mark.parametrize("name", ["mpc-qp", "mpc"])
def test_human_seats_are_not_solved(name: str) -> None:
    sc = short("catchup-v1:humans=2", 20)
    ctrl = make_controller(name, horizon=10)
    trajs = rollout_batch(ctrl, sc, 4, SEEDS)
    assert all(t.steps == 20 and not t.collided for t in trajs)
    assert ctrl.solve_count == 3 * 20 * len(SEEDS)  # 3 automated seats x steps x episodes
    for t in trajs:
        assert np.all(t.command_mps2[:, 1] == 0.0)  # the human seat's (ignored) command


@pytest.mark.parametrize("prediction", ["constant-speed", "idm"])
def test_a_follower_behind_a_human_gets_no_plan_and_predicts_it_from_its_radar(
    prediction: str,
) -> None:
    """Followers 1, 3, 4 automated, follower 2 human: follower 3 (seat 2) never receives a plan
    and its problem's predecessor trajectory is the stated model of the measured speed."""
    n, steps = 4, 15
    sc = short("catchup-v1:humans=2", steps)
    ctrl = make_controller("mpc-qp", horizon=10, human_prediction=prediction)
    seen: list[np.ndarray] = []
    solve = ctrl._solve

    def spy(p: np.ndarray, warm: Any) -> Any:
        seen.append(p.copy())
        return solve(p, warm)

    ctrl._solve = spy  # type: ignore[method-assign]
    env = PlatoonEnv(sc, n)
    reset_controller(ctrl, EpisodeContext(sc, n, np.asarray([SEEDS[0]])))
    env.reset(np.asarray([SEEDS[0]]))
    s = env.state
    assert s is not None
    prev = None
    for _ in range(steps):
        seen.clear()
        v_human = float(s.speed_mps[0, 1])
        u = ctrl.act(s, None)
        assert len(seen) == 3  # seats 0, 2, 3
        vp = seen[1][ctrl.layout.vp]  # seat 2's problem
        if prediction == "constant-speed":
            np.testing.assert_array_equal(vp, np.full(11, v_human))
        else:
            a_meas = 0.0 if prev is None else (v_human - prev) / 0.1
            want = idm_prediction_mps(np.array(v_human), np.array(a_meas), 10, ctrl.params)
            np.testing.assert_allclose(vp, want, rtol=0, atol=1e-12)
        # the automated predecessors' plans arrive; the human's never does
        assert np.isfinite(ctrl._received[0, 1]).all() and np.isfinite(ctrl._received[0, 3]).all()
        assert np.isnan(ctrl._received[0, 2]).all()
        prev = v_human
        env.step(u)


def test_the_human_prediction_option() -> None:
    with pytest.raises(ConfigError, match="human_prediction"):
        make_controller("mpc-qp", human_prediction="ovm")
    # on a homogeneous string there is nobody to predict: the same commands, bit for bit
    sc = short("catchup-v1", 30)
    a = rollout_batch(make_controller("mpc-qp", horizon=10), sc, 3, SEEDS)
    b = rollout_batch(make_controller("mpc-qp", horizon=10, human_prediction="idm"), sc, 3,
                      SEEDS)
    for ta, tb in zip(a, b):
        np.testing.assert_array_equal(ta.command_mps2, tb.command_mps2)


def test_human_predecessor_mask() -> None:
    auto = np.array([True, False, True, True, False])
    assert human_predecessor_mask(auto, ring=False).tolist() == [False, False, True, False, False]
    # on a ring follower 1 follows follower N (a human here)
    assert human_predecessor_mask(auto, ring=True).tolist() == [True, False, True, False, False]
    assert not human_predecessor_mask(np.ones(3, dtype=bool), ring=True).any()


def test_idm_prediction_under_its_stated_assumption() -> None:
    params = PlatoonParams()
    v = np.array([5.0, 15.0, 25.0])
    # a human measured at constant speed is predicted at constant speed
    flat = idm_prediction_mps(v, np.zeros(3), 20, params)
    np.testing.assert_allclose(flat, np.repeat(v[:, None], 21, axis=1), atol=1e-9)
    # the inferred gap reproduces the measured acceleration at the first step
    a0 = np.array([-1.0, -0.5, 0.3])
    pred = idm_prediction_mps(v, a0, 20, params)
    np.testing.assert_allclose((pred[:, 1] - pred[:, 0]) / params.dt_s, a0, atol=1e-9)
    # a braking human brakes less and less as its unseen gap opens
    acc = np.diff(pred[0]) / params.dt_s
    assert np.all(np.diff(acc) > 0) and pred[0, -1] > v[0] - 20 * params.dt_s * 1.0
    # that unseen gap: s = s*(v) / sqrt(r), checked by the IDM itself
    p = IDMParams()
    r = 1 - (v / p.desired_speed_mps) ** p.delta - a0 / p.accel_max_mps2
    s = (p.standstill_m + v * p.time_gap_s) / np.sqrt(r)
    np.testing.assert_allclose(idm_accel_mps2(s, v, v, p), a0, atol=1e-12)


@pytest.mark.parametrize("name", ["mpc-qp", "mpc"])
def test_the_humans_unsensed_state_does_not_change_the_commands(name: str) -> None:
    """A human's own gap is sensed by no automated vehicle: the commands do not depend on it."""
    sc = make_scenario("catchup-v1:humans=2")

    def edit(s: PlatoonState) -> PlatoonState:
        gap = s.gap_m.copy()
        gap[:, 1] += 7.0
        return dataclasses.replace(s, gap_m=gap)

    u0 = first_commands(name, sc, 4, horizon=10)
    u1 = first_commands(name, sc, 4, edit, horizon=10)
    np.testing.assert_array_equal(u0[:, [0, 2, 3]], u1[:, [0, 2, 3]])


@pytest.mark.parametrize("name", ["mpc-qp", "mpc"])
@pytest.mark.parametrize("scenario", ["catchup-v1:humans=3", "ring-v1"])
def test_distributed_mpc_drives_mixed_strings(name: str, scenario: str) -> None:
    sc = make_scenario(scenario)
    if scenario != "ring-v1":
        sc = dataclasses.replace(sc, n_steps=200)
    n = 22 if scenario == "ring-v1" else 8
    check_fits(make_controller(name), sc, n)
    ctrl = make_controller(name)
    trajs = rollout_batch(ctrl, sc, n, SEEDS[:1])
    n_auto = int(sc.arrangement(n).n_automated)
    assert all(not t.collided and t.steps == sc.n_steps for t in trajs)
    assert ctrl.solver_failures == 0
    assert ctrl.solve_count == n_auto * sc.n_steps


# --------------------------------------------------------------------------- cmpc


def test_cmpc_messages_on_mixed_strings() -> None:
    assert human_watchers(np.ones(4, dtype=bool)) == []
    # humans 2, 3 and 8 of 8: follower 4 senses human 3; nobody senses 2 (behind it: a human)
    # nor 8 (last)
    auto = np.array([True, False, False, True, True, True, True, False])
    assert human_watchers(auto) == [4]
    ctrl = make_controller("cmpc")
    homo = ctrl.messages(EpisodeContext(make_scenario("catchup-v1"), 8, np.asarray(SEEDS)))
    assert [m.name for m in homo] == ["cmpc_state"]
    mixed = ctrl.messages(
        EpisodeContext(make_scenario("catchup-v1:humans=2+3+8"), 8, np.asarray(SEEDS))
    )
    assert [(m.name, m.width, m.links) for m in mixed] == [
        ("cmpc_state", 3, "to_leader"), ("cmpc_human", 1, ((4, 0),))]
    with pytest.raises(ConfigError, match="constant speed"):
        make_controller("cmpc", human_prediction="idm")
    with pytest.raises(ConfigError, match="leader"):
        check_fits(make_controller("cmpc"), make_scenario("ring-v1"), 22)


def test_cmpc_plans_the_automated_seats_and_predicts_humans_at_constant_speed() -> None:
    n = 8
    sc = make_scenario("catchup-v1:humans=2+3+8")
    check_fits(make_controller("cmpc"), sc, n)  # drives mixed strings behind a leader
    ctrl = make_controller("cmpc", horizon=10)
    env = PlatoonEnv(sc, n)
    ctx = EpisodeContext(sc, n, np.asarray(SEEDS[:1]))
    reset_controller(ctrl, ctx)
    env.reset(np.asarray(SEEDS[:1]))
    s = env.state
    assert s is not None
    u = ctrl.act(s, None)
    pr = ctrl.problem
    humans = [1, 2, 7]
    assert np.all(u[0, humans] == 0.0)
    np.testing.assert_allclose(pr.u.value[humans], 0.0, atol=1e-9)
    # human 3 (seat 2) is sensed by follower 4: its measured speed held over the horizon
    np.testing.assert_allclose(pr.v.value[2], s.speed_mps[0, 2], atol=1e-6)
    # the automated seats are planned: not all zero
    assert np.abs(pr.u.value[[0, 3, 4, 5, 6]]).max() > 1e-3
    # bits: 5 automated followers x 3 floats + follower 4's one float, 32 bits each
    assert ctx.bits_sent == (5 * 3 + 1) * 32


def test_cmpc_does_not_read_what_nobody_senses() -> None:
    """The gaps of humans 2, 3, 8, the speed of human 2 (followed by human 3) and of human 8
    (last) reach no automated vehicle: the commands do not depend on them."""
    sc = make_scenario("catchup-v1:humans=2+3+8")

    def edit(s: PlatoonState) -> PlatoonState:
        gap, speed = s.gap_m.copy(), s.speed_mps.copy()
        gap[:, [1, 2, 7]] += 6.0
        speed[:, [1, 7]] -= 2.0
        return dataclasses.replace(s, gap_m=gap, speed_mps=speed)

    u0 = first_commands("cmpc", sc, 8, horizon=10)
    u1 = first_commands("cmpc", sc, 8, edit, horizon=10)
    np.testing.assert_allclose(u0, u1, atol=1e-7)


def test_cmpc_drives_a_mixed_string() -> None:
    sc = short("catchup-v1:humans=3", 200)
    ctrl = make_controller("cmpc", horizon=10)
    trajs = rollout_batch(ctrl, sc, 8, SEEDS[:1])
    assert not trajs[0].collided and trajs[0].steps == 200
    assert ctrl.solver_failures == 0
    assert np.all(trajs[0].command_mps2[:, 2] == 0.0)
    assert trajs[0].bits_sent == 200 * (7 * 3 + 1) * 32
