"""The MPC family (``mpc``, ``mpc-qp``, ``cmpc``): backends agree, LQR limit, bounds, fallback,
V2V handling, options, batching, and closed-loop behaviour (fast versions here, the 10-seed
checks marked slow)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from benchmark.rollout import rollout_batch
from controllers.base import EpisodeContext, reset_controller
from controllers.mpc_controller import DistributedMPCBase
from controllers.mpc_model import (
    ParamLayout,
    VehicleModel,
    assumed_predecessor_speeds,
    make_parameters,
    shift_and_hold,
)
from controllers.mpc_optimiser import SolveResult, kinetic_energy_rate, lqr_weights, smooth_max
from controllers.registry import make_controller, parse_controller_list
from envs.channel import ChannelConfig
from envs.params import EVAL_SEEDS, PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import make_scenario
from infra.errors import ConfigError

VARIANTS = ("mpc", "mpc-qp", "cmpc")
SCENARIOS = (
    "catchup-v1",
    "slowdown-v1",
    "brake-v1",
    "openacc-s-v1",
    "openacc-m-v1",
    "openacc-l-v1",
)


# --------------------------------------------------------------------------- helpers


def one_problem(
    ctrl: Any,
    gap_m: float,
    speed_mps: float,
    last_u: float,
    vp: np.ndarray | float,
    accel_mps2: float = 0.0,
    vhat: np.ndarray | None = None,
    d_star: float = 20.0,
    v_star: float = 15.0,
) -> np.ndarray:
    """Parameter vector of one follower's problem for a prepared distributed controller."""
    h = ctrl.config.horizon
    vp_arr = np.broadcast_to(np.asarray(vp, dtype=np.float64), (h + 1,)).reshape(1, 1, h + 1)
    vh = np.full((1, 1, h + 1), speed_mps) if vhat is None else vhat.reshape(1, 1, h + 1)
    p = make_parameters(
        ctrl.layout,
        ctrl.model,
        ctrl.params,
        np.array([[gap_m]]),
        np.array([[speed_mps]]),
        np.array([[accel_mps2]]),
        np.array([[last_u]]),
        vp_arr,
        vh,
        d_star,
        v_star,
    )
    return p[0, 0]


@dataclass
class RunStats:
    collided: np.ndarray  # (B,)
    energy_kwh: np.ndarray  # (B,) platoon energy
    gap_rmse_m: float
    speed_rmse_mps: float
    min_gap_m: float
    failures: int
    u_min: float
    u_max: float


def run(
    name: str,
    scenario: str,
    seeds: list[int] | tuple[int, ...],
    n_vehicles: int | None = None,
    n_steps: int | None = None,
    channel: ChannelConfig = ChannelConfig(),
    params: PlatoonParams = PlatoonParams(),
    options: dict[str, object] | None = None,
) -> RunStats:
    """One controller over a batch of episodes, through the harness's own loop."""
    ctrl = make_controller(name, **(options or {}))
    sc = make_scenario(scenario)
    if n_steps is not None:
        sc = dataclasses.replace(sc, n_steps=min(n_steps, sc.n_steps))
    trajs = rollout_batch(ctrl, sc, n_vehicles or sc.default_vehicles, list(seeds), params,
                          channel)
    gap = np.concatenate([t.gap_m[1:] for t in trajs])
    speed = np.concatenate([t.speed_mps[1:] for t in trajs])
    u = np.concatenate([t.command_mps2 for t in trajs])
    return RunStats(
        collided=np.array([t.collided for t in trajs]),
        energy_kwh=np.array([t.power_kw.sum() * params.dt_s / 3600.0 for t in trajs]),
        gap_rmse_m=float(np.sqrt(np.mean((gap - sc.target_gap_m) ** 2))),
        speed_rmse_mps=float(np.sqrt(np.mean((speed - sc.target_speed_mps) ** 2))),
        min_gap_m=float(min(t.gap_m.min() for t in trajs)),
        failures=int(ctrl.solver_failures),
        u_min=float(u.min()),
        u_max=float(u.max()),
    )


# --------------------------------------------------------------------------- options


