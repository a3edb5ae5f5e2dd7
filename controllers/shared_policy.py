"""Shared-policy learners (IPPO, MAPPO) as controllers, at any platoon size.

``SharedPolicyController(algo)`` loads ``<algo>__<scenario>__n<vehicles>__s<seed>.pt`` (the
checkpoint trained with ``vehicles`` followers, 8 by default) and drives any N from 2 to 64 with
it: every follower runs the same actor on its own observation, whose position features (first,
last, ``i / N``) tell it where it is. In the ``accel`` action mode the command is the actor's
acceleration; in ``ovm-gain`` its OVM-gain index becomes the published OVM command.

Everything the policy receives from another vehicle goes through the run's channels (declared as
:class:`controllers.base.Message`, so delay and loss act on it and its bits are counted):
``accel`` mode, the predecessor's command and the leader's planned acceleration and speed with
``cacc``'s timing (:mod:`envs.accel_mode`); ``ovm-gain`` mode, each follower's 5-float vehicle
block to both neighbours (as the paper's policies). Sampled actions (``mode=sampled``, the
default: the policy as trained) come from the episode's own uniform stream, so reruns, batches
and executors give the same actions.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np

from controllers.base import Controller, EpisodeContext, Message
from controllers.policy import (
    CHECKPOINT_DIR,
    MIN_LANES,
    UNIFORM_BLOCK_STEPS,
    VARIANT_DIR,
    checkpoint_path,
    shipped_variants,
)
from envs.accel_mode import (
    LEADER_MESSAGE,
    PRED_MESSAGE,
    accel_observations,
    leader_links,
)
from envs.dynamics import agent_observations
from envs.params import EVAL_MODES, PlatoonParams
from envs.platoon import PlatoonState
from envs.scenarios import Scenario, make_scenario
from envs.streams import episode_uniforms
from infra.errors import ConfigError
from infra.limits import MAX_TRAIN_SEED, check_seeds
from infra.naming import coerce_option
from marl.learners import SHARED_LEARNERS

#: Shipped variants of ``ippo`` (``ippo:variant=NAME``, folders below
#: ``controllers/checkpoints/variants``): a residual on ``cacc``, the same with a time-aware
#: critic, and the published OVM-gain action set.
IPPO_VARIANTS: tuple[str, ...] = ("residual-cacc", "residual-timed", "ovm-gain")


#: Fewest episodes' rows a per-agent actor (``ippo-bdc``, batched products ``(N, M, D) @ (N, D,
#: H)``) is evaluated on: with 1 to 6 rows this torch build's batched product rounds otherwise
#: than with more (measured on AMD EPYC); from 7 on, equal.
PER_AGENT_MIN_LANES = 8


@functools.cache
def mlp_rows_are_batch_invariant(action_mode: str = "accel", algo: str = "ippo") -> bool:
    """Whether a row of the actor gets the same numbers among 64 episodes' rows as among the
    fewest lanes the controller pads to (:data:`controllers.policy.MIN_LANES`, or
    :data:`PER_AGENT_MIN_LANES` for a per-agent actor; random weights, once per process)."""
    import torch

    from marl.ppo_nets import PPOConfig, SharedActor

    torch.manual_seed(0)
    cfg = PPOConfig(action_mode=action_mode, algo=algo if algo == "ippo-bdc" else "ippo")
    actor = SharedActor(cfg, n_agents=8 if cfg.per_agent else 0)
    lanes = PER_AGENT_MIN_LANES if cfg.per_agent else MIN_LANES
    with torch.no_grad():
        for p in actor.body.parameters():
            p.add_(0.1 * torch.randn(p.shape))
        obs = torch.randn(64, 8, cfg.obs_dim,
                          generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        full = actor(obs)
        for row in (0, 31, 63):
            sub = actor(obs[[row] * lanes].contiguous())
            if not torch.equal(sub[0], full[row]):
                return False
    return True


class SharedPolicyController(Controller):
    """A shared policy of ``ippo``, ``mappo`` or ``distill``, sampled (default) or greedy, at
    any N.

    Parameters
    ----------
    algo : str
        ``ippo``, ``mappo`` or ``distill``.
    scenario : str, optional
        Load the checkpoint trained on this scenario instead of the run's one.
    checkpoint : str, optional
        Explicit checkpoint file.
    checkpoint_dir : str, optional
        Folder of ``cacc-bench train --out`` to load from instead of the shipped checkpoints.
    seed : int
        Training seed (0).
    vehicles : int
        N the checkpoint was trained with (8); the run's N may differ.
    variant : str, optional
        A shipped variant (a folder of ``controllers/checkpoints/variants``; ``ovm-gain``: the
        same learner in the published action mode).
    mode : {"sampled", "greedy"}
        Actions drawn from the policy as trained (default) or its mode.
    """

    family = "marl"
    #: on a mixed string it sees only what an automated vehicle senses or receives: a human
    #: predecessor sends nothing (its command reads as the 0 held before any message)
    drives_mixed = True
    #: on a ring the leader's broadcast never arrives (held at 0) and follower 1 hears follower N
    needs_leader = False
    deterministic = False
    batch_invariant = True
    needs_observation = False

    def __init__(self, algo: str, scenario: str | None = None, checkpoint: str | None = None,
                 checkpoint_dir: str | None = None, seed: int | str = 0,
                 vehicles: int | str = 8, variant: str | None = None,
                 mode: str = "sampled") -> None:
        super().__init__()
        if algo not in SHARED_LEARNERS:
            raise ConfigError(f"unknown shared-policy algorithm {algo!r}; valid: "
                              f"{', '.join(SHARED_LEARNERS)}")
        if mode not in EVAL_MODES:
            raise ConfigError(f"{algo}: mode must be one of {', '.join(EVAL_MODES)}, got {mode!r}")
        seed = int(coerce_option(seed, int, "seed", algo))  # the one rule for option values
        vehicles = int(coerce_option(vehicles, int, "vehicles", algo))
        check_seeds([seed], f"{algo}: seed", MAX_TRAIN_SEED)  # what `train` can make
        if not 2 <= vehicles <= 64:
            raise ConfigError(f"{algo}: vehicles must lie in 2..64, got {vehicles}")
        if variant is not None:
            if checkpoint_dir is not None:
                raise ConfigError(f"{algo}: give variant or checkpoint_dir, not both")
            if variant not in shipped_variants():  # the list: those holding this algorithm
                raise ConfigError(f"{algo}: unknown variant {variant!r}; shipped with {algo}: "
                                  f"{', '.join(shipped_variants(algo)) or 'none'}")
            checkpoint_dir = str(VARIANT_DIR / variant)
        self.name = self.algo = algo
        self.variant = variant
        self.scenario, self.checkpoint, self.checkpoint_dir = scenario, checkpoint, checkpoint_dir
        self.seed, self.vehicles, self.mode = seed, vehicles, mode
        self.deterministic = mode == "greedy"
        self.options = {k: v for k, v in {
            "scenario": scenario, "checkpoint": checkpoint, "variant": variant,
            "checkpoint_dir": checkpoint_dir if variant is None else None,
            "seed": seed or None, "vehicles": vehicles if vehicles != 8 else None,
            "mode": mode if mode != EVAL_MODES[0] else None}.items() if v is not None}
        self.actor: Any = None
        self.loaded: dict[str, Any] = {}
        self._source: str | None = None

    @staticmethod
    def batch_invariant_probe(algo: str, **_: Any) -> bool:
        """Whether the harness may batch this policy's episodes here."""
        return mlp_rows_are_batch_invariant(algo=algo)

    # ---------------------------------------------------------------- loading
    def _path(self, source: str) -> Path:
        if self.checkpoint:
            return Path(self.checkpoint)
        return checkpoint_path(self.algo, source, self.vehicles, self.seed, self.checkpoint_dir)

    def preflight(self, scenario: Scenario, n_vehicles: int, params: PlatoonParams | None = None
                  ) -> None:
        """Load the policy now: a missing or damaged checkpoint fails before a sweep starts."""
        source = self.scenario or scenario.id
        if self.actor is None or self._source != source:
            self._load(source)
        if self.actor.n_agents and n_vehicles != self.actor.n_agents:
            raise ConfigError(
                f"{self.algo} has one network per follower, trained for N = "
                f"{self.actor.n_agents}; run it with --vehicles {self.actor.n_agents} (the "
                "shared policies ippo, mappo and distill act at any N)")

    def _load(self, source: str) -> None:
        """Load and verify the checkpoint trained on ``source``."""
        import torch

        from marl.checkpoint import load_checkpoint, policy_id
        from marl.ppo_eval import load_actor

        torch.set_num_threads(1)
        path = self._path(source)
        if not path.exists():
            make_scenario(source)  # an unknown scenario id is named as such, not to be trained on
            where = self.variant or self.checkpoint_dir or CHECKPOINT_DIR.name
            raise ConfigError(
                f"no trained {self.algo} policy for {source} with N = {self.vehicles} in {where} "
                f"({path.name} missing); make it with `cacc-bench train --algo {self.algo} "
                f"--scenario {source} --vehicles {self.vehicles} --seed {self.seed}`, or pick "
                f"another with {self.algo}:scenario=ID")
        # a file named for N = vehicles holds that N (an explicit checkpoint=FILE: any N)
        data = load_checkpoint(path, algo=self.algo, scenario=source,
                               n_vehicles=None if self.checkpoint else self.vehicles)
        self.actor = load_actor(data)
        self.action_mode = data["config"]["action_mode"]
        self.loaded, self._source, self._policy_sha256 = data, source, policy_id(data)

    # ---------------------------------------------------------------- interface
    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """``accel``: the command to the follower behind, the leader's broadcast; ``ovm-gain``:
        the vehicle block to both neighbours."""
        self.preflight(ctx.scenario, ctx.n_vehicles, ctx.params)
        if self.action_mode == "accel":
            name, width = PRED_MESSAGE
            lname, lwidth = LEADER_MESSAGE
            return (Message(name, width, "predecessor"),
                    Message(lname, lwidth, tuple(leader_links(ctx.n_vehicles))))
        return (Message(f"{self.algo}-blocks", 5, "neighbours"),)

    def reset(self, ctx: EpisodeContext) -> None:
        self.preflight(ctx.scenario, ctx.n_vehicles, ctx.params)
        self.params, self.ctx = ctx.params, ctx
        b, n = ctx.batch_size, ctx.n_vehicles
        self.seeds, self.t = ctx.seeds, 0
        self._u_block: np.ndarray | None = None
        self._u_start = 0
        self._lanes = max(b, PER_AGENT_MIN_LANES if self.actor.n_agents else MIN_LANES)
        if self.action_mode == "accel":
            self._pred_channel = ctx.channel(PRED_MESSAGE[0])
            self._leader_channel = ctx.channel(LEADER_MESSAGE[0])
            self._pred_held = np.zeros((b, n))
            self._leader_held = np.zeros((b, n, 2))
        else:
            self._block_channel = ctx.channel(f"{self.algo}-blocks")

    def _observation(self, state: PlatoonState) -> np.ndarray:
        ctx, p = self.ctx, self.params
        if self.action_mode == "accel":
            return accel_observations(
                state.gap_m, state.speed_mps, state.pred_speed_mps, state.applied_accel_mps2,
                state.realised_accel_mps2, self._pred_held, self._leader_held,
                ctx.target_gap_m, ctx.target_speed_mps, p)
        from envs.dynamics import vehicle_blocks
        from marl.ppo_eval import agent_inputs

        own = vehicle_blocks(state.gap_m, state.speed_mps, state.pred_speed_mps,
                             state.applied_accel_mps2, ctx.target_gap_m, ctx.target_speed_mps,
                             p).astype(np.float32)
        b, n, _ = own.shape
        payload = np.zeros((b, n + 1, 5))
        payload[:, 1:] = own
        held = self._block_channel.transmit(payload)
        obs = agent_observations(own)
        obs[:, 1:, 5:10] = held[:, : n - 1]   # (i-1 -> i) for i = 2..N
        obs[:, :-1, 10:15] = held[:, n - 1:]  # (i+1 -> i) for i = 1..N-1
        return agent_inputs(obs, "ovm-gain")

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        import torch

        from marl.ppo_eval import ACTION_STREAM, sample_with_uniforms, to_command

        obs = self._observation(state)
        b, n = obs.shape[:2]
        if b < self._lanes:  # at least MIN_LANES episodes' rows: see controllers.policy
            obs = np.concatenate([obs, np.repeat(obs[:1], self._lanes - b, 0)])
        uniforms = None
        if self.mode == "sampled":
            k = self.t - self._u_start
            if self._u_block is None or k >= len(self._u_block):  # the same numbers as one
                self._u_block = episode_uniforms(  # draw per step, in one vectorised pass
                    self.seeds, ACTION_STREAM, self.t, n, steps=UNIFORM_BLOCK_STEPS)
                self._u_start, k = self.t, 0
            uniforms = self._u_block[k]
            if b < self._lanes:
                uniforms = np.concatenate([uniforms, np.repeat(uniforms[:1], self._lanes - b, 0)])
        self.t += 1
        with torch.no_grad():
            out = self.actor(torch.from_numpy(np.ascontiguousarray(obs)))
            action = sample_with_uniforms(self.actor, out, uniforms)[:b]
            command = to_command(self.actor, action, state, self.params, obs[:b],
                                 (self.ctx.target_gap_m, self.ctx.target_speed_mps))
        if self.action_mode == "accel":
            from envs.accel_mode import transmit_accel_messages

            pred, lead = transmit_accel_messages(
                self._pred_channel, self._leader_channel, command, state.leader_accel_now_mps2,
                state.leader_speed_now_mps, self.ctx.target_speed_mps, self.params)
            self._pred_held, self._leader_held = pred.copy(), lead.copy()
        return command
