"""The acceleration action mode: the same platoon, a continuous command, V2V in the observation."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test

from envs.accel_mode import ACCEL_OBS_DIM, ACCEL_OBS_NAMES, ACTION_MODES
from envs.adapters import PlatoonGymEnv, PlatoonParallelEnv
from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import make_scenario
from infra.errors import ConfigError


def test_the_modes_and_the_observation_names() -> None:
    assert ACTION_MODES == ("ovm-gain", "accel")
    assert len(ACCEL_OBS_NAMES) == ACCEL_OBS_DIM == 12
    with pytest.raises(ConfigError, match="unknown action mode 'gains'"):
        PlatoonEnv("catchup-v1", 4, action_mode="gains")


def test_the_published_mode_is_untouched_by_the_accel_mode() -> None:
    """The same OVM commands through ``step`` give the same physics, reward and power in both
    modes; only the observation differs (and the published mode stays the default)."""
    a = PlatoonEnv("catchup-v1", 6)
    b = PlatoonEnv("catchup-v1", 6, action_mode="accel")
    assert a.action_mode == "ovm-gain" and a.obs_dim == 15 and b.obs_dim == 12
    oa, ob = a.reset([3, 4]), b.reset([3, 4])
    assert oa is not None and ob is not None and oa.shape == (2, 6, 15) and ob.shape == (2, 6, 12)
    rng = np.random.default_rng(0)
    for _ in range(50):
        u = rng.uniform(-3, 3, (2, 6))
        ra, rb = a.step(u), b.step(u)
        for field in ("reward", "power_kw", "applied_accel_mps2", "tracking_reward", "done"):
            np.testing.assert_array_equal(getattr(ra, field), getattr(rb, field))
    with pytest.raises(ConfigError, match="accel mode"):
        b.step_actions(np.zeros((2, 6), dtype=int))


def test_the_observation_columns_by_hand() -> None:
    """Column by column against the state, after one step of known commands (no delay)."""
    env = PlatoonEnv("slowdown-v1", 3, action_mode="accel", dtype=np.float64)
    env.reset([7])
    s = env.state
    assert s is not None
    u = np.array([[1.0, -0.5, 9.0]])  # the last one beyond the bound: V2V carries what is applied
    lead_a, lead_v = s.leader_accel_now_mps2.copy(), s.leader_speed_now_mps.copy()
    res = env.step(u)
    obs = res.observation
    assert obs is not None
    p, sc = env.params, env.scenario
    col = {name: obs[0, :, k] for k, name in enumerate(ACCEL_OBS_NAMES)}
    np.testing.assert_allclose(col["speed_error"], (s.speed_mps[0] - sc.target_speed_mps)
                               / sc.target_speed_mps)
    np.testing.assert_allclose(col["realised_accel"], s.realised_accel_mps2[0] / 2.5)
    np.testing.assert_allclose(col["applied_accel"], s.applied_accel_mps2[0] / 2.5)
    np.testing.assert_allclose(col["pred_command"], [lead_a[0] / 2.5, 1.0 / 2.5, -0.5 / 2.5])
    np.testing.assert_allclose(col["leader_accel"], lead_a[0] / 2.5)
    np.testing.assert_allclose(col["leader_speed_error"],
                               (lead_v[0] - sc.target_speed_mps) / sc.target_speed_mps)
    np.testing.assert_array_equal(col["is_first"], [1, 0, 0])
    np.testing.assert_array_equal(col["is_last"], [0, 0, 1])
    np.testing.assert_allclose(col["position"], [1 / 3, 2 / 3, 1])
    dv = s.pred_speed_mps[0] - s.speed_mps[0]
    np.testing.assert_allclose(col["gap_error"], (s.gap_m[0] + dv * p.dt_s - sc.target_gap_m)
                               / sc.target_gap_m)


def test_delay_and_loss_reach_the_observation_as_they_reach_cacc() -> None:
    """A 0.2 s delay shifts what V2V delivers by two steps; with loss a follower holds its last
    message; and the losses are the episode's own (the same alone and in a batch)."""
    cmds = np.linspace(-1, 1, 4 * 30).reshape(30, 1, 4)

    def run(channel: ChannelConfig, seeds: list[int]) -> np.ndarray:
        env = PlatoonEnv("catchup-v1", 4, action_mode="accel", channel=channel,
                         dtype=np.float64)
        env.reset(seeds)
        seen = []
        for k in range(30):
            res = env.step(np.repeat(cmds[k], len(seeds), axis=0))
            assert res.observation is not None
            seen.append(res.observation[:, :, 6] * 2.5)
        return np.array(seen)  # (T, B, N)

    ideal = run(ChannelConfig(), [5])
    late = run(ChannelConfig(delay_s=0.2), [5])
    np.testing.assert_allclose(ideal[:, 0, 1:], cmds[:, 0, :3])
    np.testing.assert_allclose(late[2:, 0, 1:], cmds[:-2, 0, :3])
    np.testing.assert_array_equal(late[:2, 0, 1:], 0.0)
    lossy = run(ChannelConfig(packet_loss=0.5), [5, 6])
    alone = run(ChannelConfig(packet_loss=0.5), [6])
    np.testing.assert_array_equal(lossy[:, 1], alone[:, 0])
    held = lossy[1:, 0, 1:] == lossy[:-1, 0, 1:]
    assert 0.3 < held.mean() < 0.7


