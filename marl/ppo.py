"""IPPO and MAPPO with one policy shared by every follower, in either action mode.

Read top to bottom, as CleanRL's ``ppo_continuous_action.py`` reads: the config and the networks
(:mod:`marl.ppo_nets`), then here the training world, the rollout, the returns (GAE), the
clipped PPO loss and the update, each a method of :class:`PPOTrainer` in that order. ``ippo-bdc``
differs only in its update (a network per follower, compressed critic gradients, consensus):
its own file, :mod:`marl.ippo_bdc`, overrides those steps. What is this project's own, and why
it is written here rather than taken from a library, is in ``docs/notes/marl-library-choice.md``.

- **Shared policy**: one actor for all followers; each agent's observation carries its position
  (first, last, ``i / N``: :func:`envs.accel_mode.position_features`), so one checkpoint acts at
  any N from 2 to 64. A batch of ``B`` episodes with ``N`` followers is ``B N`` rows of one
  product per layer.
- **Action modes** (:mod:`envs.accel_mode`): ``accel``, a tanh-squashed Gaussian in the command
  bounds (``c + h tanh(z)``; PPO's ratio needs only ``z``, the Jacobian cancels), with the V2V
  part of the observation through the training channel; ``ovm-gain``, a categorical over the
  published four OVM gain pairs.
- **IPPO vs MAPPO**: the critic sees the agent's observation (``ippo``) or the agent's
  observation beside the platoon's mean observation (``mappo``: a centralised critic that any N
  can feed).
- **Rewards**: the paper's training reward per agent (safety term included), the cruise power
  ``P(v*, 0)`` subtracted from the power term (a constant per running agent-step, so the same
  optimum, a centred value), divided by the running standard deviation of the discounted return
  and clipped to +-10 (Stable-Baselines3's and CleanRL's reward normalisation; the quadratic
  costs of a platoon drifting apart are unbounded otherwise). Observations are normalised by
  running statistics kept in the actor (frozen in the checkpoint). A collision ends the episode
  with the collision penalty at every remaining scheduled step, discounted (the absorbing value
  of ``marl.a2c``), so ending early never pays; the time limit is a truncation (bootstrapped).
- **Domain randomisation** (:attr:`marl.ppo_nets.PPOConfig.randomised`,
  :meth:`PPOTrainer.draw_world`): each batch of episodes may draw its N, V2V delay and loss,
  scenario, vehicle classes and share of automated followers, placed at random (the other seats
  human drivers, :mod:`envs.humans`, whose agent-steps enter neither the loss nor the statistics).
- **Determinism**: every random number comes from the run's ``torch.Generator`` (the action
  noise, minibatch order, initial weights, the batches' draws) and the training episodes'
  seeds from the run's seed, so a seed gives the same weights, on one thread count.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import Scenario, as_scenario, check_vehicles
from envs.vehicle_classes import canonical_classes, class_features
from infra.errors import ConfigError
from infra.limits import MAX_ROLLOUT_AGENT_STEPS, MAX_SEED, training_episode_seeds
from marl.a2c import absorbing_value, sharing_matrix
from marl.acting import agent_inputs, to_command
from marl.checkpoint import (
    Snapshots,
    plain_state,
    process_rng_state,
    restore_state,
    set_process_rng_state,
)
from marl.layers import module_tensors
from marl.ppo_nets import Critic, PPOConfig, SharedActor, as_shipped, check_finite_weights

#: Scores a policy on the validation seeds: ``(actor, mode) -> {"reward", "collisions", ...}``
#: (:func:`benchmark.policy_eval.validation_evaluator`, given by the layer above).
Evaluator = Callable[[SharedActor, str], dict[str, float]]


def validation(evaluate: Evaluator, actor: SharedActor) -> dict[str, float]:
    """The validation reward and collisions of ``actor``, actions sampled as trained."""
    score = evaluate(actor, "sampled")
    return {"reward": float(score["reward"]), "collisions": float(score["collisions"])}


def beats(score: dict[str, float], kept: dict[str, float]) -> bool:
    """Whether a validation ``score`` replaces the ``kept`` one (none yet: ``{}``): fewer
    collisions, then a higher reward; a tie goes to the newer."""
    return not kept or ((score["collisions"], -score["reward"])
                        <= (kept["collisions"], -kept["reward"]))


@dataclass
class PPOResult:
    """What :func:`train` returns: the kept actor (acting weights), its validation score, the
    learning curve and the throughput."""

    actor: SharedActor
    steps: int
    curve: list[dict[str, float]]
    best: dict[str, float]
    env_steps_per_s: float
    config: PPOConfig
    bits_per_agent: dict[str, float] = dataclasses.field(default_factory=dict)


# ---------------------------------------------------------------------------- the world
@dataclass
class World:
    """The road one batch of training episodes runs on: its env (scenario, N, V2V, humans),
    the reward sharing over its N, the cruise-power baseline and its automated seats."""

    env: PlatoonEnv
    n: int
    sharing: torch.Tensor   # (N, N): agent i learns from sum_j alpha^|i-j| r_j
    baseline: float         # minus the power weight times the cruise power P(v*, 0)
    automated: torch.Tensor  # (N,) bool: seats the policy drives
    features: np.ndarray | None = None  # (N, F) class features the networks read, or None

    @property
    def targets(self) -> tuple[float, float]:
        """The scenario's target gap (m) and speed (m/s): a prior's targets."""
        sc = self.env.scenario
        return sc.target_gap_m, sc.target_speed_mps


class RewardScale:
    """The running standard deviation of the discounted return of the live agent-steps
    (Stable-Baselines3's ``VecNormalize`` reward; Chan et al.'s parallel update)."""

    def __init__(self, gamma: float) -> None:
        self.gamma = gamma
        self.count, self.mean, self.var = 1e-4, 0.0, 1.0
        self.returns = torch.zeros(0, dtype=torch.float64)

    def reset(self, b: int, n: int) -> None:
        """New episodes: ``(B, N)`` returns from zero."""
        self.returns = torch.zeros(b, n, dtype=torch.float64)

    def __call__(self, reward: torch.Tensor, live: torch.Tensor) -> float:
        """Add this step's rewards, merge the live returns (``live``: ``(B,)`` or ``(B, N)``)
        into the statistics, return the standard deviation."""
        self.returns.mul_(self.gamma).add_(reward.double())
        x = self.returns[live]
        if len(x):
            n_b, mean_b, var_b = float(x.numel()), float(x.mean()), float(x.var(unbiased=False))
            tot = self.count + n_b
            delta = mean_b - self.mean
            self.var = (self.var * self.count + var_b * n_b
                        + delta**2 * self.count * n_b / tot) / tot
            self.mean, self.count = self.mean + delta * n_b / tot, tot
        return math.sqrt(self.var + 1e-8)


@dataclass
class Rollout:
    """``T`` steps of ``B`` episodes of ``N`` agents (T shorter where a randomised batch ended)."""

    obs: torch.Tensor         # (T, B, N, D) normalised observations
    critic_obs: torch.Tensor  # (T, B, N, D') the critic's inputs
    action: torch.Tensor      # (T, B, N)
    logp: torch.Tensor        # (T, B, N)
    value: torch.Tensor       # (T + 1, B, N)
    reward: torch.Tensor      # (T, B, N) normalised, clipped
    live: torch.Tensor        # (T, B, N) bool: a running episode's automated seat
    cont: torch.Tensor        # (T, B) the episode goes on after the step
    end_value: torch.Tensor   # (T, B, N) value after an ending: absorbing or bootstrap

    def cut(self, t_len: int) -> Rollout:
        """The first ``t_len`` steps (every episode ended at the last of them)."""
        fields = {f.name: getattr(self, f.name)[: t_len + (f.name == "value")]
                  for f in dataclasses.fields(self)}
        return Rollout(**fields)


# ---------------------------------------------------------------------------- the trainer
class PPOTrainer:
    """One run: the networks, the training world, and the loop (rollout, returns, update).

    Parameters
    ----------
    scenario : Scenario
        The run's scenario (validation's and the checkpoint's; the training batches draw
        from ``config.scenarios`` when it names others).
    n_vehicles, seed, total_steps : int
        The run's N (the batches' N where not randomised), seed and environment steps.
    config : PPOConfig
    params : PlatoonParams
    """

    #: The actor's and the training env's classes (``ippo-gains``: its own).
    actor_cls: type[SharedActor] = SharedActor
    env_cls: type[PlatoonEnv] = PlatoonEnv

    def __init__(self, scenario: Scenario, n_vehicles: int, seed: int, total_steps: int,
                 config: PPOConfig, params: PlatoonParams = PlatoonParams()) -> None:
        cfg = self.cfg = config
        self.sc, self.params = scenario, params
        self.n, self.seed, self.total_steps = check_vehicles(n_vehicles), int(seed), total_steps
        roads = self.roads = cfg.roads or [scenario]
        for mix in cfg.mixes:  # each batch's classes name its N: one N, no ring's own
            if len(mix) != self.n or cfg.vehicles_min or cfg.vehicles_max or any(
                    s.ring for s in roads):
                raise ConfigError(f"class_mixes={cfg.class_mixes!r}: every arrangement names "
                                  f"the run's {self.n} followers (--vehicles), with no vehicles "
                                  "range (vehicles_min, vehicles_max: 0) and no ring road")
        rollout = cfg.n_envs * cfg.rollout_steps  # environment steps per update
        widest = max([self.n, cfg.vehicles_max] + [s.default_vehicles for s in roads if s.ring])
        if rollout * widest > MAX_ROLLOUT_AGENT_STEPS:
            raise ConfigError(f"one rollout of n_envs x rollout_steps x N = {cfg.n_envs} x "
                              f"{cfg.rollout_steps} x {widest} agent-steps exceeds "
                              f"{MAX_ROLLOUT_AGENT_STEPS:,}; lower n_envs or rollout_steps")
        if rollout > total_steps:
            raise ConfigError(f"one rollout is n_envs x rollout_steps = {rollout:,} environment "
                              f"steps, more than the {total_steps:,} asked (--steps); raise "
                              "--steps or lower n_envs or rollout_steps")
        self.gen = torch.Generator().manual_seed(self.seed)
        torch.manual_seed(self.seed)  # nn.init draws from the global generator
        n_agents = self.n if cfg.per_agent else 0
        self.actor, self.critic = self.actor_cls(cfg, params, n_agents), Critic(cfg, n_agents)
        before = set(vars(self))
        self.setup()
        #: the attributes :meth:`setup` made: the learner's own state, which snapshots keep
        self.own_state = tuple(sorted(set(vars(self)) - before))
        self.opt = torch.optim.Adam([*self.actor.parameters(), *self.critic.parameters()],
                                    lr=cfg.lr, eps=1e-5)
        self.world = self.make_world(scenario, self.n, cfg.comm_delay_s, cfg.packet_loss)
        self.scale = RewardScale(cfg.gamma)  # reset by new_episodes
        self.episode = self.steps = self.updates = 0
        #: the batch of episodes in progress, to rebuild its env in a snapshot: the generator's
        #: state before its world was drawn (randomised), and the commands it has stepped
        self.world_draw: torch.Tensor | None = None
        self.commands: list[np.ndarray] = []
        self.obs = self.new_episodes()
        self.curve: list[dict[str, float]] = []  # validations: steps, reward, collisions
        self.best: dict[str, float] = {}  # the kept snapshot's validation
        self.best_state: dict[str, torch.Tensor] = {}
        self.next_eval = 0  # environment steps of the next validation
        self.elapsed_s = 0.0  # seconds trained in earlier processes (a resumed run)

    def setup(self) -> None:
        """What a learner adds before its optimiser (``ippo-bdc``: its compressor)."""

    # ---- the world each batch of episodes runs on
    def make_world(self, sc: Scenario, n: int, delay_s: float, loss: float) -> World:
        """The env and what the rewards read for ``sc`` with ``n`` followers."""
        env = self.env_cls(sc, n, self.params, training=True, action_mode=self.cfg.action_mode,
                           channel=ChannelConfig(delay_s, loss, self.params.dt_s))
        sharing = sharing_matrix(n, self.cfg.reward_alpha)
        p0 = float(env.power(np.array([sc.target_speed_mps]), np.array([0.0]))[0])
        automated = torch.from_numpy(np.asarray(sc.arrangement(n).automated, dtype=bool))
        features = (class_features(sc.vehicle_arrays(n, self.params), n, self.params)
                    if self.cfg.class_features else None)
        return World(env, n, sharing, -env.weights.power * p0, automated, features)

    def inputs(self, obs: np.ndarray | None, world: World | None = None) -> torch.Tensor:
        """What the networks read of ``world``'s (this batch's) observation ``obs``."""
        w = self.world if world is None else world
        return torch.from_numpy(agent_inputs(obs, self.cfg.action_mode, w.features))

    def draw_world(self) -> World:
        """This batch's road, from the run's generator: its scenario, N, V2V, automated seats
        and vehicle classes (in that order; each draw only where the config randomises it)."""
        cfg, gen, dt = self.cfg, self.gen, self.params.dt_s
        n_lo, n_hi = cfg.vehicles_min or self.n, cfg.vehicles_max or self.n
        if n_lo > n_hi:
            raise ConfigError(f"the vehicles range {n_lo}..{n_hi} is empty")
        n = n_lo + int(torch.randint(n_hi - n_lo + 1, (1,), generator=gen))
        steps_lo = round(cfg.comm_delay_s / dt)
        steps_hi = round(max(cfg.comm_delay_max_s, cfg.comm_delay_s) / dt)
        delay = dt * (steps_lo + int(torch.randint(steps_hi - steps_lo + 1, (1,), generator=gen)))
        loss_hi = max(cfg.packet_loss_max, cfg.packet_loss)
        loss = cfg.packet_loss + (loss_hi - cfg.packet_loss) * float(
            torch.rand(1, generator=gen, dtype=torch.float64))
        sc = self.sc
        if cfg.scenarios:
            sc = self.roads[int(torch.randint(len(self.roads), (1,), generator=gen))]
        if sc.ring:
            n = sc.default_vehicles
        if cfg.mixed_traffic:
            share = cfg.cav_share_min + (cfg.cav_share_max - cfg.cav_share_min) * float(
                torch.rand(1, generator=gen, dtype=torch.float64))
            placement_seed = int(torch.randint(MAX_SEED + 1, (1,), generator=gen))
            sc = sc.derive(cav_fraction=share, placement="random", placement_seed=placement_seed)
        if cfg.class_mixes:  # one arrangement of the list, in the order of a drawn class_seed
            mix = cfg.mixes[int(torch.randint(len(cfg.mixes), (1,), generator=gen))]
            class_seed = int(torch.randint(MAX_SEED + 1, (1,), generator=gen))
            sc = sc.derive(class_mix=canonical_classes(mix), class_seed=class_seed)
        return self.make_world(sc, n, delay, loss)

    def new_episodes(self) -> torch.Tensor:
        """Start the next ``B`` training episodes (a newly drawn world where randomised);
        their observations."""
        b = self.cfg.n_envs
        seeds = training_episode_seeds(self.seed, self.episode, b)
        self.episode += b
        if self.cfg.randomised:
            self.world_draw = self.gen.get_state()
            self.world = self.draw_world()
        self.scale.reset(b, self.world.n)
        self.commands = []
        obs = self.world.env.reset(seeds)
        return self.inputs(obs)

    # ---- rollout: T steps of B episodes (fewer where a randomised batch ends)
    def collect(self) -> Rollout:
        """Act in the world for up to ``rollout_steps`` steps, recording what the update
        needs; new episodes start where all end."""
        cfg, actor, critic, gen = self.cfg, self.actor, self.critic, self.gen
        w = self.world
        env, n_r, b, t_len, d = w.env, w.n, cfg.n_envs, cfg.rollout_steps, cfg.obs_dim
        ro = Rollout(
            obs=torch.zeros(t_len, b, n_r, d),
            critic_obs=torch.zeros(t_len, b, n_r, d * (2 if critic.central else 1) + critic.timed),
            action=torch.zeros(t_len, b, n_r), logp=torch.zeros(t_len, b, n_r),
            value=torch.zeros(t_len + 1, b, n_r), reward=torch.zeros(t_len, b, n_r),
            live=torch.zeros(t_len, b, n_r, dtype=torch.bool), cont=torch.zeros(t_len, b),
            end_value=torch.zeros(t_len, b, n_r))
        obs = self.obs
        for t in range(t_len):
            s = env.state
            assert s is not None
            live = torch.from_numpy(~s.done)
            live_seats = live[:, None] & w.automated[None, :]
            with torch.no_grad():
                actor.update_obs_stats(obs[live_seats])
                nobs = actor.normalise(obs)
                out = actor.policy(nobs)
                if actor.continuous:
                    action = out + actor.log_std.exp() * torch.randn(out.shape, generator=gen)
                else:
                    u = torch.rand(out.shape, generator=gen).clamp_(1e-12, 1.0)
                    action = (out - torch.log(-torch.log(u))).argmax(-1).to(out.dtype)
                logp, _ = actor.log_prob_entropy(out, action)
                ro.critic_obs[t] = critic.inputs(nobs, s.step / env.n_steps)
                ro.value[t] = critic.body(ro.critic_obs[t])[..., 0]
            command = to_command(actor, action, env.state, env.params, obs.numpy(), w.targets)
            self.commands.append(command.copy())
            res = env.step(command)
            ro.obs[t], ro.action[t], ro.logp[t], ro.live[t] = nobs, action, logp, live_seats
            reward = (torch.from_numpy(res.reward.astype(np.float32)) + w.baseline) * live[:, None]
            if cfg.reward_alpha > 0:
                reward = reward @ w.sharing
            std = self.scale(reward, live_seats)
            ro.reward[t] = (reward / std).clamp_(-cfg.reward_clip, cfg.reward_clip)
            ended = torch.from_numpy(res.done) & live
            collided = torch.from_numpy(res.collided) & live
            ro.cont[t] = (~ended).float()
            absorbing = absorbing_value(env.weights.collision, cfg.gamma,
                                        env.n_steps - s.step) / std
            all_done, next_obs = bool(res.done.all()), self.inputs(res.observation, w)
            if ended.any():  # a collision's absorbing value, else a bootstrap from the next
                with torch.no_grad():  # state (all done: the time limit, which a time-aware
                    # critic knows: a finite horizon, 0)
                    last = torch.zeros(b, n_r) if all_done and cfg.critic_time else critic(
                        actor.normalise(next_obs), 0.0 if all_done else s.step / env.n_steps)
                ro.end_value[t] = torch.where(collided[:, None], torch.tensor(absorbing),
                                              last) * ended[:, None]
            obs = self.new_episodes() if all_done else next_obs
            self.steps += int(live.sum())
            if cfg.randomised and all_done and t + 1 < t_len:
                self.obs = obs  # the next batch may be another world: this rollout ends here
                return ro.cut(t + 1)
        self.obs = obs
        if obs.shape[-2] == n_r:  # else every episode ended at the last step (unread)
            now = self.world.env.state  # new episodes where all ended at the last step
            assert now is not None
            with torch.no_grad():
                ro.value[t_len] = critic(actor.normalise(obs), now.step / env.n_steps)
        return ro

    # ---- returns: GAE over the rollout, ended episodes closed by their end value
    def advantages(self, ro: Rollout) -> tuple[torch.Tensor, torch.Tensor]:
        """GAE advantages and the critic's targets, ``(T, B, N)`` each."""
        cfg = self.cfg
        t_len = ro.reward.shape[0]
        adv = torch.zeros_like(ro.reward)
        last_gae = torch.zeros(ro.reward.shape[1:])
        for t in reversed(range(t_len)):
            cont = ro.cont[t][:, None]
            next_value = ro.value[t + 1] * cont + ro.end_value[t]
            delta = ro.reward[t] + cfg.gamma * next_value - ro.value[t]
            last_gae = delta + cfg.gamma * cfg.gae_lambda * cont * last_gae
            adv[t] = last_gae
        return adv, adv + ro.value[:t_len]

    # ---- loss and update: PPO's clipped objective on the live agent-steps
    def rows(self, ro: Rollout, adv: torch.Tensor, ret: torch.Tensor
             ) -> tuple[list[torch.Tensor], int]:
        """The update's rows (observation, critic input, action, log-prob, advantage, return;
        one per live automated agent-step) and the rows per minibatch."""
        keep = ro.live.reshape(-1)
        return ([x.reshape(-1, *x.shape[3:])[keep]
                 for x in (ro.obs, ro.critic_obs, ro.action, ro.logp, adv, ret)],
                self.cfg.minibatch_rows)

    def loss(self, obs: torch.Tensor, critic_obs: torch.Tensor, action: torch.Tensor,
             logp_old: torch.Tensor, adv: torch.Tensor, ret: torch.Tensor) -> torch.Tensor:
        """PPO's clipped policy loss, the value loss and the entropy bonus of one minibatch
        (only the value loss during the critic's warm-up)."""
        cfg = self.cfg
        # one row alone is its own mean: a zero advantage (its std would be NaN)
        adv = (adv - adv.mean()) / ((adv.std() if adv.numel() > 1 else 0.0) + 1e-8)
        out = self.actor.policy(obs)
        logp, ent = self.actor.log_prob_entropy(out, action)
        ratio = (logp - logp_old).exp()
        pg = torch.max(-adv * ratio,
                       -adv * ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef)).mean()
        v_loss = 0.5 * (self.critic.body(critic_obs)[..., 0] - ret).pow(2).mean()
        loss = cfg.vf_coef * v_loss
        if self.updates >= cfg.critic_warmup_updates:
            loss = loss + pg - cfg.ent_coef * ent.mean()
        return loss

    def update(self, ro: Rollout) -> None:
        """``epochs`` passes of minibatch Adam steps over the rollout, the learning rate
        annealed linearly to 0 over the run."""
        cfg = self.cfg
        adv, ret = self.advantages(ro)
        flat, mb_rows = self.rows(ro, adv, ret)
        n_rows = flat[0].shape[0]
        n_updates = max(1, math.ceil(self.total_steps / (cfg.n_envs * cfg.rollout_steps)))
        for g in self.opt.param_groups:
            g["lr"] = cfg.lr * (1.0 - self.updates / n_updates)
        for _ in range(cfg.epochs):
            order = torch.randperm(n_rows, generator=self.gen)
            for start in range(0, n_rows, mb_rows):
                idx = order[start:start + mb_rows]
                loss = self.loss(*(x[idx] for x in flat))
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                # apart: the critic's gradient (returns of hundreds) must not shrink the actor's
                nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
                nn.utils.clip_grad_norm_(self.critic.parameters(), cfg.max_grad_norm)
                self.before_step()
                self.opt.step()
                self.after_step()
        self.updates += 1
        check_finite_weights((self.actor, self.critic),
                             f"{cfg.algo} on {self.sc.id}, seed {self.seed}",
                             f"{self.updates} updates ({self.steps} environment steps)")

    def before_step(self) -> None:
        """What a learner does to the gradients before each Adam step (``ippo-bdc``)."""

    def after_step(self) -> None:
        """What a learner does to the weights after each Adam step (``ippo-bdc``)."""

    def bits_per_agent(self) -> dict[str, float]:
        """What each agent sent in training, by kind (bits; none for a shared policy)."""
        return {}

    # ---- the run: validate, collect, update, until the budget is spent
    def validate(self, evaluate: Evaluator, log: Callable[[str], None] | None) -> None:
        """Score the weights as they would ship; keep them if they beat the kept snapshot
        (fewer collisions, then a higher reward)."""
        shipped = as_shipped(self.actor)
        score = validation(evaluate, shipped)
        self.curve.append({"steps": float(self.steps), **score})
        if beats(score, self.best):
            self.best, self.best_state = {"steps": float(self.steps), **score}, shipped.state_dict()
        if log:
            log(f"{self.cfg.algo} {self.sc.id} seed {self.seed}: {self.steps} steps, validation "
                f"reward {score['reward']:.1f}, collisions {score['collisions']:.0f}")

    def train(self, evaluate: Evaluator | None = None,
              log: Callable[[str], None] | None = None,
              snapshots: Snapshots | None = None) -> PPOResult:
        """Train until ``total_steps``; returns the snapshot with the fewest validation
        collisions, then the best validation reward (the last when ``evaluate`` is None).

        With ``snapshots``, the run continues from its snapshot file where there is one, and
        keeps one there every so often (after an update; :meth:`snapshot_state`)."""
        if snapshots is not None:
            # a learner keeping what a snapshot cannot hold fails here, at once
            plain_state({k: getattr(self, k) for k in self.own_state}, (self.gen,))
            state = snapshots.read()
            if state is not None:
                self.restore(state)
                if log:
                    log(f"resumed from {snapshots.path}: {self.steps} steps, {self.updates} "
                        "updates")
        t0 = time.perf_counter()
        while self.steps < self.total_steps:
            if evaluate is not None and self.steps >= self.next_eval:
                self.validate(evaluate, log)
                self.next_eval += self.cfg.eval_every_steps
            self.update(self.collect())
            if snapshots is not None and self.steps < self.total_steps and snapshots.due():
                snapshots.write(self.steps, self.snapshot_state(time.perf_counter() - t0))
        rate = self.steps / max(self.elapsed_s + time.perf_counter() - t0, 1e-9)
        if evaluate is None:
            actor = as_shipped(self.actor)
        else:
            self.validate(evaluate, log)
            actor = self.actor
            actor.load_state_dict(self.best_state)
        return PPOResult(actor, self.steps, self.curve, self.best, rate, self.cfg,
                         self.bits_per_agent())

    # ---- resumable snapshots: everything the run continues from, bit for bit
    def snapshot_state(self, elapsed_s: float = 0.0) -> dict[str, Any]:
        """The run's state between two updates (:class:`marl.checkpoint.Snapshots`): the
        networks' weights and buffers, Adam's state, the run's generator and the process's
        (torch's, numpy's, Python's), the reward statistics, counters, the learning curve and
        the kept snapshot, what :meth:`setup` made (:attr:`own_state`), and the batch of
        episodes in progress as its draw and the commands it stepped (its env is rebuilt by
        stepping them again, :meth:`restore`). ``elapsed_s``: seconds trained in this
        process."""
        scale = self.scale
        return {
            "modules": {name: {k: v.detach().clone() for k, v in module_tensors(m).items()}
                        for name, m in self._modules().items()},
            "optimiser": self.opt.state_dict(),
            "generator": self.gen.get_state(),
            "process_rng": process_rng_state(),
            "own": plain_state({k: getattr(self, k) for k in self.own_state}, (self.gen,)),
            "scale": [scale.count, scale.mean, scale.var, scale.returns.clone()],
            "counters": [self.episode, self.steps, self.updates, self.next_eval],
            "elapsed_s": self.elapsed_s + elapsed_s,
            "curve": [dict(row) for row in self.curve],
            "best": dict(self.best),
            "best_state": {k: v.clone() for k, v in self.best_state.items()},
            "batch": {"world_draw": self.world_draw,
                      "commands": torch.from_numpy(np.stack(self.commands)) if self.commands
                      else torch.zeros(0),
                      "obs": self.obs.clone()},
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`snapshot_state`'s ``state`` (this trainer freshly made with
        the same arguments): the batch in progress is rebuilt by resetting its episodes and
        stepping its commands again, and must give the recorded observations."""
        with torch.no_grad():
            for name, module in self._modules().items():
                mine = module_tensors(module)
                saved = state["modules"][name]
                if mine.keys() != saved.keys() or any(
                        mine[k].shape != saved[k].shape for k in mine):
                    raise ConfigError(f"the snapshot's {name} is not this learner's network; "
                                      "remove the snapshot to train from the start")
                for k, t in mine.items():
                    t.copy_(saved[k])
        self.opt.load_state_dict(state["optimiser"])
        self.episode, self.steps, self.updates, self.next_eval = state["counters"]
        self.elapsed_s = float(state["elapsed_s"])
        self.curve = [dict(row) for row in state["curve"]]
        self.best, self.best_state = dict(state["best"]), dict(state["best_state"])
        for k, v in restore_state({k: getattr(self, k) for k in self.own_state}, state["own"],
                                  (self.gen,)).items():
            setattr(self, k, v)
        batch = state["batch"]
        self.world_draw = batch["world_draw"]
        if self.world_draw is not None:  # the world this batch drew
            self.gen.set_state(self.world_draw)
            self.world = self.draw_world()
        env, b = self.world.env, self.cfg.n_envs
        obs = env.reset(training_episode_seeds(self.seed, self.episode - b, b))
        self.commands = [c.numpy() for c in batch["commands"]]
        for command in self.commands:
            obs = env.step(command.copy()).observation
        self.obs = self.inputs(obs)
        if not torch.equal(self.obs, batch["obs"]):
            raise ConfigError("the snapshot's episodes in progress step to other observations "
                              "here (another cacc-bench or numpy?); remove the snapshot to "
                              "train from the start")
        self.gen.set_state(state["generator"])
        set_process_rng_state(state["process_rng"])
        count, mean, var, returns = state["scale"]
        self.scale.count, self.scale.mean, self.scale.var = count, mean, var
        self.scale.returns = returns.clone()

    def _modules(self) -> dict[str, nn.Module]:
        return {"actor": self.actor, "critic": self.critic}


def train(
    scenario: str | Scenario,
    n_vehicles: int = 8,
    seed: int = 0,
    total_steps: int = 1_000_000,
    config: PPOConfig = PPOConfig(),
    params: PlatoonParams = PlatoonParams(),
    log: Callable[[str], None] | None = None,
    evaluate: Evaluator | None = None,
    snapshots: Snapshots | None = None,
) -> PPOResult:
    """Train one policy of ``config.algo`` on ``scenario`` with N followers for ``total_steps``
    environment steps (one step of one episode each).

    Returns the snapshot with the fewest validation collisions, then the best validation reward
    (actions sampled as trained, scored by ``evaluate``: the layer above gives
    :func:`benchmark.policy_eval.validation_evaluator`), or the last one when ``evaluate`` is
    None. With ``snapshots`` it continues from the run's snapshot file and keeps one
    (:meth:`PPOTrainer.train`).
    """
    from marl.learners import LEARNERS, load

    trainer_cls = load(f"{LEARNERS[config.algo].module}:TRAINER")
    return trainer_cls(as_scenario(scenario), n_vehicles, seed, total_steps, config,
                       params).train(evaluate, log, snapshots)


#: The trainer of ``ippo`` and ``mappo`` (the learner registry names this module).
TRAINER = PPOTrainer
