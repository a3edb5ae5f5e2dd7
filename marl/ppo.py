"""IPPO and MAPPO with one policy shared by every follower, in either action mode.

Read top to bottom, as CleanRL's ``ppo_continuous_action.py`` reads: the rollout, the returns
(GAE), the clipped PPO loss and the update. The config and the networks are in
:mod:`marl.ppo_nets`, acting, validation and loading in :mod:`marl.ppo_eval` (what the
controller imports without the trainer). What is this project's own, and why it is written here rather than taken from a
library, is in ``docs/notes/marl-library-choice.md``.

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
  running statistics kept in the actor (frozen in the checkpoint). A collision ends the episode with the
  collision penalty at every remaining scheduled step, discounted (the absorbing value of
  ``marl.a2c``), so ending early never pays; the time limit is a truncation (bootstrapped).
- **Determinism**: every random number comes from the run's ``torch.Generator`` (the action
  noise, minibatch order, initial weights) and the training episodes' seeds from the run's seed,
  so a seed gives the same weights, on one thread count.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import check_vehicles, make_scenario
from infra.errors import ConfigError
from infra.limits import MAX_ROLLOUT_AGENT_STEPS, training_episode_seeds
from marl.consensus import bdc, consensus_round
from marl.ppo_eval import (
    agent_inputs,
    as_shipped,
    check_finite_weights,
    to_command,
    validation_score,
)
from marl.ppo_nets import Critic, PPOConfig, SharedActor
from marl.quantize import ErrorFeedbackQSGD, qsgd_bits, ternary_bits


# ---------------------------------------------------------------------------- training
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


def train(
    scenario: str,
    n_vehicles: int = 8,
    seed: int = 0,
    total_steps: int = 1_000_000,
    config: PPOConfig = PPOConfig(),
    params: PlatoonParams = PlatoonParams(),
    log: Callable[[str], None] | None = None,
    validate: bool = True,
) -> PPOResult:
    """Train one shared policy on ``scenario`` with N followers for ``total_steps`` environment
    steps (one step of one episode each).

    Returns the snapshot with the fewest validation collisions, then the best validation reward
    (actions sampled as trained), or the last one when ``validate`` is False.
    """
    cfg, sc = config, make_scenario(scenario)
    n = check_vehicles(n_vehicles)
    rollout = cfg.n_envs * cfg.rollout_steps  # environment steps per update
    if rollout * max(n, cfg.vehicles_max) > MAX_ROLLOUT_AGENT_STEPS:
        raise ConfigError(f"one rollout of n_envs x rollout_steps x N = {cfg.n_envs} x "
                          f"{cfg.rollout_steps} x {max(n, cfg.vehicles_max)} agent-steps exceeds "
                          f"{MAX_ROLLOUT_AGENT_STEPS:,}; lower n_envs or rollout_steps")
    if rollout > total_steps:
        raise ConfigError(f"one rollout is n_envs x rollout_steps = {rollout:,} environment "
                          f"steps, more than the {total_steps:,} asked (--steps); raise --steps "
                          "or lower n_envs or rollout_steps")
    gen = torch.Generator().manual_seed(int(seed))
    torch.manual_seed(int(seed))  # nn.init draws from the global generator
    n_agents = n if cfg.per_agent else 0
    actor, critic = SharedActor(cfg, params, n_agents), Critic(cfg, n_agents)
    bits = {"consensus": 0.0, "qsgd_local": 0.0}  # per agent, ippo-bdc
    qsgd = ErrorFeedbackQSGD(max(cfg.qsgd_levels, 1), gen, cfg.qsgd_bucket)
    opt = torch.optim.Adam([*actor.parameters(), *critic.parameters()], lr=cfg.lr, eps=1e-5)
    def make_env(n_b: int, delay_s: float, loss: float) -> PlatoonEnv:
        return PlatoonEnv(sc, n_b, params, training=True, action_mode=cfg.action_mode,
                          channel=ChannelConfig(delay_s, loss, params.dt_s))

    env = make_env(n, cfg.comm_delay_s, cfg.packet_loss)
    targets = (sc.target_gap_m, sc.target_speed_mps)
    p0 = float(env.power(np.array([sc.target_speed_mps]), np.array([0.0]))[0])
    baseline = -env.weights.power * p0  # the cruise power's constant part, per running agent-step
    b, t_len = cfg.n_envs, cfg.rollout_steps
    episode = 0

    def sharing_of(n_b: int) -> torch.Tensor:
        idx_n = torch.arange(n_b, dtype=torch.float32)
        return cfg.reward_alpha ** (idx_n[:, None] - idx_n[None, :]).abs()  # (N, N)

    sharing = sharing_of(n)
    n_now = n                                          # followers of the batch running now
    ret_acc = torch.zeros(b, n, dtype=torch.float64)   # discounted return so far, per agent
    ret_stats = [1e-4, 0.0, 1.0]                       # count, mean, var of those returns

    def new_episodes() -> torch.Tensor:
        nonlocal episode, env, n_now, sharing, ret_acc
        seeds = training_episode_seeds(seed, episode, b)
        episode += b
        if cfg.randomised:  # this batch's N and V2V, from the run's generator
            n_lo, n_hi = cfg.vehicles_min or n, cfg.vehicles_max or n
            if n_lo > n_hi:
                raise ConfigError(f"the vehicles range {n_lo}..{n_hi} is empty")
            n_now = n_lo + int(torch.randint(n_hi - n_lo + 1, (1,), generator=gen))
            steps_hi = round(max(cfg.comm_delay_max_s, cfg.comm_delay_s) / params.dt_s)
            steps_lo = round(cfg.comm_delay_s / params.dt_s)
            delay = params.dt_s * (steps_lo + int(torch.randint(
                steps_hi - steps_lo + 1, (1,), generator=gen)))
            loss_hi = max(cfg.packet_loss_max, cfg.packet_loss)
            loss = cfg.packet_loss + (loss_hi - cfg.packet_loss) * float(
                torch.rand(1, generator=gen, dtype=torch.float64))
            env = make_env(n_now, delay, loss)
            sharing = sharing_of(n_now)
            ret_acc = torch.zeros(b, n_now, dtype=torch.float64)
        ret_acc.zero_()
        return torch.from_numpy(agent_inputs(env.reset(seeds), cfg.action_mode))

    def reward_std(reward: torch.Tensor, live: torch.Tensor) -> float:
        """Update the running variance of the discounted return with this step's rewards."""
        ret_acc.mul_(cfg.gamma).add_(reward.double())
        x = ret_acc[live]
        if len(x):
            n_a, mean_a, var_a = ret_stats
            n_b, mean_b, var_b = float(x.numel()), float(x.mean()), float(x.var(unbiased=False))
            tot = n_a + n_b
            delta = mean_b - mean_a
            ret_stats[:] = [tot, mean_a + delta * n_b / tot,
                            (var_a * n_a + var_b * n_b + delta**2 * n_a * n_b / tot) / tot]
        return math.sqrt(ret_stats[2] + 1e-8)

    obs = new_episodes()
    steps, updates, next_eval = 0, 0, 0
    curve: list[dict[str, float]] = []
    best: dict[str, float] = {}
    best_state = as_shipped(actor).state_dict()
    n_updates = max(1, math.ceil(total_steps / (b * t_len)))
    d = cfg.obs_dim
    t0 = time.perf_counter()
    while steps < total_steps:
        if validate and steps >= next_eval:
            shipped = as_shipped(actor)
            score = validation_score(shipped, sc, n, params, cfg)
            curve.append({"steps": float(steps), **score})
            if not best or (score["collisions"], -score["reward"]) <= (best["collisions"], -best["reward"]):
                best = {"steps": float(steps), **score}
                best_state = shipped.state_dict()
            if log:
                log(f"{cfg.algo} {sc.id} seed {seed}: {steps} steps, validation reward "
                    f"{score['reward']:.1f}, collisions {score['collisions']:.0f}")
            next_eval += cfg.eval_every_steps
        # ---- rollout: T steps of B episodes (fewer where a randomised batch ends)
        n_r = n_now
        buf_obs = torch.zeros(t_len, b, n_r, d)
        buf_cobs = torch.zeros(t_len, b, n_r, d * (2 if critic.central else 1) + critic.timed)
        buf_act = torch.zeros(t_len, b, n_r)
        buf_logp = torch.zeros(t_len, b, n_r)
        buf_val = torch.zeros(t_len + 1, b, n_r)
        buf_rew = torch.zeros(t_len, b, n_r)
        buf_live = torch.zeros(t_len, b)     # the step belongs to a running episode
        buf_cont = torch.zeros(t_len, b)     # the episode goes on after the step
        buf_term_value = torch.zeros(t_len, b, n_r)  # value after an ending: absorbing or bootstrap
        for t in range(t_len):
            s = env.state
            assert s is not None
            live = ~s.done
            with torch.no_grad():
                actor.update_obs_stats(obs[torch.from_numpy(live)])
                nobs = actor.normalise(obs)
                out = actor.policy(nobs)
                if actor.continuous:
                    action = out + actor.log_std.exp() * torch.randn(out.shape, generator=gen)
                else:
                    u = torch.rand(out.shape, generator=gen).clamp_(1e-12, 1.0)
                    action = (out - torch.log(-torch.log(u))).argmax(-1).to(out.dtype)
                logp, _ = actor.log_prob_entropy(out, action)
                buf_cobs[t] = critic.inputs(nobs, s.step / env.n_steps)
                buf_val[t] = critic.body(buf_cobs[t])[..., 0]
            res = env.step(to_command(actor, action, env.state, env.params, obs.numpy(), targets))
            buf_obs[t], buf_act[t], buf_logp[t] = nobs, action, logp
            live_t = torch.from_numpy(live)
            buf_live[t] = live_t.float()
            reward = (torch.from_numpy(res.reward.astype(np.float32)) + baseline) * live_t[:, None]
            if cfg.reward_alpha > 0:
                reward = reward @ sharing
            std = reward_std(reward, live_t)
            buf_rew[t] = (reward / std).clamp_(-cfg.reward_clip, cfg.reward_clip)
            ended = torch.from_numpy(res.done & live)
            collided = torch.from_numpy(res.collided & live)
            buf_cont[t] = (~ended).float()
            remaining = env.n_steps - s.step
            absorbing = _absorbing(env.weights.collision, cfg.gamma, remaining) / std
            if res.done.all():
                next_obs = new_episodes()
                with torch.no_grad():  # truncated at the time limit: bootstrap from the last
                    # state; a time-aware critic knows the time is up (a finite horizon: 0)
                    last = torch.zeros(b, n_r) if cfg.critic_time else critic(actor.normalise(
                        torch.from_numpy(agent_inputs(res.observation, cfg.action_mode))))
            else:
                next_obs = torch.from_numpy(agent_inputs(res.observation, cfg.action_mode))
                last = None
            if ended.any():
                if last is None:
                    with torch.no_grad():
                        last = critic(actor.normalise(next_obs), s.step / env.n_steps)
                term_value = torch.where(collided[:, None], torch.tensor(absorbing), last)
                buf_term_value[t] = term_value * ended[:, None]
            obs = next_obs
            steps += int(live.sum())
            if cfg.randomised and res.done.all() and t + 1 < t_len:
                t_len_r = t + 1  # the next batch may have another N: this rollout ends here
                break
        else:
            t_len_r = t_len
            if obs.shape[-2] == n_r:  # else every episode ended at the last step (unread)
                now = env.state
                assert now is not None
                with torch.no_grad():
                    buf_val[t_len] = critic(actor.normalise(obs), now.step / env.n_steps)
        if t_len_r < t_len:  # every episode ended at the last step: no value after it is read
            buf_obs, buf_cobs, buf_act, buf_logp, buf_rew, buf_live, buf_cont, buf_term_value = (
                x[:t_len_r] for x in (buf_obs, buf_cobs, buf_act, buf_logp, buf_rew, buf_live,
                                      buf_cont, buf_term_value))
            buf_val = buf_val[: t_len_r + 1]
            adv_len = t_len_r
        else:
            adv_len = t_len
        # ---- returns: GAE over the rollout, ended episodes closed by their terminal value
        adv = torch.zeros(adv_len, b, n_r)
        last_gae = torch.zeros(b, n_r)
        for t in reversed(range(adv_len)):
            cont = buf_cont[t][:, None]
            next_value = buf_val[t + 1] * cont + buf_term_value[t]
            delta = buf_rew[t] + cfg.gamma * next_value - buf_val[t]
            last_gae = delta + cfg.gamma * cfg.gae_lambda * cont * last_gae
            adv[t] = last_gae
        ret = adv + buf_val[:adv_len]
        # ---- PPO update on the live agent-steps (per agent: live episode-steps of N agents)
        if cfg.per_agent:
            keep = buf_live.bool().reshape(-1)
            flat = [x.reshape(adv_len * b, *x.shape[2:])[keep]
                    for x in (buf_obs, buf_cobs, buf_act, buf_logp, adv, ret)]
            mb_rows = max(1, cfg.minibatch_rows // n)
        else:
            keep = buf_live.bool()[:, :, None].expand(adv_len, b, n_r).reshape(-1)
            flat = [x.reshape(-1, *x.shape[3:])[keep]
                    for x in (buf_obs, buf_cobs, buf_act, buf_logp, adv, ret)]
            mb_rows = cfg.minibatch_rows
        f_obs, f_cobs, f_act, f_logp, f_adv, f_ret = flat
        rows = f_obs.shape[0]
        frac = 1.0 - updates / n_updates
        for g in opt.param_groups:
            g["lr"] = cfg.lr * frac
        for _ in range(cfg.epochs):
            order = torch.randperm(rows, generator=gen)
            for start in range(0, rows, mb_rows):
                idx = order[start:start + mb_rows]
                mb_adv = f_adv[idx]
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
                out = actor.policy(f_obs[idx])
                logp, ent = actor.log_prob_entropy(out, f_act[idx])
                ratio = (logp - f_logp[idx]).exp()
                pg = torch.max(-mb_adv * ratio,
                               -mb_adv * ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef)).mean()
                v_loss = 0.5 * (critic.body(f_cobs[idx])[..., 0] - f_ret[idx]).pow(2).mean()
                loss = cfg.vf_coef * v_loss
                if updates >= cfg.critic_warmup_updates:
                    loss = loss + pg - cfg.ent_coef * ent.mean()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                # apart: the critic's gradient (returns of hundreds) must not shrink the actor's
                nn.utils.clip_grad_norm_(actor.parameters(), cfg.max_grad_norm)
                nn.utils.clip_grad_norm_(critic.parameters(), cfg.max_grad_norm)
                if cfg.per_agent:
                    _compress_critic_gradients(critic, qsgd, cfg, bits)
                opt.step()
                if cfg.per_agent:  # BDC: one synchronous round on the critics' weights
                    n_weights = consensus_round(critic.parameters(),
                                                functools.partial(bdc, eps=cfg.consensus_eps))
                    bits["consensus"] += ternary_bits(n_weights)
        updates += 1
        check_finite_weights((actor, critic), f"{cfg.algo} on {sc.id}, seed {seed}",
                             f"{updates} updates ({steps} environment steps)")
    rate = steps / max(time.perf_counter() - t0, 1e-9)
    if validate:
        shipped = as_shipped(actor)
        score = validation_score(shipped, sc, n, params, cfg)
        curve.append({"steps": float(steps), **score})
        if (score["collisions"], -score["reward"]) <= (best["collisions"], -best["reward"]):
            best = {"steps": float(steps), **score}
            best_state = shipped.state_dict()
        actor.load_state_dict(best_state)
    else:
        actor = as_shipped(actor)
    return PPOResult(actor, steps, curve, best, rate, cfg, bits if cfg.per_agent else {})


def _compress_critic_gradients(critic: Critic, qsgd: ErrorFeedbackQSGD, cfg: PPOConfig,
                               bits: dict[str, float]) -> None:
    """``ippo-bdc``: every critic gradient replaced by its QSGD compression with error
    feedback before the step (applied locally, as :func:`marl.bdc.compress_critic_gradients`;
    its payload tallied per agent)."""
    if cfg.qsgd_levels == 0:
        return
    grads = [p.grad for p in critic.parameters() if p.grad is not None]
    for g, q in zip(grads, qsgd.compress(grads), strict=True):
        g.copy_(q)
        bits["qsgd_local"] += qsgd_bits(g[0].numel(), cfg.qsgd_levels, bucket=cfg.qsgd_bucket)


def _absorbing(penalty: float, gamma: float, remaining: int) -> float:
    """The collision penalty at each of ``remaining`` steps, discounted."""
    if remaining <= 0:
        return 0.0
    return penalty * remaining if gamma == 1 else penalty * (1 - gamma**remaining) / (1 - gamma)
