"""Thin adapters for outside libraries: a PettingZoo ``ParallelEnv`` and a Gymnasium view.

Both wrap one episode (B = 1) of :class:`envs.platoon.PlatoonEnv`, in either action mode
(:data:`envs.accel_mode.ACTION_MODES`): ``ovm-gain``, the MARL interface of the published
benchmark (4 discrete actions per follower choosing OVM gains, 15-number observations: own, front
and rear vehicle blocks, zero-padded), or ``accel`` (a Box acceleration command per follower in
the MPC's bounds, 12-number observations with what V2V delivers through the channel's delay and
loss). The reward is the paper's. Training inside cacc-bench uses the batched arrays directly;
these are for outside MARL libraries.

They keep the command line's rules: the scenario and its options go through
:func:`envs.scenarios.make_scenario`, a V2V delay must be a whole number of steps (as ``run
--comm-delay``), a reset seed lies in 0..:data:`infra.limits.MAX_SEED` (as ``run --seeds``), and an
action of the wrong shape, not finite, or a non-integer or out-of-range gain index is refused
(:func:`envs.platoon.check_actions`); each with a ConfigError (a ValueError) saying what is
expected. On a mixed string (the scenario options ``humans``, ``cav_fraction``, ``cavs``) every
follower stays an agent, and a human seat's action is ignored (its model drives it); a string
with no automated follower is refused.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from envs.channel import ChannelConfig
from envs.params import OVM_ACTIONS, PlatoonParams
from envs.platoon import PlatoonEnv, StepResult, check_actions
from envs.scenarios import make_scenario
from infra.errors import ConfigError
from infra.limits import MAX_SEED, check_seeds, check_whole_steps

#: Observation bound: no 60 s episode gets near it (a normalised gap of 1e4 is 200 km).
OBS_BOUND = 1e4


def _draw_seed(rng: np.random.Generator) -> int:
    return int(rng.integers(0, MAX_SEED))


def _check_seed(seed: Any) -> int:
    """``seed`` if it is an episode seed by the command line's rule (``run --seeds``)."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise ConfigError(f"seed must be a whole number in 0..{MAX_SEED}, got {seed!r}")
    return check_seeds([int(seed)], "seed")[0]


def _reset(env: PlatoonEnv, episode_seed: int, options: dict[str, Any] | None) -> np.ndarray:
    """Observations ``(1, N, obs_dim)`` of a new episode (``options``: ``perturbation``)."""
    if options is not None and not isinstance(options, dict):
        raise ConfigError(f"options must be a dict (perturbation: U in [0, 1]), got {options!r}")
    obs = env.reset([episode_seed], perturbation=(options or {}).get("perturbation"))
    assert obs is not None
    return obs


class _PlatoonAdapter:
    """What both adapters share: the wrapped env (B = 1), built by the command line's rules
    (parameters: :class:`PlatoonParallelEnv`), and its step."""

    def __init__(
        self,
        scenario: str = "catchup-v1",
        n_vehicles: int | None = 8,
        params: PlatoonParams = PlatoonParams(),
        training: bool = False,
        collision_mode: str = "terminate",
        action_mode: str = "ovm-gain",
        comm_delay_s: float = 0.0,
        packet_loss: float = 0.0,
        **scenario_options: Any,
    ) -> None:
        sc = make_scenario(scenario, **scenario_options)  # one rule with every --scenarios
        channel = ChannelConfig(comm_delay_s, packet_loss, params.dt_s)
        check_whole_steps(channel.delay_s, "comm_delay_s", params.dt_s)  # as run --comm-delay
        self.env = PlatoonEnv(sc, sc.default_vehicles if n_vehicles is None else n_vehicles,
                              params, training=training, collision_mode=collision_mode,
                              observe=True, action_mode=action_mode, channel=channel)
        if sc.arrangement(self.env.n_vehicles).n_automated == 0:  # as run refuses a controller
            raise ConfigError(f"{sc.label} with N = {self.env.n_vehicles} has no automated "
                              "follower, so no action would act; give the scenario automated "
                              "followers (cav_fraction > 0, cavs >= 1)")
        if self.env.action_mode != "accel" and (channel.delay_s or channel.packet_loss):
            raise ConfigError("comm_delay_s and packet_loss act on the V2V messages of the accel "
                              "mode; the ovm-gain observations are exact (published): give "
                              "action_mode='accel' or leave them at 0")
        self.action_mode = action_mode
        self._spaces()

    def _spaces(self) -> None:
        """Set the observation and action spaces."""

    def _step(self, actions: np.ndarray) -> tuple[StepResult, bool, bool]:
        """One step of checked actions ``(1, N)``: the result, collided, over."""
        env = self.env
        res = env.step(actions) if self.action_mode == "accel" else env.step_actions(actions)
        return res, bool(res.collided[0]), bool(res.done[0])