class _CACCFromObservation:
    """Ploeg's CACC computed from nothing but the accel mode's observation (float64)."""

    def __init__(self, scenario: str, n: int, h: float = 0.5, kp: float = 0.2, kd: float = 0.7):
        sc = make_scenario(scenario)
        self.d, self.v, self.h, self.kp, self.kd = (sc.target_gap_m, sc.target_speed_mps, h,
                                                    kp, kd)
        self.r = self.d - h * self.v
        self.alpha = np.exp(-0.1 / h)
        self.c = np.zeros((1, n))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        v = obs[..., 0] * self.v + self.v
        dv = obs[..., 1] * 5.0
        gap = obs[..., 3] * self.d + self.d - dv * 0.1
        w = self.kp * (gap - self.r - self.h * v) + self.kd * (dv - self.h * obs[..., 5] * 2.5)
        w += obs[..., 6] * 2.5
        self.c = np.clip(self.alpha * self.c + (1 - self.alpha) * w, -2.5, 2.5)
        return self.c.copy()


@pytest.mark.parametrize("channel", [ChannelConfig(), ChannelConfig(delay_s=0.2),
                                     ChannelConfig(delay_s=0.2, packet_loss=0.3)])
def test_cacc_written_on_the_observation_drives_the_platoon_as_the_cacc_controller(
        channel: ChannelConfig, monkeypatch: pytest.MonkeyPatch) -> None:
    """The accel mode gives a policy exactly what ``cacc`` uses: the CACC law computed from the
    observation alone reproduces the registered ``cacc`` controller's run through the harness's
    own closed loop (a reference written separately), delay and loss included (the predecessor
    channel named as cacc's, so both draw the same losses)."""
    import envs.accel_mode
    from benchmark.rollout import rollout
    from controllers.registry import make_controller

    monkeypatch.setattr(envs.accel_mode, "PRED_MESSAGE", ("cacc_u", 1))
    sc = make_scenario("catchup-v1")
    ref = rollout(make_controller("cacc"), sc, 4, 2000, PlatoonParams(), channel)
    env = PlatoonEnv(sc, 4, action_mode="accel", channel=channel, dtype=np.float64)
    obs = env.reset([2000])
    law = _CACCFromObservation("catchup-v1", 4)
    gaps = [env.state.gap_m[0].copy()]  # type: ignore[union-attr]
    for _ in range(ref.steps):
        res = env.step(law(obs))
        obs = res.observation
        gaps.append(env.state.gap_m[0].copy())  # type: ignore[union-attr]
    np.testing.assert_allclose(np.array(gaps), ref.gap_m, atol=1e-8)


@pytest.mark.parametrize(("scenario", "n", "seed", "exact", "lag_s"), [
    ("catchup-v1", 5, 2001, False, 0.0), ("slowdown-v1", 5, 2001, False, 0.0),
    ("openacc-s-v1", 5, 2001, False, 0.0), ("slowdown-v1", 8, 2000, True, 0.0),
    ("slowdown-v1", 8, 3, True, 0.0), ("catchup-v1", 8, 2001, True, 0.0),
    ("slowdown-v1", 8, 2000, True, 0.2)])