def test_options_from_the_command_line() -> None:
    [(name, opts)] = parse_controller_list("mpc:solver=ipopt,horizon=30")
    ctrl = make_controller(name, **opts)
    assert ctrl.config.solver == "ipopt" and ctrl.config.horizon == 30
    assert ctrl.options == {"solver": "ipopt", "horizon": "30"}
    assert "horizon=30" in ctrl.describe()
    qp = make_controller("mpc-qp", w_gap="2.5", polishing="true")
    assert qp.config.w_gap == 2.5 and qp.config.polishing is True
    assert make_controller("cmpc", horizon="10").config.horizon == 10


@pytest.mark.parametrize(
    ("name", "options"),
    [
        ("mpc", {"solver": "acados"}),
        ("mpc", {"nonsense": "1"}),
        ("mpc", {"horizon": "0"}),
        ("mpc", {"self_weight": "0.5"}),  # Zheng: the self weight must dominate (or be 0)
        ("mpc", {"energy_weight": "-1"}),
        ("mpc-qp", {"terminal": "cone"}),
        ("mpc-qp", {"energy_weight": "1"}),  # no energy term in the QP variant
        ("cmpc", {"solver": "SCS"}),
    ],
)
def test_bad_options_fail_loudly(name: str, options: dict[str, str]) -> None:
    with pytest.raises(ConfigError):
        make_controller(name, **options)


# --------------------------------------------------------------------------- formulation pieces


