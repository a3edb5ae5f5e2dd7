"""The safety filter ``safe:<controller>`` (controllers/safety_filter.py, docs/safety-filter.md).

It never changes a safe command; an unsafe controller collides without it and never with it;
it counts its interventions right; the envelope's invariant holds in closed loop (against an
independent simulation of the braking plan, with and without actuator lag); bad specs are
refused by the CLI with exit 2; the same seed gives the same numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmark.check import check_controller
from benchmark.export import runs_frame
from benchmark.rollout import Trajectory, rollout, rollout_batch
from benchmark.suite import build_sweep, execute_batch, execute_run
from commands.cli import main as cli
from controllers.base import Controller, EpisodeContext, reset_controller
from controllers.registry import (
    CONTROLLERS,
    canonical_options,
    controller_label,
    make_controller,
    parse_controller_list,
    resolve,
    runs_inside_simulator,
)
from controllers.safety_filter import (
    SafetyFilter,
    SafetyFilterConfig,
    barrier_m,
    braking_distance_m,
    filter_commands,
    max_safe_command_mps2,
    next_margin_m,
)
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv, PlatoonState
from envs.scenarios import make_scenario

SEEDS = list(range(2000, 2100, 10))
SCENARIOS = ("catchup-v1", "slowdown-v1", "brake-v1")
#: Rounding slack of the closed-form margin (m).
TOL_M = 1e-9


class FullThrottle(Controller):
    """A deliberately unsafe controller: every follower commands ``accel`` all the time."""

    name = "full-throttle"
    family = "linear"
    batch_invariant = True

    def __init__(self, accel_mps2: float = 2.5) -> None:
        super().__init__()
        self.accel_mps2 = accel_mps2

    def reset(self, ctx: EpisodeContext) -> None:
        pass

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        return np.full(state.gap_m.shape, self.accel_mps2)


def filtered(inner: Controller, config: SafetyFilterConfig = SafetyFilterConfig()
             ) -> SafetyFilter:
    """``inner`` (an unregistered test controller) behind the filter."""
    ctrl = SafetyFilter("cacc")  # a registered name to build with, then its inner replaced
    ctrl.inner, ctrl.config, ctrl.name = inner, config, f"safe:{inner.name}"
    ctrl.batch_invariant = inner.batch_invariant
    return ctrl


# ------------------------------------------------------------------ the envelope itself


def _simulated_stop_m(speed_mps: np.ndarray, accel_mps2: np.ndarray, params: PlatoonParams,
                      brake_mps2: float, speed_max_mps: float | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Distances covered (cumulative, (T, ...)) braking with ``-brake_mps2`` from ``(v, a)``
    through the env's lag, with the env's own rules (an independent implementation of the
    plan); ``speed_max_mps`` None: the env's bound (a leader's profile has none: ``inf``)."""
    v, a = np.array(speed_mps, dtype=float), np.array(accel_mps2, dtype=float)
    top = params.speed_max_mps if speed_max_mps is None else speed_max_mps
    steps = []
    for _ in range(2000):
        a = a + (-brake_mps2 - a) * params.lag_gain
        v_next = np.clip(v + a * params.dt_s, 0.0, top)
        steps.append(params.dt_s / 2 * (v + v_next))
        v = v_next
        if not v.any():
            break
    return np.cumsum(steps, axis=0), v


def test_braking_distance_is_the_simulated_stop() -> None:
    """``D(w; beta)`` in closed form equals the env's trapezoidal sum of a braking vehicle, by
    hand on one case, and tends to ``w^2 / 2b`` (45 m from 15 m/s at 2.5 m/s^2) as dt -> 0."""
    params = PlatoonParams()
    w = np.linspace(0.0, 30.0, 1201)
    dist, _ = _simulated_stop_m(w, np.full_like(w, -2.5), params, 2.5)
    np.testing.assert_allclose(braking_distance_m(w, 0.25, 0.1), dist[-1], rtol=0, atol=1e-9)
    # by hand: 0.25 m/s per step from 1 m/s: speeds 1, .75, .5, .25, 0 -> 0.05 (1.75+1.25+.75+.25)
    assert braking_distance_m(np.array(1.0), 0.25, 0.1) == pytest.approx(0.2, abs=1e-12)
    assert braking_distance_m(np.array(15.0), 0.025, 0.01) == pytest.approx(45.0, rel=1e-3)