def test_memoryless_cacc_law_of_the_observation_is_the_cacc_controller(
        scenario: str, n: int, seed: int, exact: bool, lag_s: float,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """:func:`envs.accel_mode.cacc_from_observation` (the prior of the residual learners) reads
    its filter state from the observation's last applied command: it drives the platoon as the
    registered ``cacc`` controller does, with 0.2 s delay and 30 % loss; given the state's
    unclipped relative speed and last command, also where the speed bound acts (slowdown-v1
    seeds whose initial speed is above it)."""
    import envs.accel_mode
    from benchmark.rollout import rollout
    from controllers.registry import make_controller
    from envs.accel_mode import cacc_from_observation

    monkeypatch.setattr(envs.accel_mode, "PRED_MESSAGE", ("cacc_u", 1))
    channel = ChannelConfig(delay_s=0.2, packet_loss=0.3)
    sc = make_scenario(scenario)
    params = PlatoonParams(lag_s=lag_s)  # with lag the last command is not the realised one
    ref = rollout(make_controller("cacc"), sc, n, seed, params, channel)
    env = PlatoonEnv(sc, n, params, action_mode="accel", channel=channel, dtype=np.float64)
    obs = env.reset([seed])
    gaps = [env.state.gap_m[0].copy()]  # type: ignore[union-attr]
    for _ in range(ref.steps):
        st = env.state
        assert st is not None
        exact_state = {"relative_speed_mps": st.pred_speed_mps - st.speed_mps,
                       "last_command_mps2": st.command_mps2} if exact else {}
        res = env.step(cacc_from_observation(obs, sc.target_gap_m, sc.target_speed_mps,
                                             params, **exact_state))
        obs = res.observation
        gaps.append(env.state.gap_m[0].copy())  # type: ignore[union-attr]
    np.testing.assert_allclose(np.array(gaps), ref.gap_m, atol=1e-8)


def test_the_observation_alone_is_not_cacc_where_the_speed_bound_acts() -> None:
    """Why the prior reads the state: on a slowdown-v1 episode that starts above the speed bound
    (seed 2000, 31.1 m/s) the applied acceleration is not the command, and the law of the
    observation alone drifts from the ``cacc`` controller's run by a metre."""
    from benchmark.rollout import rollout
    from controllers.registry import make_controller
    from envs.accel_mode import cacc_from_observation

    sc = make_scenario("slowdown-v1")
    ref = rollout(make_controller("cacc"), sc, 8, 2000, PlatoonParams(), ChannelConfig())
    env = PlatoonEnv(sc, 8, action_mode="accel", dtype=np.float64)
    obs = env.reset([2000])
    assert env.state is not None
    assert env.state.speed_mps.min() > PlatoonParams().speed_max_mps
    gaps = [env.state.gap_m[0].copy()]
    for _ in range(ref.steps):
        obs = env.step(cacc_from_observation(obs, sc.target_gap_m, sc.target_speed_mps)).observation
        gaps.append(env.state.gap_m[0].copy())
    assert np.abs(np.array(gaps) - ref.gap_m).max() > 0.5


def test_pettingzoo_parallel_api_in_the_accel_mode() -> None:
    env = PlatoonParallelEnv("catchup-v1", 4, action_mode="accel", comm_delay_s=0.2,
                             packet_loss=0.3)
    assert env.action_space("follower_1").shape == (1,)
    assert env.action_space("follower_1").low[0] == -2.5  # type: ignore[attr-defined]
    assert env.observation_space("follower_1").shape == (12,)
    parallel_api_test(env, num_cycles=700)
    parallel_seed_test(lambda: PlatoonParallelEnv("slowdown-v1", 4, action_mode="accel",
                                                  packet_loss=0.3))


def test_gymnasium_checker_in_the_accel_mode() -> None:
    env = PlatoonGymEnv("catchup-v1", 4, action_mode="accel", comm_delay_s=0.1)
    assert env.action_space.shape == (4,)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # the one recommendation it makes: a [-1, 1] Box; ours is in m/s^2, the MPC's bounds
        warnings.filterwarnings("ignore", message=".*symmetric and normalized")
        check_env(env, skip_render_check=True)


@pytest.mark.parametrize(("prior", "exact"), [("cacc-exact", True), ("cacc", False)])
def test_a_zero_residual_on_the_exact_prior_is_the_cacc_controller(prior: str, exact: bool) -> None:
    """``PPOConfig.prior = "cacc-exact"``: with a zero residual the learner's command is the
    ``cacc`` controller's on slowdown-v1 seed 2000 (above the speed bound at the start); the
    shipped ``"cacc"`` prior, the observation's law alone, is not there."""
    import torch

    from benchmark.rollout import rollout
    from controllers.registry import make_controller
    from marl.acting import agent_inputs, to_command
    from marl.ppo_nets import PPOConfig, SharedActor

    params = PlatoonParams()
    actor = SharedActor(PPOConfig(action_mode="accel", prior=prior), params, 0)
    sc = make_scenario("slowdown-v1")
    ref = rollout(make_controller("cacc"), sc, 8, 2000, params, ChannelConfig())
    env = PlatoonEnv(sc, 8, params, action_mode="accel", dtype=np.float64)
    obs = env.reset([2000])
    gaps = [env.state.gap_m[0].copy()]  # type: ignore[union-attr]
    for _ in range(ref.steps):
        x = agent_inputs(obs, "accel")
        obs = env.step(to_command(actor, torch.zeros(x.shape[:2]), env.state, params, x,
                                  (sc.target_gap_m, sc.target_speed_mps))).observation
        gaps.append(env.state.gap_m[0].copy())  # type: ignore[union-attr]
    error = np.abs(np.array(gaps) - ref.gap_m).max()
    assert (error < 1e-4) if exact else (error > 0.5)