def test_shift_and_hold() -> None:
    plan = np.arange(5.0)[None, :].repeat(2, 0)
    out = shift_and_hold(plan, np.array([0, 3]))
    np.testing.assert_array_equal(out[0], [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(out[1], [3, 4, 4, 4, 4])
    np.testing.assert_array_equal(shift_and_hold(plan[:1], 9)[0], [4, 4, 4, 4, 4])


def test_assumed_predecessor_trajectory_from_stale_messages() -> None:
    h = 4
    received = np.full((1, 3, h + 2), np.nan)
    received[0, 0] = [5, 10, 11, 12, 13, 14]  # made at step 5
    received[0, 1] = [7, 20, 19, 18, 17, 16]  # made at step 7 (age 1 at step 8)
    measured = np.array([[12.5, 19.0, 9.0]])
    out = assumed_predecessor_speeds(received, 8, measured)
    # age 3: [13, 14, 14, 14, 14], offset to start at the measured 12.5
    np.testing.assert_allclose(out[0, 0], [12.5, 13.5, 13.5, 13.5, 13.5])
    np.testing.assert_allclose(out[0, 1], [19, 18, 17, 16, 16])
    # nothing received yet: the measured speed held
    np.testing.assert_allclose(out[0, 2], [9.0] * 5)


def test_kinetic_energy_rate_is_about_the_equivalent_mass() -> None:
    from envs.energy import VehicleParams, load_power_polynomial

    c = kinetic_energy_rate(load_power_polynomial())
    m_t = VehicleParams().equivalent_mass_kg / 1000
    assert 0.95 * m_t < c < 1.15 * m_t


def test_v2v_plans_age_with_the_channel_delay() -> None:
    """Delay 0.2 s = 2 steps: a plan used at step t was made at t - 3 (one step of DMPC)."""
    ctrl = make_controller("mpc-qp", horizon=10)
    sc = dataclasses.replace(make_scenario("catchup-v1"), n_steps=6)
    traj = rollout_batch(ctrl, sc, 3, [2000], channel=ChannelConfig(0.2, 0.0))[0]
    # after act at step 5 the receivers hold the plans sent at step 3
    np.testing.assert_array_equal(ctrl._received[0, :, 0], [3, 3, 3])
    # every sender broadcasts H+2 floats of 32 bits each step
    assert traj.bits_sent == 6 * 3 * 12 * 32  # senders: the leader and followers 1, 2


# --------------------------------------------------------------------------- two backends, LQR


def _energy_cases(ctrl: Any) -> list[np.ndarray]:
    h = ctrl.config.horizon
    k = np.arange(h + 1)
    return [
        one_problem(ctrl, 35.0, 15.0, 0.0, 15.0),  # catch up
        one_problem(ctrl, 20.0, 15.0, -0.5, np.maximum(15 - 0.25 * k, 10)),  # braking pred.
        one_problem(ctrl, 7.0, 14.0, 0.0, 11.0),  # minimum gap about to be violated
        one_problem(ctrl, 27.0, 30.0, 0.0, 36.5),  # at the speed bound behind a faster leader
        one_problem(ctrl, 18.0, 11.0, 0.3, 11.0 + 0.1 * k, vhat=11 + 0.05 * k),  # self term
    ]


def test_mpc_fatrop_sqp_ipopt_give_the_same_first_input() -> None:
    tol = {"tol": "1e-9"}
    solvers = {s: make_controller("mpc", solver=s, **tol) for s in ("fatrop", "sqp", "ipopt")}
    for c in solvers.values():
        c.prepare(PlatoonParams())
    diffs = []
    for p in _energy_cases(solvers["ipopt"]):
        ref, _ = solvers["ipopt"].solve_parameters(p)
        assert ref.ok
        for s in ("fatrop", "sqp"):
            res, _ = solvers[s].solve_parameters(p)
            assert res.ok, s
            diffs.append(abs(res.command_mps2 - ref.command_mps2))
            np.testing.assert_allclose(res.plan_speed_mps, ref.plan_speed_mps, atol=1e-5)
    assert max(diffs) < 1e-5


def test_qp_osqp_matches_casadi_ipopt_and_cvxpy() -> None:
    """mpc-qp (OSQP) and mpc with energy_weight=0 (IPOPT) solve one problem; so does cvxpy."""
    import cvxpy as cp

    qp = make_controller("mpc-qp", polishing="true", eps_abs=1e-9, eps_rel=1e-9, max_iter=100000)
    nlp = make_controller("mpc", solver="ipopt", energy_weight=0, tol=1e-10)
    qp.prepare(PlatoonParams())
    nlp.prepare(PlatoonParams())
    for p in _energy_cases(qp):
        a, _ = qp.solve_parameters(p)
        b, _ = nlp.solve_parameters(p)
        assert a.ok and b.ok
        assert abs(a.command_mps2 - b.command_mps2) < 1e-5  # IPOPT relaxes bounds by 1e-8
        # the same QP matrices in cvxpy (Clarabel)
        q, lo, up = qp.qp.vectors(p)
        z = cp.Variable(len(q))
        big = 1e20
        fin_l, fin_u = lo > -big, up < big
        cons = [qp.qp.A[fin_l] @ z >= lo[fin_l], qp.qp.A[fin_u] @ z <= up[fin_u]]
        prob = cp.Problem(
            cp.Minimize(0.5 * cp.quad_form(z, qp.qp.H, assume_PSD=True) + q @ z), cons
        )
        prob.solve(solver="CLARABEL")
        assert z.value is not None
        assert abs(z.value[qp.ocp.i_u[0]] - a.command_mps2) < 1e-5


@pytest.mark.parametrize(
    ("lag_s", "terminal", "horizon"),
    [(0.0, "lqr", 20), (0.0, "stage", 300), (0.3, "lqr", 20), (0.3, "stage", 300)],
)
def test_unconstrained_qp_feedback_equals_dlqr(lag_s: float, terminal: str, horizon: int) -> None:
    """No active constraint, predecessor at constant speed, no self term: first input = -K x."""
    import control

    params = PlatoonParams(lag_s=lag_s)
    ctrl = make_controller(
        "mpc-qp",
        self_weight=0,
        terminal=terminal,
        horizon=horizon,
        polishing=True,
        eps_abs=1e-10,
        eps_rel=1e-10,
        max_iter=200000,
    )
    ctrl.prepare(params)
    model: VehicleModel = ctrl.model
    a_mat, b_mat = model.linear_error_model()
    q, r, n = lqr_weights(ctrl.config, model)
    k_gain, _, _ = control.dlqr(a_mat, b_mat, q, r, n)
    rng = np.random.default_rng(0)
    for _ in range(4):
        e_gap, e_v, accel, last_u = rng.uniform([-1, -0.5, -0.2, -0.2], [1, 0.5, 0.2, 0.2])
        x = [e_gap, e_v] + ([accel] if model.has_lag else []) + [last_u]
        p = one_problem(ctrl, 20 + e_gap, 15 + e_v, last_u, 15.0, accel_mps2=accel)
        res, _ = ctrl.solve_parameters(p)
        assert res.ok
        expected = float(-(k_gain @ np.asarray(x))[0])
        assert res.command_mps2 == pytest.approx(expected, abs=1e-6)


def test_parameter_layout_round_trip() -> None:
    layout = ParamLayout(3, 5)
    assert layout.size == 3 + 2 + 4 * 6
    assert layout.vref.stop == layout.size


# --------------------------------------------------------------------------- bounds and fallback


@pytest.mark.parametrize("name", VARIANTS)
@pytest.mark.parametrize("scenario", ["brake-v1", "slowdown-v1"])
def test_commands_respect_the_bounds(name: str, scenario: str) -> None:
    # brake-v1 brakes at -2.5 from t = 10 s; slowdown-v1 starts above the speed bound
    steps = 160 if scenario == "brake-v1" else 40
    stats = run(name, scenario, [2020], n_vehicles=3, n_steps=steps)
    p = PlatoonParams()
    assert p.accel_min_mps2 <= stats.u_min and stats.u_max <= p.accel_max_mps2
    assert not stats.collided.any()
    assert stats.failures == 0


@pytest.mark.parametrize(
    ("name", "options"),
    [
        ("mpc", {"max_iter": 1}),
        ("mpc", {"solver": "fatrop", "max_iter": 1}),
        ("mpc-qp", {"max_iter": 1}),
    ],
)
def test_iteration_limit_falls_back_safely(name: str, options: dict[str, object]) -> None:
    stats = run(name, "catchup-v1", [2000], n_vehicles=3, n_steps=40, options=options)
    assert stats.failures == 40 * 3  # every solve failed, every one was counted
    assert not stats.collided.any()
    assert -2.5 <= stats.u_min and stats.u_max <= 2.5


@pytest.mark.parametrize("name", ["mpc", "mpc-qp"])
def test_solver_exception_falls_back(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    ctrl = make_controller(name, horizon=10)
    env = PlatoonEnv("brake-v1", 3, observe=False)
    ctx = EpisodeContext(env.scenario, 3, np.array([2000]), env.params)
    reset_controller(ctrl, ctx)
    env.reset([2000])
    real = ctrl._solve
    calls = {"n": 0}

    def flaky(p: np.ndarray, warm: object) -> object:
        calls["n"] += 1
        if calls["n"] % 3 == 0:
            raise RuntimeError("solver crashed")
        return real(p, warm)

    monkeypatch.setattr(ctrl, "_solve", flaky)
    for _ in range(150):
        u = ctrl.act(env.state, None)
        assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= 2.5)
        res = env.step(u)
    assert ctrl.solver_failures == 150
    assert not res.collided.any()


def test_cmpc_failure_falls_back(monkeypatch: pytest.MonkeyPatch) -> None:
    ctrl = make_controller("cmpc", horizon=10)
    env = PlatoonEnv("catchup-v1", 3, observe=False)
    ctx = EpisodeContext(env.scenario, 3, np.array([2000]), env.params)
    reset_controller(ctrl, ctx)
    env.reset([2000])
    env.step(ctrl.act(env.state, None))
    monkeypatch.setattr(ctrl.problem, "solve", lambda *a: (False, np.full((3, 10), np.nan)))
    for _ in range(30):
        u = ctrl.act(env.state, None)
        assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= 2.5)
        res = env.step(u)
    assert ctrl.solver_failures == 30
    assert not res.collided.any()


# --------------------------------------------------------------------------- batching, timing


@pytest.mark.parametrize("name", ["mpc", "mpc-qp", "cmpc"])
def test_batched_equals_one_by_one(name: str) -> None:
    seeds = [2000, 2010]
    n, steps = 3, 30

    def commands(batch: list[int]) -> np.ndarray:
        sc = dataclasses.replace(make_scenario("catchup-v1"), n_steps=steps)
        trajs = rollout_batch(make_controller(name, horizon=10), sc, n, batch)
        return np.stack([t.command_mps2 for t in trajs])  # (B, T, N)

    together = commands(seeds)
    alone = np.concatenate([commands([s]) for s in seeds])
    # the distributed variants solve each follower's problem on its own (own warm start, own
    # OSQP step size): exact; cmpc's cvxpy/OSQP warm start is shared: solver tolerance
    np.testing.assert_allclose(together, alone, atol=1e-4 if name == "cmpc" else 1e-10)


def test_perf_timing_reports_per_vehicle_times() -> None:
    from commands.perf import controller_timing

    out = controller_timing("mpc-qp", n_steps=5, n_vehicles=3, options={"horizon": "10"})
    assert {"median_ms", "p95_ms", "first_ms"} <= set(out)
    assert 0 < out["median_ms"] <= out["p95_ms"] and out["first_ms"] > 0 and out["steps"] == 5


# --------------------------------------------------------------------------- behaviour (fast)


@pytest.mark.parametrize("name", VARIANTS)
@pytest.mark.parametrize("scenario", ["catchup-v1", "slowdown-v1"])
def test_no_collision_fast(name: str, scenario: str) -> None:
    stats = run(name, scenario, [EVAL_SEEDS[2]], n_vehicles=4, n_steps=200)
    assert not stats.collided.any()
    assert stats.failures == 0


def test_mpc_saves_energy_fast() -> None:
    qp = run("mpc-qp", "catchup-v1", [EVAL_SEEDS[0]], n_vehicles=4, n_steps=300)
    mpc = run("mpc", "catchup-v1", [EVAL_SEEDS[0]], n_vehicles=4, n_steps=300)
    assert mpc.energy_kwh.sum() < qp.energy_kwh.sum()


def test_mpc_degraded_v2v_fast() -> None:
    stats = run(
        "mpc",
        "catchup-v1",
        [EVAL_SEEDS[0]],
        n_vehicles=4,
        n_steps=200,
        channel=ChannelConfig(delay_s=0.2, packet_loss=0.1),
    )
    assert not stats.collided.any()


# --------------------------------------------------------------------------- behaviour (slow)


@pytest.mark.slow
@pytest.mark.parametrize("name", VARIANTS)
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_no_collision_ten_seeds(name: str, scenario: str) -> None:
    stats = run(name, scenario, list(EVAL_SEEDS[:10]))
    assert not stats.collided.any(), f"{name} collides on {scenario}"


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["catchup-v1", "slowdown-v1"])
def test_mpc_uses_less_energy_than_mpc_qp(scenario: str) -> None:
    seeds = list(EVAL_SEEDS[:10])
    qp = run("mpc-qp", scenario, seeds)
    mpc = run("mpc", scenario, seeds)
    for label, s in (("mpc", mpc), ("mpc-qp", qp)):
        print(
            f"{scenario} {label}: energy {s.energy_kwh.mean():.4f} kWh/episode, "
            f"gap RMSE {s.gap_rmse_m:.3f} m, speed RMSE {s.speed_rmse_mps:.3f} m/s"
        )
    assert not mpc.collided.any() and not qp.collided.any()
    assert mpc.energy_kwh.mean() < qp.energy_kwh.mean()


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["catchup-v1", "slowdown-v1"])
def test_mpc_degraded_v2v_ten_seeds(scenario: str) -> None:
    stats = run(
        "mpc",
        scenario,
        list(EVAL_SEEDS[:10]),
        channel=ChannelConfig(delay_s=0.2, packet_loss=0.1),
    )
    print(
        f"{scenario} mpc delay 0.2 s loss 0.1: min gap {stats.min_gap_m:.2f} m, "
        f"energy {stats.energy_kwh.mean():.4f} kWh, failures {stats.failures}"
    )
    assert not stats.collided.any()