def _accel_space(params: PlatoonParams, shape: tuple[int, ...]) -> spaces.Box:
    """The acceleration command's Box: the MPC's input bounds."""
    return spaces.Box(np.float32(params.accel_min_mps2), np.float32(params.accel_max_mps2),
                      shape, np.float32)


class PlatoonParallelEnv(_PlatoonAdapter, ParallelEnv):
    """PettingZoo parallel env: agents ``follower_1 .. follower_N``.

    Parameters
    ----------
    scenario : str
        Scenario id (default ``catchup-v1``).
    n_vehicles : int or None
        Followers N (None: the scenario's default, as its registered Gymnasium id).
    params : PlatoonParams
        Physics (``lag_s``).
    training : bool
        Reward in training form (with the safety term).
    collision_mode : str
        ``terminate`` (default) or ``published``.
    action_mode : str
        ``ovm-gain`` (default, published: ``Discrete(4)``) or ``accel`` (``Box(accel_min,
        accel_max, (1,))`` m/s^2).
    comm_delay_s, packet_loss : float
        V2V delay (whole steps of ``params.dt_s``) and loss of the ``accel`` mode's messages.
    **scenario_options
        Options of the scenario (``amplitude_mps=2`` of ``sine-v1``), checked as the command
        line's ``--scenarios sine-v1:amplitude_mps=2``.

    Notes
    -----
    ``reset(seed=s)`` uses ``s`` (0..:data:`infra.limits.MAX_SEED`) as the episode seed (published
    seeding of the perturbation); without a seed, an episode seed is drawn from the adapter's own
    generator. ``options`` may hold ``perturbation`` (explicit U in [0, 1]); other keys are
    ignored. ``step`` takes one action for every agent, in its action space (a bare number
    for the ``accel`` Box too). The episode's time limit is a truncation, a collision a
    termination.
    """

    metadata = {"name": "cacc_platoon_v1", "render_modes": [], "is_parallelizable": True}

    def _spaces(self) -> None:
        self.possible_agents = [f"follower_{i}" for i in range(1, self.env.n_vehicles + 1)]
        self.agents: list[str] = []
        self.render_mode = None
        self._obs_space = spaces.Box(-OBS_BOUND, OBS_BOUND, (self.env.obs_dim,), np.float32)
        self._act_space: spaces.Space = (
            _accel_space(self.env.params, (1,)) if self.action_mode == "accel"
            else spaces.Discrete(len(OVM_ACTIONS)))
        self._rng = np.random.Generator(np.random.PCG64())
        self.episode_seed: int | None = None

    def observation_space(self, agent: str) -> spaces.Space:
        """Box of 15 floats (own, front, rear blocks; missing neighbours are zeros), or of 12 in
        the ``accel`` mode (:data:`envs.accel_mode.ACCEL_OBS_NAMES`)."""
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Space:
        """Discrete(4): index -> (alpha, beta) of the OVM law; or the acceleration's Box."""
        return self._act_space

    def _obs_dict(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {a: obs[0, i].copy() for i, a in enumerate(self.agents)}

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        if seed is not None:
            self.episode_seed = _check_seed(seed)
            self._rng = np.random.Generator(np.random.PCG64(self.episode_seed))
        else:
            self.episode_seed = _draw_seed(self._rng)
        obs = _reset(self.env, self.episode_seed, options)
        self.agents = list(self.possible_agents)
        return self._obs_dict(obs), {a: {} for a in self.agents}

    def _actions(self, actions: dict[str, Any]) -> np.ndarray:
        """The ``(1, N)`` actions of ``actions`` (one per agent, each in its action space)."""
        given = actions if isinstance(actions, dict) else {}
        missing = [ag for ag in self.agents if ag not in given]
        unknown = [k for k in given if k not in self.agents]
        if missing or unknown:
            raise ConfigError(
                f"actions must map each agent ({self.agents[0]} .. {self.agents[-1]}) to its "
                f"action; " + (f"missing {missing[0]}" if missing else f"unknown {unknown[0]!r}"))
        accel, vals = self.action_mode == "accel", []
        for ag in self.possible_agents:
            v = given[ag]
            if accel and isinstance(v, int | float | np.number):  # a bare number for the Box
                v = [v]
            vals.append(check_actions(v, (1,) if accel else (), self.env.params, not accel,
                                      f"the action of {ag}"))
        return np.stack(vals).astype(np.float64 if accel else np.int64).reshape(1, -1)

    def step(self, actions: dict[str, Any]) -> tuple[
        dict[str, np.ndarray], dict[str, float], dict[str, bool], dict[str, bool], dict[str, dict]
    ]:
        if not self.agents:
            raise RuntimeError("episode over: call reset()")
        res, collided, over = self._step(self._actions(actions))
        assert res.observation is not None
        obs = self._obs_dict(res.observation)
        rewards = {ag: float(res.reward[0, i]) for i, ag in enumerate(self.agents)}
        terms = {ag: collided and over for ag in self.agents}
        truncs = {ag: over and not collided for ag in self.agents}
        infos = {
            ag: {"power_kw": float(res.power_kw[0, i]), "collision": collided}
            for i, ag in enumerate(self.agents)
        }
        if over:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def render(self) -> None:
        return None

    def close(self) -> None:
        return None


class PlatoonGymEnv(_PlatoonAdapter, gymnasium.Env):
    """Gymnasium single-agent (centralised) view: one agent chooses every follower's action.

    Observation ``(N, 15)`` floats and action ``MultiDiscrete([4] * N)`` (``ovm-gain``), or
    ``(N, 12)`` floats and ``Box(accel_min, accel_max, (N,))`` m/s^2 (``accel``); reward = sum
    over agents. Parameters and rules as :class:`PlatoonParallelEnv`; ``step`` takes an action
    of the action space's shape ``(N,)``.
    """

    metadata = {"render_modes": []}

    def _spaces(self) -> None:
        self.n_vehicles = n = self.env.n_vehicles
        self.observation_space = spaces.Box(-OBS_BOUND, OBS_BOUND, (n, self.env.obs_dim),
                                            np.float32)
        self.action_space: spaces.Space = (
            _accel_space(self.env.params, (n,)) if self.action_mode == "accel"
            else spaces.MultiDiscrete([len(OVM_ACTIONS)] * n))

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict]:
        seed = None if seed is None else _check_seed(seed)
        super().reset(seed=seed)
        episode_seed = seed if seed is not None else _draw_seed(self.np_random)
        return _reset(self.env, episode_seed, options)[0].copy(), {"episode_seed": episode_seed}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        accel = self.action_mode == "accel"
        a = check_actions(action, (self.n_vehicles,), self.env.params, not accel, "action")
        res, collided, over = self._step(a.astype(np.float64 if accel else np.int64)
                                         .reshape(1, -1))
        assert res.observation is not None
        info = {"power_kw": res.power_kw[0].copy(), "collision": collided}
        return (res.observation[0].copy(), float(res.reward[0].sum()), collided and over,
                over and not collided, info)