def test_a_hand_made_case_is_corrected_exactly_and_counted() -> None:
    """A follower at 1 m/s, 2.26 m behind a stopped predecessor, may command at most -1 m/s^2
    (d_min = 2 m: after -1 m/s^2 its speed is 0.9 m/s, the gap 2.26 - 0.05 (1 + 0.9) = 2.165 m
    and its stop D(0.9) = 0.1 (4 * 0.9 - 1.5 - 0.45) = 0.165 m, leaving exactly 2 m).
    Follower 2 (30 m at equal speeds) is safe at +1 and at +5 (beyond the bound: kept as
    given); follower 3 is the first one again, commanding -1.5, already safe."""
    params = PlatoonParams()
    gap = np.array([[2.26, 30.0, 2.26, 30.0]])
    speed = np.array([[1.0, 15.0, 1.0, 15.0]])
    pred = np.array([[0.0, 15.0, 0.0, 15.0]])
    accel = np.zeros((1, 4))
    u_star = max_safe_command_mps2(gap, speed, pred, accel, params)
    assert u_star[0, 0] == pytest.approx(-1.0, abs=1e-12)
    given = np.array([[0.5, 1.0, -1.5, 5.0]])
    out, changed, correction = filter_commands(given, gap, speed, pred, accel, params)
    np.testing.assert_allclose(out, [[-1.0, 1.0, -1.5, 5.0]], atol=1e-12)
    assert out[0, 1:].tolist() == given[0, 1:].tolist()  # bit for bit
    assert changed.tolist() == [[True, False, False, False]]
    np.testing.assert_allclose(correction, [[1.5, 0.0, 0.0, 0.0]], atol=1e-12)
    # outside the envelope nothing is safe: full braking, counted only if it lowers the command
    out, changed, _ = filter_commands(np.array([[0.0, -2.5, -9.0, 0.0]]),
                                      np.full((1, 4), 1.5), speed, pred, accel, params)
    assert out.tolist() == [[-2.5, -2.5, -9.0, -2.5]]
    assert changed.tolist() == [[True, False, False, True]]


def test_safe_commands_are_returned_unchanged_to_the_last_bit() -> None:
    """Random commands of followers far inside the envelope come back as the same array."""
    rng = np.random.default_rng(3)
    params = PlatoonParams(lag_s=0.3)
    shape = (64, 8)
    speed = rng.uniform(0.0, 30.0, shape)
    given = rng.uniform(-4.0, 4.0, shape)
    out, changed, correction = filter_commands(
        given, speed + 200.0, speed, speed, rng.uniform(-2.5, 2.5, shape), params)
    assert np.array_equal(out, given) and not changed.any() and not correction.any()


@pytest.mark.parametrize("lag_s", [0.0, 0.1, 0.5, 2.0])
def test_the_closed_form_is_the_largest_safe_command(lag_s: float) -> None:
    """``u*`` against a bisection of the margin on random states: inside the bounds it is the
    largest command with ``h(u) >= 0`` (except at the 30 m/s speed clip, where it may be lower:
    conservative), and no state with a safe command in the bounds is given full braking."""
    rng = np.random.default_rng(int(lag_s * 10))
    params, n = PlatoonParams(lag_s=lag_s), 20000
    d = rng.uniform(0.0, 60.0, n)
    v = rng.uniform(0.0, 29.0, n) * (rng.random(n) > 0.1)
    vp = rng.uniform(0.0, 30.0, n) * (rng.random(n) > 0.1)
    a = rng.uniform(-2.5, 2.5, n)

    def margin(u: np.ndarray) -> np.ndarray:
        return next_margin_m(u, d, v, vp, a, params)

    lo, hi = np.full(n, -2.5), np.full(n, 2.5)
    for _ in range(60):
        mid = (lo + hi) / 2
        ok = margin(mid) >= 0
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    feasible = margin(np.full(n, -2.5)) >= -TOL_M
    ref = np.where(margin(np.full(n, 2.5)) >= 0, 2.5, lo)
    got = np.clip(max_safe_command_mps2(d, v, vp, a, params), -2.5, 2.5)
    got_ok = margin(got) >= -TOL_M
    assert np.array_equal(got_ok, feasible)
    np.testing.assert_allclose(got[feasible], ref[feasible], atol=1e-6)