@pytest.mark.parametrize(
    ("gap", "v", "v_pred", "target", "want"),
    [
        (20.0, 15.0, 15.0, 20.0, 0.0),            # at the target: nothing to do
        (25.0, 15.0, 15.0, 20.0, 1.0),            # 0.2 * 5
        (15.0, 15.0, 14.0, 20.0, -1.7),           # 0.2 * -5 + 0.7 * -1
        (100.0, 15.0, 15.0, 20.0, 2.5),           # clipped to accel_max
        (1.8, 10.0, 9.5, 2.0, -2.5),              # below 2 gap_min and closing: full brake
        (1.8, 10.0, 10.5, 2.0, 0.2 * -0.2 + 0.7 * 0.5),  # below but opening: the law
        (2.5, 10.0, 9.5, 2.0, 0.2 * 0.5 + 0.7 * -0.5),   # closing but not below: the law
        (2.0, 10.0, 9.5, 2.0, 0.7 * -0.5),        # at exactly 2 gap_min: not below, the law
        (1.8, 10.0, 10.0, 2.0, 0.2 * -0.2),       # below, speeds equal (not closing): the law
        (5.0, 15.0, 15.0, 20.0, -2.5),            # the law's -3.0 clipped to accel_min
    ],
)
def test_fallback_law_and_its_emergency_brake(gap, v, v_pred, target, want) -> None:
    """The fallback ``u = 0.2 (gap - d*) + 0.7 (v_pred - v)`` clipped to [-2.5, 2.5], with a
    full brake when the gap is below 2 gap_min (2 m) and closing (values by hand)."""
    from controllers.mpc_controller import acc_fallback_mps2

    got = float(acc_fallback_mps2(gap, v, v_pred, target, PlatoonParams()))
    assert got == pytest.approx(want, abs=1e-12)


