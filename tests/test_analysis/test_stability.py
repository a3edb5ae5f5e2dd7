"""String stability: reference tables, two norms, discrete model vs the simulator, linear laws."""

from __future__ import annotations

import math

import numpy as np
import pytest
from run_marks import representative

from analysis import stability as st
from controllers.base import EpisodeContext, reset_controller
from controllers.registry import make_controller
from envs.channel import ChannelConfig
from envs.params import EVAL_SEEDS, PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import make_scenario
from infra.errors import ConfigError

# spec/controllers.md, kp = 0.2, kd = 0.7, theta = 0.2 s:
# (tau, h, ||Gamma||_inf, peak at, ACC ||Gamma||_inf)
NORM_TABLE = [
    (0.1, 0.5, 1.0486, 0.638, 1.2320),
    (0.1, 0.3, 1.0890, 0.822, 1.2439),
    (0.5, 0.5, 1.0885, 0.728, 1.3511),
]
H_MIN_DELAYS = (0.02, 0.05, 0.10, 0.15, 0.20, 0.30)
H_MIN_TABLE = {
    0.1: (0.243, 0.385, 0.547, 0.672, 0.779, 0.961),
    0.5: (0.268, 0.425, 0.605, 0.746, 0.866, 1.072),
}
SCENARIOS = ("catchup-v1", "slowdown-v1", "sine-v1", "brake-v1")


def run_batch(name, scenario, seeds, n=8, params=PlatoonParams(), channel=ChannelConfig(), **opt):
    """Run one batch of episodes; return (env, ctx, commands over time)."""
    env = PlatoonEnv(scenario, n, params, observe=False)
    ctrl = make_controller(name, **opt)
    ctx = EpisodeContext(env.scenario, n, np.asarray(seeds), params, channel)
    reset_controller(ctrl, ctx)
    env.reset(seeds)
    commands = []
    for _ in range(env.n_steps):
        u = ctrl.act(env.state, None)
        commands.append(u)
        if env.step(u).done.all():
            break
    return env, ctx, np.array(commands)


# ------------------------------------------------------------------------------ reference tables


@pytest.mark.parametrize(("tau", "h", "norm_ref", "omega_ref", "acc_ref"), NORM_TABLE)
def test_norm_table(tau, h, norm_ref, omega_ref, acc_ref):
    loop = st.PloegLoop(0.2, 0.7, h, 0.2, tau, True)
    res = st.hinf_norm(loop)
    assert res.gain == pytest.approx(norm_ref, abs=1e-3)
    assert res.omega_rad_s == pytest.approx(omega_ref, abs=1e-3)
    acc = st.hinf_norm(loop.replace(feedforward=False))
    assert acc.gain == pytest.approx(acc_ref, abs=1e-3)
    assert not res.string_stable and not acc.string_stable


@pytest.mark.parametrize("tau", sorted(H_MIN_TABLE))
def test_h_min_table(tau):
    for theta, ref in zip(H_MIN_DELAYS, H_MIN_TABLE[tau]):
        assert st.h_min(0.2, 0.7, theta, tau) == pytest.approx(ref, abs=1e-3), theta
    acc = st.h_min(0.2, 0.7, 0.2, tau, feedforward=False)
    assert acc == pytest.approx(math.sqrt(2 / 0.2), abs=1e-3)


def test_h_min_is_the_string_stability_boundary():
    h = st.h_min(0.2, 0.7, 0.2, 0.1)
    assert st.hinf_norm(st.PloegLoop(time_gap_s=h + 1e-3, delay_s=0.2, lag_s=0.1)).string_stable
    assert not st.hinf_norm(st.PloegLoop(time_gap_s=h - 1e-2, delay_s=0.2, lag_s=0.1)).string_stable
    assert st.h_min(0.2, 0.7, 0.0, 0.1) == 0.0  # no delay: CACC string stable at any h


@pytest.mark.parametrize("feedforward", [True, False])
@pytest.mark.parametrize(("tau", "h"), [(0.1, 0.5), (0.1, 0.3), (0.5, 0.5), (0.0, 1.0)])
def test_two_norm_computations_agree(tau, h, feedforward):
    loop = st.PloegLoop(0.2, 0.7, h, 0.2, tau, feedforward)
    assert st.hinf_norm_pade(loop, pade_order=5) == pytest.approx(st.hinf_norm(loop).gain, abs=1e-5)


def test_pade_model_matches_exact_response():
    loop = st.PloegLoop(delay_s=0.2, lag_s=0.1)
    w = np.geomspace(0.01, 5.0, 40)
    tf = st.gamma_tf(loop, pade_order=6)
    np.testing.assert_allclose(tf(1j * w), st.gamma_response(w, loop), atol=1e-6)
    assert abs(st.gamma_response(1e-9, loop) - 1) < 1e-6  # Gamma(0) = 1