# ------------------------------------------------------------------ in closed loop


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("lag_s", [0.0, 0.5])
def test_an_unsafe_controller_collides_without_the_filter_and_never_with_it(
        scenario: str, lag_s: float) -> None:
    sc, params = make_scenario(scenario), PlatoonParams(lag_s=lag_s)
    raw = rollout_batch(FullThrottle(), sc, 4, SEEDS, params)
    safe = rollout_batch(filtered(FullThrottle()), sc, 4, SEEDS, params)
    assert all(t.collided for t in raw)
    assert not any(t.collided for t in safe)
    assert min(t.gap_m.min() for t in safe) >= SafetyFilterConfig().min_gap_m - TOL_M
    assert all(t.safety_interventions > 0 for t in safe)
    assert all(t.safety_interventions == 0 for t in raw)


def test_interventions_are_what_the_filter_changed() -> None:
    """The counters equal what the trajectory shows: every follower-step whose command differs
    from the constant +2.5, and the sum of how much lower the applied command was."""
    sc = make_scenario("brake-v1")
    traj = rollout(filtered(FullThrottle()), sc, 4, 2000)
    lowered = traj.command_mps2 != 2.5
    assert traj.safety_interventions == int(lowered.sum()) > 0
    assert traj.safety_correction_mps2 == pytest.approx(
        float((2.5 - np.clip(traj.command_mps2, -2.5, 2.5)).sum()), rel=1e-12)
    # a command above the bound counts against what the env would apply (2.5), not 4.0
    over = rollout(filtered(FullThrottle(4.0)), sc, 4, 2000)
    assert over.safety_interventions == traj.safety_interventions
    assert over.safety_correction_mps2 == pytest.approx(traj.safety_correction_mps2, rel=1e-12)


def _exact_barrier_m(state: PlatoonState, params: PlatoonParams, d_min: float) -> np.ndarray:
    """The smallest gap minus ``d_min`` along the full-braking plan of each follower against a
    predecessor braking at 2.5 m/s^2 from now on, simulated step by step (not the closed form).
    """
    own, _ = _simulated_stop_m(state.speed_mps, state.realised_accel_mps2, params, 2.5)
    pred, _ = _simulated_stop_m(state.pred_speed_mps, np.full(state.speed_mps.shape, -2.5),
                                PlatoonParams(), 2.5, np.inf)  # at most 2.5 m/s^2, no lag
    t = max(len(own), len(pred))
    own = np.concatenate([own, np.repeat(own[-1:], t - len(own), 0)])
    pred = np.concatenate([pred, np.repeat(pred[-1:], t - len(pred), 0)])
    gaps = state.gap_m + pred - own
    return np.minimum(state.gap_m, gaps.min(axis=0)) - d_min


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("lag_s", [0.0, 0.5])
def test_the_barrier_stays_nonnegative_in_closed_loop(scenario: str, lag_s: float) -> None:
    """The derivation's invariant: starting with ``h >= 0``, the filtered unsafe controller
    keeps ``h >= 0`` at every step, for the closed form (exact without lag) and for the gap
    along a simulated full-braking plan (with lag too); the closed form never exceeds it."""
    sc, params, config = make_scenario(scenario), PlatoonParams(lag_s=lag_s), SafetyFilterConfig()
    seeds = np.array(SEEDS[:4])
    env = PlatoonEnv(sc, 4, params)
    ctrl = filtered(FullThrottle())
    reset_controller(ctrl, EpisodeContext(sc, 4, seeds, params))
    env.reset(seeds)
    s = env.state
    assert s is not None

    def closed_form() -> np.ndarray:
        return barrier_m(s.gap_m, s.speed_mps, s.pred_speed_mps, s.realised_accel_mps2,
                         params, config)

    assert closed_form().min() >= 0
    low_closed, low_exact = np.inf, np.inf
    for t in range(sc.n_steps):
        env.step(ctrl.act(s, None))
        h = closed_form()
        low_closed = min(low_closed, float(h.min()))
        if t % 20 == 0 or h.min() < 2.0:
            exact = _exact_barrier_m(s, params, config.min_gap_m)
            assert np.all(h <= exact + TOL_M)
            low_exact = min(low_exact, float(exact.min()))
    assert not s.collided.any()
    assert low_exact >= -TOL_M
    if lag_s == 0:
        assert low_closed >= -TOL_M
    assert ctrl.intervention_totals()[0].min() > 0  # the filter was binding, not idle


