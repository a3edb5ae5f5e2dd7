"""Ploeg's laws (``acc``, ``cacc``) step by step against the law written out by hand.

The hand loop below is the discretised law of ``controllers/linear.py``'s docstring, fed with the
states the env recorded; with no actuator lag the env applies the command, so row ``k + 1`` of
the recorded acceleration must be the command computed from row ``k``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark.rollout import Trajectory, rollout
from controllers.registry import make_controller
from envs.params import PlatoonParams
from envs.scenarios import make_scenario
from infra.errors import ConfigError

OPTS = {"time_gap_s": "0.6", "kp": "0.3", "kd": "0.9"}
#: Stiff gains: the command reaches the bounds, so the clip (anti-windup) is exercised.
STIFF = {"time_gap_s": "0.6", "kp": "3.0", "kd": "4.0"}


def _by_hand(traj: Trajectory, h: float, kp: float, kd: float, r: float, feedforward: bool,
             p: PlatoonParams) -> np.ndarray:
    alpha = math.exp(-p.dt_s / h)
    n = traj.gap_m.shape[1]
    c, m = np.zeros(n), np.zeros(n)
    out = []
    for k in range(traj.steps):
        gap, v, a = traj.gap_m[k], traj.speed_mps[k], traj.accel_mps2[k]
        v_pred = np.concatenate([[traj.leader_speed_mps[k]], v[:-1]])
        w = kp * (gap - r - h * v) + kd * ((v_pred - v) - h * a) + (m if feedforward else 0.0)
        c = np.clip(alpha * c + (1 - alpha) * w, p.accel_min_mps2, p.accel_max_mps2)
        out.append(c)
        leader_plan = (traj.leader_speed_mps[k + 1] - traj.leader_speed_mps[k]) / p.dt_s
        m = np.concatenate([[leader_plan], c[:-1]])  # arrives for the next update
    return np.array(out)


@pytest.mark.parametrize("opts", [OPTS, STIFF], ids=["soft", "stiff"])
@pytest.mark.parametrize("name", ["cacc", "acc"])
@pytest.mark.parametrize("scenario", ["catchup-v1", "slowdown-v1"])
def test_the_law_step_by_step(name: str, scenario: str, opts: dict[str, str]) -> None:
    sc = make_scenario(scenario)
    ctrl = make_controller(name, **opts)
    traj = rollout(ctrl, sc, 4, 2003)
    p = PlatoonParams()
    h, kp, kd = (float(opts[k]) for k in ("time_gap_s", "kp", "kd"))
    r = sc.target_gap_m - h * sc.target_speed_mps
    assert ctrl.standstill_m == pytest.approx(r)
    want = _by_hand(traj, h, kp, kd, r, name == "cacc", p)
    assert traj.steps > 100
    np.testing.assert_allclose(traj.accel_mps2[1:], want, rtol=0, atol=1e-9)
    if opts is STIFF:  # a bound is reached: the clip is part of what was compared
        assert (np.abs(want) == p.accel_max_mps2).any()


def test_cacc_and_acc_differ_only_by_the_feedforward() -> None:
    sc = make_scenario("slowdown-v1")
    a = rollout(make_controller("cacc", **OPTS), sc, 4, 2003)
    b = rollout(make_controller("acc", **OPTS), sc, 4, 2003)
    assert not np.allclose(a.accel_mps2, b.accel_mps2)
    assert a.bits_sent > 0 and b.bits_sent == 0


def test_a_set_standstill_distance_and_zero_time_gap() -> None:
    sc = make_scenario("catchup-v1")
    ctrl = make_controller("acc", time_gap_s="0", kp="0.3", kd="0.9", standstill_m="5")
    traj = rollout(ctrl, sc, 3, 2001)
    assert ctrl.standstill_m == 5.0
    p = PlatoonParams()
    # h = 0: the law is algebraic, c = kp (gap - r) + kd (v_pred - v), clipped
    v_pred = np.concatenate([traj.leader_speed_mps[:1], traj.speed_mps[0, :-1]])
    c0 = np.clip(0.3 * (traj.gap_m[0] - 5.0) + 0.9 * (v_pred - traj.speed_mps[0]),
                 p.accel_min_mps2, p.accel_max_mps2)
    np.testing.assert_allclose(traj.accel_mps2[1], c0, atol=1e-12)


@pytest.mark.parametrize("bad, needle", [
    ({"time_gap_s": "-0.1"}, "time_gap_s must be >= 0"),
    ({"kp": "0"}, "kp must be > 0"),
    ({"kd": "0"}, "kd must be > 0"),
    ({"standstill_m": "-1"}, "standstill_m must be >= 0"),
    ({"kp": "nan"}, "option kp of acc"),
    ({"feedforward": "true"}, "^acc has no V2V feedforward; use the cacc controller for it$"),
])
def test_bad_gains_are_refused(bad: dict[str, str], needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        make_controller("acc", **bad)


def test_the_lag_check_is_the_hurwitz_condition() -> None:
    """tau s^3 + s^2 + kd s + kp is Hurwitz iff kd > tau kp (kp, kd > 0): Routh-Hurwitz."""
    from controllers.linear import PloegConfig

    cfg = PloegConfig(kp=2.0, kd=0.5)
    cfg.check_lag(0.0)
    cfg.check_lag(0.249)
    for tau in (0.25, 0.3):
        with pytest.raises(ConfigError, match="unstable with this actuator lag"):
            cfg.check_lag(tau)
        roots = np.roots([tau, 1.0, 0.5, 2.0])
        assert roots.real.max() >= -1e-9  # the rule agrees with the polynomial's roots
    assert np.roots([0.249, 1.0, 0.5, 2.0]).real.max() < 0


def test_preflight_checks_the_lag_of_the_run() -> None:
    from envs.params import PlatoonParams

    ctrl = make_controller("cacc", kp="2", kd="0.5")
    sc = make_scenario("catchup-v1")
    ctrl.preflight(sc, 4)  # no physics given: nothing to check
    ctrl.preflight(sc, 4, PlatoonParams(lag_s=0.2))
    with pytest.raises(ConfigError, match="unstable with this actuator lag"):
        ctrl.preflight(sc, 4, PlatoonParams(lag_s=0.3))


@pytest.mark.parametrize("field", ["time_gap_s", "kp", "kd", "standstill_m"])
@pytest.mark.parametrize("value", ["0.3", True, float("inf")])
def test_gains_must_be_finite_numbers_given_directly(field: str, value: object) -> None:
    from controllers.linear import PloegConfig

    with pytest.raises(ConfigError, match=f"^{field} must be a finite number, got {value!r}$"):
        PloegConfig(**{field: value})  # type: ignore[arg-type]
    PloegConfig(standstill_m=0.0)  # the bounds are inclusive: zero is allowed


def test_the_lag_message_names_the_numbers_and_the_remedy() -> None:
    from controllers.linear import PloegConfig

    with pytest.raises(ConfigError) as err:
        PloegConfig(kp=2.0, kd=0.5).check_lag(0.3)
    assert str(err.value) == (
        "kd = 0.5 <= lag_s * kp = 0.3 * 2.0 = 0.6: the vehicle loop tau s^3 + s^2 + kd s + kp is "
        "unstable with this actuator lag; raise kd or lower kp")


def test_cacc_without_feedforward_declares_no_v2v_and_sends_nothing() -> None:
    """``cacc:feedforward=false`` declares no message, so no channel is opened and nothing is
    sent; ``cacc`` declares its command, one float to the follower behind."""
    from benchmark.suite import build_sweep, execute_run
    from controllers.base import EpisodeContext, Message

    ctx = EpisodeContext(make_scenario("catchup-v1"), 3, np.array([2000]))
    assert make_controller("cacc").messages(ctx) == (Message("cacc_u", 1, "predecessor"),)
    assert make_controller("acc").messages(ctx) == ()
    assert make_controller("cacc", feedforward="false").messages(ctx) == ()
    rec = execute_run(build_sweep([("cacc", {"feedforward": "false"})], ["catchup-v1"], [3],
                                  [2000])[0])
    assert rec["status"] == "ok" and rec["comm_bits_per_s"] == 0


def test_options_are_recorded_and_feedforward_must_be_a_bool() -> None:
    from controllers.linear import PloegConfig

    assert make_controller("cacc", kp="0.3").options == {"kp": "0.3"}
    with pytest.raises(ConfigError, match="^feedforward must be true or false, got 'yes'$"):
        PloegConfig(feedforward="yes")  # type: ignore[arg-type]