def test_fallback_brake_threshold_scales_with_gap_min() -> None:
    """The emergency threshold is 2 gap_min for any gap_min (the default is 1 m): with
    gap_min = 2 m a gap of 3.5 m is below it, and with gap_min = 0.5 m a gap of 1.5 m is not."""
    from controllers.mpc_controller import acc_fallback_mps2

    assert float(acc_fallback_mps2(3.5, 10.0, 9.5, 2.0, PlatoonParams(gap_min_m=2.0))) == -2.5
    law = 0.2 * (1.5 - 2.0) + 0.7 * -0.5
    got = float(acc_fallback_mps2(1.5, 10.0, 9.5, 2.0, PlatoonParams(gap_min_m=0.5)))
    assert got == pytest.approx(law, abs=1e-12)


# --------------------------------------------------------------------------- the shared loop, scripted


class _ScriptedMPC(DistributedMPCBase):
    """The distributed MPC loop with a scripted solver for N = 2 followers: each ``act``'s
    solves pop the next entry for both followers (``None``: a failed solve; else
    ``(command, plan_u)``); every solve records its parameters, the warm start it was given and
    the plan it returned."""

    name = "scripted-mpc"

    def __init__(self, script: list[Any], **options: Any) -> None:
        super().__init__(**options)
        self.script = [entry for entry in script for _ in range(2)]  # both followers
        self.calls: list[tuple[np.ndarray, Any]] = []
        self.plans: list[np.ndarray] = []

    def _build(self) -> None:
        return None

    def _solve(self, p: np.ndarray, warm: Any) -> tuple[SolveResult, Any]:
        self.calls.append((p.copy(), warm))
        entry = self.script.pop(0)
        h = self.config.horizon
        plan_v = 10.0 + np.arange(h + 1.0) + len(self.calls)  # a distinct plan per call
        self.plans.append(plan_v)
        if entry is None:
            return SolveResult(False, float("nan"), np.full(h + 1, np.nan), np.zeros(h)), None
        command, plan_u = entry
        return SolveResult(True, command, plan_v, np.asarray(plan_u, float)), f"w{len(self.calls)}"