def test_a_batch_gives_each_episode_its_run_alone() -> None:
    """Batch invariance: the filter is elementwise and counts only running episodes."""
    sc = make_scenario("catchup-v1")
    batch = rollout_batch(filtered(FullThrottle()), sc, 4, SEEDS[:5])
    for seed, got in zip(SEEDS[:5], batch, strict=True):
        alone = rollout(filtered(FullThrottle()), sc, 4, seed)
        assert np.array_equal(got.gap_m, alone.gap_m)
        assert got.safety_interventions == alone.safety_interventions
        assert got.safety_correction_mps2 == alone.safety_correction_mps2


# ------------------------------------------------------------------ registry, CLI, runs.csv


def test_spec_strings_parse_and_label() -> None:
    assert parse_controller_list("safe:bdc:scenario=catchup-v1,seed=1,cacc,safe:mpc-qp") == [
        ("safe:bdc", {"scenario": "catchup-v1", "seed": "1"}), ("cacc", {}), ("safe:mpc-qp", {})]
    assert parse_controller_list("safe:cacc[time_gap_s=0.6]") == [
        ("safe:cacc", {"time_gap_s": "0.6"})]
    assert controller_label("safe:cacc", canonical_options(
        "safe:cacc", {"time_gap_s": "0.5", "safe_min_gap_m": "2"})) == "safe:cacc"
    label = controller_label("safe:cacc", canonical_options(
        "safe:cacc", {"time_gap_s": "0.6", "safe_min_gap_m": "3"}))
    assert label == "safe:cacc[safe_min_gap_m=3,time_gap_s=0.6]"
    assert parse_controller_list(label) == [
        ("safe:cacc", {"safe_min_gap_m": "3", "time_gap_s": "0.6"})]
    spec = resolve("safe:mpc-qp")
    assert (spec.family, spec.v2v) == ("mpc", CONTROLLERS["mpc-qp"].v2v)
    ctrl = make_controller("safe:cacc", time_gap_s="0.6", safe_min_gap_m="3")
    assert ctrl.inner.config.time_gap_s == 0.6 and ctrl.config.min_gap_m == 3.0
    assert ctrl.options == {**ctrl.inner.options, "safe_min_gap_m": 3.0}


@pytest.mark.parametrize("name", [n for n, spec in CONTROLLERS.items()
                                  if spec.available and spec.family != "data"
                                  and not runs_inside_simulator(spec)])
def test_every_registered_controller_filtered_keeps_the_harness_contract(name: str) -> None:
    """The registry drives the matrix: every control law, optimiser and learned policy (the
    paper's OVM-gain policies included: their actions become acceleration commands) runs
    behind the filter with the harness's contract (shape, finiteness, reruns, V2V)."""
    check_controller(f"safe:{name}")
    assert resolve(f"safe:{name}").family == CONTROLLERS[name].family


BAD_SPECS = {
    "safe:": "names no controller",
    "safe:nonexistent": "unknown controller 'nonexistent'",
    "safe:safe:cacc": "wraps a controller once",
    "safe:openacc-real": "not a control law",
    "safe:cacc:safe_min_gap_m=0.5": "below the collision gap",
    "safe:cacc:safe_min_gap_m=-1": "safe_min_gap_m must be a positive",
    "safe:cacc:safe_pred_brake_mps2=1": "below the follower's own full braking",
    "safe:cacc:safe_min_gap_m=1e308": "at most 100",  # overflowed, and was stored as ok
    "safe:cacc:safe_pred_brake_mps2=1e308": "at most 10",
    "safe:cacc:safe_bogus=1": "no option 'safe_bogus'",
    "safe:cacc:time_gap_s=-1": "time_gap_s",
    "safe:bdc:seed=7": "no trained bdc policy",
}