def test_internal_stability():
    assert st.internally_stable(st.PloegLoop(lag_s=0.1))
    assert st.internally_stable(st.PloegLoop(lag_s=0.0))
    assert not st.internally_stable(st.PloegLoop(kp=0.2, kd=0.7, lag_s=4.0))  # kd < tau kp
    with pytest.raises(ConfigError):
        st.h_min(0.2, 0.7, 0.2, 4.0)


# ------------------------------------------------------------------------------ discrete model


@pytest.mark.parametrize("feedforward", [True, False])
@pytest.mark.parametrize(("delay", "lag"), [(0.2, 0.1), (0.0, 0.0), (0.3, 0.5)])
def test_discrete_tf_matches_discrete_response(delay, lag, feedforward):
    loop = st.PloegLoop(delay_s=delay, lag_s=lag, feedforward=feedforward)
    tf = st.discrete_gamma_tf(loop, 0.1)
    assert tf.dt == pytest.approx(0.1)
    w = np.geomspace(0.01, 30.0, 60)
    np.testing.assert_allclose(
        tf(np.exp(1j * w * 0.1)), st.discrete_gamma_response(w, loop), rtol=1e-9, atol=1e-12
    )
    assert abs(tf(1.0 + 1e-12) - 1.0) < 1e-6  # unit static gain
    assert st.discrete_internally_stable(loop)


@pytest.mark.parametrize(("delay", "lag"), representative([(0.2, 0.1), (0.0, 0.0)], {(0.2, 0.1)}))
def test_cacc_empirical_matches_discrete_model(delay, lag):
    omegas = np.geomspace(0.05, 3.0, 12)
    res = st.empirical_gain("cacc", omegas, n_vehicles=4, delay_s=delay, lag_s=lag)
    assert not res.collided.any() and not res.saturated.any()
    loop = st.PloegLoop(delay_s=delay, lag_s=lag)
    discrete = np.abs(st.discrete_gamma_response(omegas, loop))
    # the README: "the measured curve equals the discrete-time model to 4e-12" (measured 3.9e-12)
    np.testing.assert_allclose(res.gain, discrete, rtol=1e-11)
    np.testing.assert_allclose(res.pair_gain[:, 1:], discrete[:, None] * np.ones((1, 3)), rtol=1e-11)
    leader = np.abs(st.discrete_gamma_response(omegas, loop, pair="leader"))
    np.testing.assert_allclose(res.pair_gain[:, 0], leader, rtol=1e-11)
    # the continuous curve is close but not equal (dt = 0.1 s): within 7 % over 0.05..3 rad/s
    continuous = np.abs(st.gamma_response(omegas, loop))
    assert np.max(np.abs(res.gain / continuous - 1)) < 0.07


def test_acc_empirical_matches_discrete_model():
    omegas = np.geomspace(0.1, 2.0, 5)
    res = st.empirical_gain("acc", omegas, delay_s=0.2, lag_s=0.1)
    loop = st.PloegLoop(delay_s=0.2, lag_s=0.1, feedforward=False)
    # ACC has no feedforward and a slower decaying transient: measured 1.6e-7
    np.testing.assert_allclose(
        res.gain, np.abs(st.discrete_gamma_response(omegas, loop)), rtol=1e-6
    )


def test_empirical_rejects_bad_input():
    with pytest.raises(ConfigError):
        st.empirical_gain("cacc", [40.0])  # above Nyquist
    with pytest.raises(ConfigError):
        st.empirical_gain("cacc", [0.5], amplitude_mps=-1.0)
    with pytest.raises(ConfigError):
        st.empirical_gain("cacc", [0.5], delay_s=-0.1)


# ------------------------------------------------------------------------------ time domain


def test_time_domain_string_gain_by_hand():
    t = np.zeros((4, 3))
    t[:, 0] = [1.0, -1.0, 1.0, -1.0]  # leader, norm 2
    t[:, 1] = [2.0, 0.0, 0.0, 0.0]  # norm 2  -> ratio 1
    t[:, 2] = [0.0, 3.0, 0.0, 0.0]  # norm 3  -> ratio 1.5
    assert st.time_domain_string_gain(t) == pytest.approx(1.5)
    batch = np.stack([t, t * [1.0, 0.5, 0.5]])
    np.testing.assert_allclose(st.time_domain_string_gain(batch), [1.5, 1.5])
    t[:, 0] = 0.0  # leader at constant speed: its pair is skipped
    assert st.time_domain_string_gain(t) == pytest.approx(1.5)
    assert math.isnan(st.time_domain_string_gain(np.zeros((5, 3))))
    e = np.array([[1.0, 1.0], [1.0, 0.0]])  # ||e_1|| = sqrt 2, ||e_2|| = 1
    assert st.spacing_string_gain(e) == pytest.approx(1 / math.sqrt(2))


def test_fit_sinusoid_recovers_amplitude_and_ignores_offset():
    t = np.arange(500) * 0.1
    x = 0.7 * np.sin(0.9 * t + 0.3) + 2.0
    amp = st.fit_sinusoid(np.stack([x, 2 * x - 4.0], axis=1), 0.9, t)
    np.testing.assert_allclose(np.abs(amp), [0.7, 1.4], rtol=1e-12)