def _scripted_env(ctrl: _ScriptedMPC, batch: int = 1, lag_s: float = 0.0):
    env = PlatoonEnv("catchup-v1", 2, PlatoonParams(lag_s=lag_s), observe=False)
    seeds = np.arange(2000, 2000 + 10 * batch, 10)
    reset_controller(ctrl, EpisodeContext(env.scenario, 2, seeds, env.params))
    env.reset(seeds)
    return env


def test_mpc_loop_plans_warm_starts_and_falls_back_on_the_shifted_plan() -> None:
    """Step by step with a scripted solver (H = 4, gaps held at 100 m so that the ACC
    fallback asks for its maximum 2.5), follower 1: a command beyond the bounds is clipped; the
    first problem assumes the measured speed held; each later one the last plan shifted by one
    step; a solve gets the warm start the previous one returned, and none after a failure; a
    failed solve falls back on min(the kept plan's command for now, ACC), and the kept plan goes
    on shifting (its last command held) through further failures."""
    h = 4
    script = [(5.0, [5.0, 0.7, 0.9, 1.1]), (0.1, [0.1, 0.3, 0.5, 0.6]), None, None, None, None,
              (0.2, [0.2] * h)]
    ctrl = _ScriptedMPC(script, horizon=h)
    env = _scripted_env(ctrl)
    layout = ctrl.layout
    us = []
    for t in range(len(script)):
        env.state.gap_m[:] = 100.0
        if t == 0:
            env.state.speed_mps[:] = 0.5  # a crawling start: the assumed plan is 0.5 m/s held
        u = ctrl.act(env.state, None)
        us.append(float(u[0, 0]))
        p, _ = ctrl.calls[2 * t]  # follower 1's problem of this step
        if t == 0:
            np.testing.assert_array_equal(p[layout.vhat], np.full(h + 1, 0.5))
        if t in (1, 2):  # follower 1's previous plan shifted by one step, its end held
            prev = ctrl.plans[2 * (t - 1)]
            np.testing.assert_array_equal(p[layout.vhat][1:], np.append(prev[2:], prev[-1]))
        env.step(u)
    assert us == [2.5, 0.1, 0.3, 0.5, 0.6, 0.6, 0.2]
    assert [w for _, w in ctrl.calls[0::2]] == [None, "w1", "w3", None, None, None, None]
    assert ctrl.solve_count == 2 * len(script) and ctrl.solver_failures == 2 * 4