#: Gymnasium namespace of the registered scenarios: ``gymnasium.make("cacc_bench/catchup-v1")``.
GYM_NAMESPACE = "cacc_bench"
#: Namespace of the same scenarios in the ``accel`` action mode:
#: ``gymnasium.make("cacc_bench_accel/catchup-v1")``.
GYM_ACCEL_NAMESPACE = "cacc_bench_accel"


def register_gymnasium() -> list[str]:
    """Register every scenario as ``cacc_bench/<scenario id>`` (the Gymnasium view,
    :class:`PlatoonGymEnv`, at the scenario's default N) and as ``cacc_bench_accel/<scenario
    id>`` (the same in the ``accel`` action mode); idempotent. ``gymnasium.make`` passes its
    keyword arguments on: the adapter's parameters and the scenario's options
    (``gymnasium.make("cacc_bench/sine-v1", amplitude_mps=2)``).

    Runs when this module is imported, so ``gymnasium.make("envs.adapters:cacc_bench/catchup-v1",
    n_vehicles=4)`` works in a fresh interpreter (Gymnasium imports the module before the id).

    Returns
    -------
    list[str]
        The registered ids.
    """
    from envs.scenarios import list_scenarios

    ids = []
    for spec in list_scenarios():
        for namespace, mode in ((GYM_NAMESPACE, "ovm-gain"), (GYM_ACCEL_NAMESPACE, "accel")):
            env_id = f"{namespace}/{spec.id}"
            if env_id not in gymnasium.registry:
                gymnasium.register(
                    env_id, entry_point="envs.adapters:PlatoonGymEnv",
                    kwargs={"scenario": spec.id, "n_vehicles": None, "action_mode": mode},
                    disable_env_checker=False,
                )
            ids.append(env_id)
    return ids


register_gymnasium()