# ------------------------------------------------------------------------------ linear laws


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_cacc_no_collision_on_eval_seeds(scenario):
    env, _, commands = run_batch("cacc", scenario, list(EVAL_SEEDS))
    assert env.batch_size == 50
    assert not env.state.collided.any()
    assert np.all(np.isfinite(commands))
    assert env.state.gap_m.min() > 10.0


def test_cacc_no_collision_with_delay_lag_and_loss():
    for scenario in SCENARIOS:
        env, _, _ = run_batch(
            "cacc",
            scenario,
            list(EVAL_SEEDS),
            params=PlatoonParams(lag_s=0.1),
            channel=ChannelConfig(delay_s=0.2, packet_loss=0.2),
        )
        assert not env.state.collided.any(), scenario


@pytest.mark.parametrize("name", ["acc", "cacc"])
def test_stays_at_equilibrium(name):
    scenario = make_scenario("sine-v1", amplitude_mps=0.0)  # constant leader, start at targets
    env, _, commands = run_batch(name, scenario, [2000, 2010], n=4)
    assert np.all(commands == 0.0)
    np.testing.assert_allclose(env.state.gap_m, 20.0, atol=1e-12)
    np.testing.assert_allclose(env.state.speed_mps, 15.0, atol=1e-12)


@pytest.mark.parametrize(("name", "tol"), [("cacc", 1e-3), ("acc", 0.05)])
def test_settles_to_targets_after_catchup(name, tol):
    env, _, _ = run_batch(name, "catchup-v1", [2000, 2250, 2490])
    np.testing.assert_allclose(env.state.gap_m, 20.0, atol=tol)
    np.testing.assert_allclose(env.state.speed_mps, 15.0, atol=tol)


def test_explicit_standstill_distance_sets_the_equilibrium():
    # r + h v* = 10 + 0.5 * 15 = 17.5 m instead of the scenario's 20 m
    env, _, _ = run_batch("cacc", "catchup-v1", [2000], n=3, standstill_m=10.0)
    np.testing.assert_allclose(env.state.gap_m, 17.5, atol=1e-2)


def test_v2v_traffic_and_slowdown_quirk():
    env, ctx, commands = run_batch("cacc", "slowdown-v1", [2490], n=4)
    steps = len(commands)
    # senders: the leader and followers 1..N-1 (follower N has no receiver), one float32 each
    assert ctx.bits_sent == steps * 1 * 4 * 32
    assert np.all(np.abs(commands) <= 2.5)
    _, ctx_acc, _ = run_batch("acc", "slowdown-v1", [2490], n=4)
    assert ctx_acc.bits_sent == 0 and not ctx_acc.channels


def test_batched_equals_single_with_packet_loss():
    channel = ChannelConfig(delay_s=0.1, packet_loss=0.3)
    batch, _, cb = run_batch("cacc", "brake-v1", [2000, 2010], n=3, channel=channel)
    one, _, c1 = run_batch("cacc", "brake-v1", [2010], n=3, channel=channel)
    np.testing.assert_array_equal(cb[:, 1], c1[:, 0])
    np.testing.assert_array_equal(batch.state.gap_m[1], one.state.gap_m[0])


@pytest.mark.parametrize(
    ("name", "options"),
    [
        ("cacc", {"kp": -0.2}),
        ("cacc", {"kp": 0.0}),
        ("cacc", {"kd": -0.7}),
        ("acc", {"time_gap_s": -0.5}),
        ("cacc", {"standstill_m": -1.0}),
        ("cacc", {"kp": "abc"}),
        ("cacc", {"gain": 1.0}),
        ("acc", {"feedforward": True}),
    ],
)
def test_invalid_parameters_raise(name, options):
    with pytest.raises(ConfigError):
        make_controller(name, **options)


def test_unstable_lag_raises_at_reset():
    ctrl = make_controller("cacc")  # kd = 0.7 <= 5 * 0.2
    ctx = EpisodeContext(make_scenario("catchup-v1"), 4, np.array([2000]), PlatoonParams(lag_s=5.0))
    with pytest.raises(ConfigError, match="unstable"):
        reset_controller(ctrl, ctx)
    with pytest.raises(ConfigError):
        st.PloegLoop(kd=-1.0)


def test_options_from_strings():
    ctrl = make_controller("cacc", time_gap_s="0.8", kp="0.3", feedforward="false")
    assert ctrl.config.time_gap_s == 0.8 and ctrl.config.kp == 0.3 and not ctrl.config.feedforward
    loop = st.PloegLoop.from_controller(ctrl, delay_s=0.2, lag_s=0.1)
    assert loop == st.PloegLoop(0.3, 0.7, 0.8, 0.2, 0.1, False)
    with pytest.raises(ConfigError):
        st.PloegLoop.from_controller(make_controller("ovm"))