def test_mpc_loop_with_a_one_step_horizon_falls_back_on_acc() -> None:
    """With H = 1 a plan made one step ago has nothing left for now: a failed solve takes the
    ACC fallback (2.5 at a 100 m gap), not the old plan's 0.2."""
    ctrl = _ScriptedMPC([(0.2, [0.2]), None], horizon=1)
    env = _scripted_env(ctrl)
    us = []
    for _ in range(2):
        env.state.gap_m[:] = 100.0
        u = ctrl.act(env.state, None)
        us.append(float(u[0, 0]))
        env.step(u)
    assert us == [0.2, 2.5]


def test_mpc_loop_skips_ended_episodes_only() -> None:
    """An ended episode of a batch is not solved (its commands are 0); the episodes after it
    are."""
    ctrl = _ScriptedMPC([(1.0, [1.0, 1.0])], horizon=2)
    env = _scripted_env(ctrl, batch=2)
    env.state.done[0] = True
    u = ctrl.act(env.state, None)
    assert u.tolist() == [[0.0, 0.0], [1.0, 1.0]] and ctrl.solve_count == 2


def test_mpc_loop_passes_the_realised_acceleration_with_a_lag() -> None:
    """With an actuator lag the problem's state holds the realised acceleration (feasible)."""
    ctrl = _ScriptedMPC([(0.0, [0.0, 0.0])], horizon=2)
    env = _scripted_env(ctrl, lag_s=0.2)
    env.state.realised_accel_mps2[:] = 0.4
    ctrl.act(env.state, None)
    p, _ = ctrl.calls[0]
    assert ctrl.layout.nx == 4 and p[2] == 0.4


@pytest.mark.parametrize("lag_s", [0.1, 0.5])
def test_feasible_lag_accel_keeps_the_coasting_speed_in_bounds(lag_s: float) -> None:
    """With u = 0 from realised acceleration a, the lag ``a' = (1-g) a`` adds
    ``dt a (1-g) / g`` to the speed in all (a geometric series, summed here step by step):
    the clipped a takes a speed of 1 m/s exactly to 0, and 29 m/s exactly to 30 (speed_max);
    accelerations that stay in bounds pass unchanged; without a lag nothing is clipped."""
    from controllers.mpc_model import VehicleModel, feasible_lag_accel

    params = PlatoonParams(lag_s=lag_s)
    model = VehicleModel.from_params(params)
    g = model.lag_gain

    def coast(v: float, a: float) -> float:
        for _ in range(5000):
            a = (1 - g) * a
            v += model.dt_s * a
        return v

    v = np.array([1.0, 29.0, 15.0])
    a = np.array([-50.0, 50.0, 0.3])
    clipped = feasible_lag_accel(v, a, model, params)
    assert coast(1.0, clipped[0]) == pytest.approx(0.0, abs=1e-9)
    assert coast(29.0, clipped[1]) == pytest.approx(params.speed_max_mps, abs=1e-9)
    assert clipped[2] == 0.3
    free = VehicleModel.from_params(PlatoonParams())
    out = feasible_lag_accel(v, a, free, PlatoonParams())
    assert out.dtype == np.float64 and out.tolist() == a.tolist()


def test_the_smoothed_maximum_is_within_half_its_width_of_the_maximum() -> None:
    """The MPC's energy term smooths max(polynomial, floor): within e / 2 at the kink, closer
    away from it, never below the maximum; the env keeps the exact maximum."""
    a = np.linspace(-10.0, 10.0, 201)
    for e in (1.0, 3.0):
        s = smooth_max(a, 0.0, e)
        assert np.all(s >= np.maximum(a, 0.0))
        assert np.max(s - np.maximum(a, 0.0)) == pytest.approx(e / 2)
        assert s[-1] - 10.0 < e**2 / 40 + 1e-9  # (sqrt(d^2 + e^2) - d) / 2 <= e^2 / (4 d)