@pytest.mark.parametrize("spec", sorted(BAD_SPECS))
def test_bad_specs_exit_2_with_a_message(spec: str, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    code = cli(["run", "--controllers", spec, "--scenarios", "catchup-v1", "--vehicles", "4",
                "--episodes", "1", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert BAD_SPECS[spec] in err
    assert "Traceback" not in err
    assert not (out / "store.sqlite").exists()


def test_the_cli_reports_interventions_and_matches_the_unfiltered_run(tmp_path: Path) -> None:
    """``cacc`` never comes near the envelope on catchup-v1 seeds 2000 and 2010 nor on
    brake-v1, so ``safe:cacc`` is ``cacc`` in every column but its name and times; ``acc``
    does on brake-v1 (1.31 m at least), so ``safe:acc`` intervenes there and keeps 2 m."""
    out = tmp_path / "run"
    assert cli(["run", "--controllers", "cacc,safe:cacc,acc,safe:acc", "--scenarios",
                "catchup-v1,brake-v1", "--vehicles", "4", "--seeds", "2000,2010", "--out",
                str(out), "--quiet"]) == 0
    runs = pd.read_csv(out / "runs.csv")
    timing = ["compute_ms_p50", "compute_ms_p95", "compute_ms_p99", "compute_ms_first", "wall_s"]
    same = [c for c in runs.columns if c not in {"controller", "controller_name", *timing}]

    def rows(label: str) -> pd.DataFrame:
        return runs[runs["controller"] == label].reset_index(drop=True)[same]

    pd.testing.assert_frame_equal(rows("safe:cacc"), rows("cacc"), check_exact=True)
    assert (runs["safety_interventions"].loc[runs["controller"] != "safe:acc"] == 0).all()
    acc, safe_acc = rows("acc"), rows("safe:acc")
    brake = safe_acc["scenario"] == "brake-v1"
    assert (acc.loc[brake, "min_gap_m"] < 2).all()
    assert (safe_acc.loc[brake, "min_gap_m"] >= 2).all()
    assert (safe_acc.loc[brake, "safety_interventions"] > 0).all()
    assert (safe_acc.loc[brake, "safety_correction_mps2"] > 0).all()
    assert not runs["collision"].any()
    assert (out / "leaderboard.csv").exists()
    before = (out / "runs.csv").read_bytes()
    assert cli(["run", "--controllers", "cacc,safe:cacc,acc,safe:acc", "--scenarios",
                "catchup-v1,brake-v1", "--vehicles", "4", "--seeds", "2000,2010", "--out",
                str(out), "--quiet", "--resume"]) == 0  # the stored labels read back
    assert (out / "runs.csv").read_bytes() == before


def test_same_seed_same_numbers() -> None:
    key = build_sweep([("safe:acc", {})], ["brake-v1"], [4], [2000, 2010])
    first = [execute_run(k) for k in key]
    again = execute_batch(key)
    for a, b in zip(first, again, strict=True):
        for col in ("reward", "min_gap_m", "safety_interventions", "safety_correction_mps2",
                    "energy_kwh"):
            assert a[col] == b[col], col
    assert first[0]["safety_interventions"] > 0


def test_a_store_written_before_the_filter_reads_as_unfiltered() -> None:
    """Records without the two columns (older stores) read 0 for a finished run, nothing for a
    failed one."""
    base = {"controller": "cacc", "name": "cacc", "options": json.dumps({}), "family": "linear",
            "scenario": "catchup-v1", "n_vehicles": 4, "seed": 2000, "comm_delay_s": 0.0,
            "packet_loss": 0.0, "lag_s": 0.0}
    frame = runs_frame([{**base, "status": "ok"}, {**base, "seed": 2010, "status": "failed"}])
    assert frame["safety_interventions"].tolist()[0] == 0.0
    assert frame["safety_correction_mps2"].tolist()[0] == 0.0
    assert frame["safety_interventions"].isna().tolist() == [False, True]


def test_trajectory_defaults_are_unfiltered() -> None:
    """A trajectory built without the filter's fields (a recorded platoon) has none."""
    fields = Trajectory.__dataclass_fields__
    assert fields["safety_interventions"].default == 0
    assert fields["safety_correction_mps2"].default == 0.0
