"""The learner: on-policy A2C of one run of N agents, in the order it runs.

Read top to bottom, as a CleanRL file: **config** (:class:`marl.config.A2CConfig`), **networks**
(:mod:`marl.networks`), **rollout** state (:class:`Run`, :class:`Segment`, :class:`Batch`),
**returns**, **loss** (:func:`segment_loss`), then the :class:`Trainer`: its rollout loop
(:meth:`Trainer.train`) and its **update** (recompute with gradient, loss, backward, per-agent
clipping, the algorithm's hooks, RMSprop). Around it: :mod:`marl.population` (K runs at once,
each exactly as alone), :mod:`marl.selection` (validation and checkpoint selection),
:mod:`marl.acting` (acting from a checkpoint). Each algorithm file (``ia2c.py`` ... ``bdc.py``)
fills an :class:`marl.config.Algorithm`.

Published A2C (``docs/spec/marl.md``): n-step segments (60 steps; every episode length and
published collision end is a multiple of 60), bootstrap from V of the next observation (0 if
terminal), truncated backprop through the LSTM within a segment, entropy bonus, per-agent
grad-norm clip, RMSprop. The acting LSTM state advances once per observation: at a segment
boundary the next segment starts from the state the bootstrap used, acting again with the
updated weights. B episodes run in one batched :class:`envs.platoon.PlatoonEnv`
(``training=True, collision_mode="published"``); a step of B active episodes counts as B steps.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from envs.params import RewardWeights
from envs.platoon import PlatoonEnv, StepResult
from envs.scenarios import Scenario, make_scenario
from infra.errors import TrainingDivergedError
from infra.limits import training_episode_seeds
from marl.config import A2CConfig, Algorithm, training_device
from marl.layers import per_agent_clip_, rmsprop_, sqrt
from marl.networks import AgentNet, State, exchange, neighbour_action_onehot

# ---------------------------------------------------------------------------- config
# :class:`marl.config.A2CConfig`: every hyper-parameter, the paper's values as defaults.
# ---------------------------------------------------------------------------- networks
# :mod:`marl.networks`: N agents' actor-critics batched as one module.


# ---------------------------------------------------------------------------- rollout
@dataclass
class Run:
    """One training run: everything of its own.

    Its random stream, environment settings, optimiser rates, return statistics, step counts,
    bit tallies and algorithm state (``hook_state``); in a population
    (:mod:`marl.population`) the runs share only the stacked network tensors, each owning its
    agent rows ``rows``, so each run trains exactly as it would alone.
    """

    index: int
    seed: int
    #: the resolved config (``reward_alpha`` and ``power_baseline_kw`` filled in)
    config: A2CConfig
    generator: torch.Generator
    #: its environment's settings (reward weights, length, physics); its episodes run in
    #: batched envs shared with the runs whose batch starts at the same step
    env: PlatoonEnv
    #: its agents' rows in the stacked network, ``slice(index N, (index + 1) N)``
    rows: slice
    #: per running agent and step, added to the env's reward: ``-w5 P0`` (0 as published)
    baseline_reward: float
    #: the run's step budget (entropy schedule); :func:`marl.selection.run_population` sets it
    total_steps: int = 0
    steps: int = 0
    episodes: int = 0
    updates: int = 0
    #: training bits over the run, per agent: consensus messages sent to the neighbours,
    #: and the payload of QSGD-compressed gradients that are applied locally (sent nowhere)
    bits: dict[str, float] = field(default_factory=lambda: {"consensus": 0.0, "qsgd_local": 0.0})
    episode_counter: int = 0
    #: running (count, mean, sum of squared deviations) of discounted returns (return_norm)
    return_stats: tuple[float, float, float] = (0.0, 0.0, 0.0)
    return_acc: torch.Tensor = field(default_factory=lambda: torch.zeros(0))
    #: what an algorithm keeps between updates (BDC: its QSGD residuals)
    hook_state: dict[str, Any] = field(default_factory=dict)
    #: why the run stopped early (its weights became non-finite), None while it is healthy
    failed: str | None = None

    def training_seeds(self, batch: int) -> np.ndarray:
        """Env seeds of the run's next ``batch`` training episodes."""
        seeds = training_episode_seeds(self.seed, self.episode_counter, batch)
        self.episode_counter += batch
        return seeds

    def uniforms(self, shape: tuple[int, ...]) -> torch.Tensor:
        """The run's uniforms for one sampling step (Gumbel-max over the last axis)."""
        g = self.generator  # on the CPU whatever the training device
        return torch.rand(shape, generator=g, device=g.device).clamp_(1e-12, 1.0)

    def learning_rates(self) -> tuple[float, float]:
        """RMSprop rates of actor and critic parameters."""
        cfg = self.config
        return cfg.actor_lr * cfg.lr_scale, cfg.critic_lr * cfg.lr_scale

    @torch.no_grad()
    def return_scale(
        self, reward: torch.Tensor, term: torch.Tensor, mask: torch.Tensor
    ) -> torch.Tensor:
        """Running standard deviation of the discounted return (``return_norm``).

        The return of every agent of every running episode is accumulated step by step across
        segments (``G <- gamma G + r``, reset at episode end) and its mean and variance are
        merged into running totals (Chan et al.), as Stable-Baselines3's reward normalisation.
        """
        cfg = self.config
        acc = self.return_acc
        rets = []
        for t in range(reward.shape[0]):
            acc = acc * cfg.gamma + reward[t]
            rets.append(acc)
            acc = acc * (~term[t]).to(acc.dtype).unsqueeze(-1)
        self.return_acc = acc
        x = torch.stack(rets)[mask.expand_as(reward) > 0].to(torch.float64)
        if x.numel():
            n_b, mean_b, var_b = float(x.numel()), float(x.mean()), float(x.var(unbiased=False))
            n_a, mean_a, m2_a = self.return_stats
            n = n_a + n_b
            delta = mean_b - mean_a
            m2 = m2_a + var_b * n_b + delta * delta * n_a * n_b / n
            self.return_stats = (n, mean_a + delta * n_b / n, m2)
        n, _, m2 = self.return_stats
        std = math.sqrt(m2 / n) if n > 0 else 1.0
        return torch.tensor(max(std, 1e-6), dtype=reward.dtype, device=reward.device)

    def absorbing_value(self, remaining_steps: int) -> float:
        """Per-agent value (unscaled, unshared) of a collided state with ``remaining_steps``
        scheduled steps left: the collision penalty at each of them, discounted (0 under
        ``collision_value="published"``)."""
        cfg = self.config
        if cfg.collision_value == "published" or remaining_steps <= 0:
            return 0.0
        penalty = self.env.weights.collision
        g = cfg.gamma
        if g == 1.0:
            return penalty * remaining_steps
        return penalty * (1.0 - g**remaining_steps) / (1.0 - g)


@dataclass
class Segment:
    """One run's part of an n-step segment: per step its rewards ``(B, N)``, running mask,
    terminal flags, absorbing values ``(B,)``; and the bootstrap values ``(B, N)``."""

    rews: list[np.ndarray] = field(default_factory=list)
    masks: list[np.ndarray] = field(default_factory=list)
    terms: list[np.ndarray] = field(default_factory=list)
    absorbed: list[np.ndarray] = field(default_factory=list)
    bootstrap: torch.Tensor | None = None


@dataclass
class Batch:
    """A run's batch of B episodes in progress: the batched env they run in (rows ``rows``; a
    population's runs whose batches start together share one), which still run, their training
    reward and length so far, its open segment (started at step ``seg_start`` of a population's
    loop) and whether it is over."""

    env: PlatoonEnv
    rows: slice
    active: np.ndarray
    ep_reward: np.ndarray
    ep_len: np.ndarray
    seg_start: int = 0
    seg: Segment = field(default_factory=Segment)
    steps: int = 0
    t_episode: int = 0
    done: bool = False


# ---------------------------------------------------------------------------- returns and loss
def sharing_matrix(n_agents: int, alpha: float, dtype: torch.dtype = torch.float32,
                   device: torch.device | str = "cpu") -> torch.Tensor:
    """``(N, N)`` weights ``alpha^|i-j|`` (alpha = 0: own reward only, alpha = 1: global sum)."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"reward-sharing alpha must lie in [0, 1], got {alpha}")
    idx = torch.arange(n_agents, device=device)
    dist = (idx[:, None] - idx[None, :]).abs().to(dtype)
    if alpha == 0.0:
        return torch.eye(n_agents, dtype=dtype, device=device)
    return torch.pow(torch.tensor(alpha, dtype=dtype, device=device), dist)


def share_rewards(reward: torch.Tensor, alpha: float) -> torch.Tensor:
    """Shared rewards ``r'_i = sum_j alpha^|i-j| r_j`` over the last (agent) axis.

    Parameters
    ----------
    reward : (..., N)
        Per-agent rewards.
    alpha : float
        Spatial discount in [0, 1].
    """
    w = sharing_matrix(reward.shape[-1], alpha, reward.dtype, reward.device)
    return reward @ w.T


def nstep_returns(
    reward: torch.Tensor,
    bootstrap: torch.Tensor,
    terminal: torch.Tensor,
    gamma: float,
) -> torch.Tensor:
    """Discounted n-step returns of a segment, bootstrapped from the value after its last step.

    ``R_t = r_t + gamma (1 - terminal_t) R_{t+1}`` with ``R_T = bootstrap``: a terminal step
    (the episode ended after it) cuts both the later rewards and the bootstrap.

    Parameters
    ----------
    reward : (T, B, N)
        Rewards (already shared and scaled).
    bootstrap : (B, N)
        Value estimate of the observation after the last step (anything where terminal).
    terminal : (T, B) or (T, B, N) bool/float
        1 where the episode ended after step t.
    gamma : float
        Discount.

    Returns
    -------
    (T, B, N)
    """
    t_len = reward.shape[0]
    term = terminal.to(reward.dtype)
    if term.dim() == reward.dim() - 1:
        term = term.unsqueeze(-1)
    term = term.expand_as(reward)
    # D_k = number of terminals strictly before step k, k = 0..T
    d = torch.cat([torch.zeros_like(term[:1]), torch.cumsum(term, 0)], 0)  # (T+1, B, N)
    steps = torch.arange(t_len + 1, dtype=reward.dtype, device=reward.device)
    lag = steps[None, :] - steps[:t_len, None]  # (T, T+1): k - t
    disc = torch.where(lag >= 0, torch.pow(
        torch.tensor(gamma, dtype=reward.dtype, device=reward.device), lag.clamp(min=0)), 0.0)
    # k contributes to R_t iff k >= t and no terminal in t..k-1, i.e. D_k == D_t
    same = (d[None, :, ...] == d[:t_len, None, ...]).to(reward.dtype)  # (T, T+1, B, N)
    weights = disc[:, :, None, None] * same
    values = torch.cat([reward, bootstrap.unsqueeze(0)], 0)  # (T+1, B, N)
    return (weights * values.unsqueeze(0)).sum(1)


def a2c_losses(
    logits: torch.Tensor,
    actions: torch.Tensor,
    values: torch.Tensor,
    returns: torch.Tensor,
    mask: torch.Tensor,
    advantage_norm: bool = False,
) -> dict[str, torch.Tensor]:
    """The three terms of the A2C loss over one segment.

    Parameters
    ----------
    logits : (T, N, B, 4)
        Action logits of every agent, step and episode, with gradient.
    actions : (T, N, B) int64
        Actions taken.
    values : (T, N, B)
        Critic values, with gradient.
    returns : (T, B, N)
        n-step returns (targets, no gradient).
    mask : (T, B, 1)
        1 where the episode was running at that step, else 0.
    advantage_norm : bool
        Normalise the advantages over the valid steps (:func:`normalise_advantages`).

    Returns
    -------
    dict with ``policy`` = -sum log pi(a) A, ``value`` = sum (R - V)^2 / 2 and ``entropy`` =
    sum H(pi), each summed over agents and valid steps and divided by the number of valid
    (step, episode) pairs; ``A = R - V``, detached. The learner minimises
    ``policy + value_coef * value - entropy_coef * entropy``.
    """
    logp_all = torch.log_softmax(logits, -1)  # (T, N, B, 4)
    logp = logp_all.gather(-1, actions.unsqueeze(-1)).squeeze(-1).transpose(1, 2)
    ent = -(logp_all.exp() * logp_all).sum(-1).transpose(1, 2)  # (T, B, N)
    values = values.transpose(1, 2)
    count = mask.sum().clamp(min=1.0)
    adv = (returns - values).detach()
    if advantage_norm:
        adv = normalise_advantages(adv, mask)
    return {
        "policy": -(logp * adv * mask).sum() / count,
        "value": 0.5 * ((returns - values).square() * mask).sum() / count,
        "entropy": (ent * mask).sum() / count,
    }


def normalise_advantages(adv: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Advantages ``(T, B, N)`` standardised per agent over the running entries of the segment
    (``mask (T, B, 1)``): zero mean, unit standard deviation (population), each agent alone."""
    m = mask.expand_as(adv)
    count = m.sum((0, 1)).clamp(min=1.0)
    mean = (adv * m).sum((0, 1)) / count
    var = ((adv - mean).square() * m).sum((0, 1)) / count
    return (adv - mean) / (sqrt(var) + 1e-8)


def segment_loss(run: Run, seg: Segment, logits: torch.Tensor, values: torch.Tensor,
                 actions: torch.Tensor, rows: slice) -> torch.Tensor:
    """The run's A2C loss over its segment, from its agents' ``rows`` of the recompute: logits
    ``(A, T, B, 4)``, values and actions ``(A, T, B)``. (Slicing even all rows matters: its
    backward hands the network a contiguous gradient, so one run rounds as in a population.)"""
    cfg, device = run.config, logits.device

    def tensor(parts: list[np.ndarray], dtype: torch.dtype | None = torch.float32) -> torch.Tensor:
        return torch.from_numpy(np.stack(parts)).to(device, dtype)

    mask = tensor(seg.masks).unsqueeze(-1)  # (T, B, 1)
    term = tensor(seg.terms, None)
    # R_t = r_t + gamma V_absorbing at a step that ended the episode by collision
    reward = tensor(seg.rews) + cfg.gamma * tensor(seg.absorbed).unsqueeze(-1)
    assert cfg.reward_alpha is not None and seg.bootstrap is not None
    reward = share_rewards(reward * cfg.reward_scale, cfg.reward_alpha)
    if cfg.return_norm:
        reward = reward / run.return_scale(reward, term, mask)
    returns = nstep_returns(reward, seg.bootstrap, term, cfg.gamma)  # (T, B, N)
    terms = a2c_losses(logits[rows].permute(1, 0, 2, 3), actions[rows].permute(1, 0, 2),
                       values[rows].permute(1, 0, 2), returns, mask, cfg.advantage_norm)
    ent_coef = cfg.entropy_at(run.steps / run.total_steps if run.total_steps else 0.0)
    return terms["policy"] + cfg.value_coef * terms["value"] - ent_coef * terms["entropy"]


# ---------------------------------------------------------------------------- the trainer
class Trainer:
    """On-policy A2C of one run over a batched env: the rollout loop (:meth:`train`), then the
    update of each segment (:meth:`_update`).

    Parameters
    ----------
    algo : Algorithm
    config : A2CConfig
    scenario_id : str
        The scenario's id (it names the checkpoints).
    n_vehicles : int
    seed : int
        The run's seed: its initial weights, its actions' uniforms and its episodes' seeds.
    device : str or torch.device
        Where the network, its gradients and optimiser state live (:func:`training_device`);
        the environments, the random stream and the checkpoints stay on the CPU, so the same
        seed draws the same actions' uniforms on every device.
    scenario : Scenario, optional
        The scenario, when the caller built it already.
    """

    def __init__(self, algo: Algorithm, config: A2CConfig, scenario_id: str, n_vehicles: int,
                 seed: int, device: str | torch.device = "cpu",
                 scenario: Scenario | None = None) -> None:
        scenario = make_scenario(scenario_id) if scenario is None else scenario
        self._start(algo, scenario_id, scenario, n_vehicles, [int(seed)],
                    [config.resolved(scenario)], device)
        self.run = self.runs[0]

    def _start(self, algo: Algorithm, scenario_id: str, scenario: Scenario, n_vehicles: int,
               seeds: Sequence[int], resolved: Sequence[A2CConfig],
               device: str | torch.device) -> None:
        """Build the runs (``resolved``: their configs, ``reward_alpha`` and the power
        baseline filled in), their networks (joined by :meth:`_join`) and the optimiser."""
        torch.set_num_threads(1)
        self.device = training_device(device)
        self.algo, self.scenario_id, self.scenario = algo, scenario_id, scenario
        self.n_vehicles = n = n_vehicles
        self.shape = resolved[0]  # the structural fields (hidden, n_step, episodes_parallel)
        self.runs: list[Run] = []
        nets = []
        for k, (s, cfg) in enumerate(zip(seeds, resolved, strict=True)):
            generator = torch.Generator().manual_seed(s)
            assert cfg.power_baseline_kw is not None
            self.runs.append(Run(k, s, cfg, generator, self._make_env(cfg.reward_weights()),
                                 slice(k * n, (k + 1) * n),
                                 -cfg.reward_w_power * cfg.power_baseline_kw))
            with torch.device("cpu"):  # the same initial weights on every device
                nets.append(algo.build_net(cfg, n, True, generator))
        self.net = self._join(nets).to(self.device)
        #: (parameter, is_critic): actor parameters, then the critic's
        self.params = [(p, False) for p in self.net.actor_parameters()] + [
            (p, True) for p in self.net.critic_parameters()]
        self._square_avg = [torch.zeros_like(p) for p, _ in self.params]  # RMSprop's state
        for run in self.runs:
            algo.setup(run)

    def _join(self, nets: list[AgentNet]) -> AgentNet:
        """The network trained: the run's own."""
        return nets[0]

    # -- rollout
    def train(self, on_batch: Callable[[Run, int, float], bool]) -> None:
        """Train batch after batch of B episodes, an update every n steps, until ``on_batch(run,
        steps, mean_training_reward)``, called after each batch (``run.steps`` counts it), says
        stop. A run that diverges stops there (``run.failed`` says why)."""
        run, b, n = self.run, self.shape.episodes_parallel, self.n_vehicles
        net = self.net
        while True:
            env = self._make_env(run.env.weights)
            first = env.reset(run.training_seeds(b))
            assert first is not None
            obs = self._observation(first)
            run.return_acc = torch.zeros(b, n, device=self.device)
            bt = Batch(env, slice(0, b), np.ones(b, dtype=bool), np.zeros(b), np.zeros(b))
            state = net.initial_state(b)
            cur = self._act(obs, state)
            history: list[tuple[State, dict[str, Any]]] = []  # the open segment's steps
            while True:
                history.append((state, cur))
                res = env.step_actions(cur["actions"].cpu().T.numpy())
                self._record(run, bt, res)
                nxt: dict[str, Any] | None = None
                if bt.done:  # every episode ended: the segment bootstraps from 0
                    bt.seg.bootstrap = torch.zeros(b, n, device=self.device)
                else:  # act on the next observation, with the weights before any update
                    assert res.observation is not None
                    obs = self._observation(res.observation)
                    nxt = self._act(obs, cur["state"])
                    if len(bt.seg.rews) < self.shape.n_step:
                        state, cur = cur["state"], nxt
                        continue
                    if not net.separate_critic:  # (a separate critic's: in the update)
                        with torch.no_grad():
                            bt.seg.bootstrap = net.value(nxt["out"], neighbour_action_onehot(
                                nxt["actions"], net.platoon_size)).T
                # the segment ends: one update
                critic_after = self._update(history[0][0], [h[1] for h in history], bt.seg, nxt)
                # most episodes ended (published collision rule): truncate the rest (their last
                # segment was bootstrapped) instead of stepping finished episodes
                if (bt.done or run.failed is not None
                        or bt.active.sum() < run.config.min_active_fraction * b):
                    break
                # the next segment starts from the same observation and state, acting again
                # with the new weights (a separate critic's state is its recompute's end)
                state = cur["state"] | critic_after
                cur, history, bt.seg = self._act(obs, state), [], Segment()
            if run.failed is not None:
                return
            run.steps += bt.steps
            run.episodes += b
            if not on_batch(run, bt.steps, float((bt.ep_reward / np.maximum(bt.ep_len, 1)).mean())):
                return

    @torch.no_grad()
    def _act(self, obs: torch.Tensor, state: State) -> dict[str, Any]:
        """No-grad acting step: observations ``(N, B, 15)``, messages received, logits, actions
        sampled (Gumbel-max with the run's uniforms), next state."""
        net = self.net
        front, rear = exchange(net, state)
        logits, out, new = net.act_step(obs, state, front, rear, critic=not net.separate_critic)
        u = self.run.uniforms((self.n_vehicles,) + tuple(logits.shape[1:])).to(self.device)
        actions = (logits - torch.log(-torch.log(u))).argmax(-1)
        return {"obs": obs, "front": front, "rear": rear, "out": out, "logits": logits,
                "actions": actions, "state": new}

    def _record(self, r: Run, bt: Batch, res: StepResult) -> Batch:
        """Record the run's rows of its env's step ``res`` in its batch and open segment."""
        sg, act, rows = bt.seg, bt.active, bt.rows
        done, collided, reward = res.done[rows], res.collided[rows], res.reward[rows]
        bt.t_episode += 1
        sg.masks.append(act.copy())
        sg.terms.append(done & act)
        if r.baseline_reward:
            running = act & ~collided
            sg.rews.append(reward + r.baseline_reward * running[:, None])
        else:
            sg.rews.append(reward)
        crashed = done & collided & act
        sg.absorbed.append(
            r.absorbing_value(r.env.n_steps - bt.t_episode) * crashed
            if crashed.any() else np.zeros(len(act))
        )
        bt.steps += int(act.sum())
        bt.ep_reward += np.where(act, sg.rews[-1].sum(1), 0.0)
        bt.ep_len += act
        bt.active = ~done
        bt.done = bool(done.all())
        return bt

    def _observation(self, obs_np: np.ndarray) -> torch.Tensor:
        """Env observations ``(B, N, 15)`` -> agent-major ``(N, B, 15)``."""
        return torch.from_numpy(obs_np).transpose(0, 1).contiguous().to(self.device)

    def _make_env(self, weights: RewardWeights) -> PlatoonEnv:
        """A batched training env of the scenario (published collision rule, ``weights``)."""
        return PlatoonEnv(self.scenario, self.n_vehicles, training=True,
                          collision_mode="published", weights=weights)

    # -- update
    def _update(self, seg_state: State, record: list[dict[str, Any]], seg: Segment,
                nxt: dict[str, Any] | None) -> State:
        """One update on the segment that starts from ``seg_state`` (``record``: its acts).

        With a separate critic, the bootstrap of a segment whose batch goes on is computed here
        from the recompute's critic state and ``nxt`` (the act on the next observation), with
        the weights before the update; returns that critic state after the segment."""
        logits, values, actions, after = self._recompute(seg_state, record)
        critic_after = self._critic_bootstrap(seg, after, nxt)
        self._optimise(segment_loss(self.run, seg, logits, values, actions, self.run.rows),
                       [self.run])
        return critic_after

    def _recompute(self, seg_state: State, record: list[dict[str, Any]]
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, State]:
        """Re-run the segment with gradient: logits ``(N, T, B, 4)``, values and actions
        ``(N, T, B)`` and the recurrent state after the segment."""
        obs, actions, msgs = self._segment_inputs(record)
        logits, values, after = self.net(seg_state, obs, actions, msgs)
        return logits, values, actions, after

    def _segment_inputs(self, record: list[dict[str, Any]]) -> tuple[Any, Any, Any]:
        """The segment's observations, actions and (gradient-free) messages ``(A, T, ...)``."""
        obs = torch.stack([r["obs"] for r in record], 1)
        actions = torch.stack([r["actions"] for r in record], 1)
        msgs = None
        if not self.net.differentiable_messages and record[0]["front"] is not None:
            msgs = (torch.stack([r["front"] for r in record], 1),
                    torch.stack([r["rear"] for r in record], 1))
        return obs, actions, msgs

    @torch.no_grad()
    def _critic_bootstrap(self, seg: Segment, after: State, nxt: dict[str, Any] | None) -> State:
        """For a separate critic and a batch that goes on: the segment's bootstrap (the critic
        one step on from the segment's end, on the next observation) and its critic state at the
        segment's end (empty otherwise)."""
        net = self.net
        if not net.separate_critic or seg.bootstrap is not None:
            return {}
        assert nxt is not None
        critic = {k: after[k].detach().clone() for k in ("ch", "cc")}
        out, _ = net.critic_features(nxt["obs"], critic)
        seg.bootstrap = net.value(out, neighbour_action_onehot(nxt["actions"], net.platoon_size)).T
        return critic

    def _optimise(self, loss: torch.Tensor, runs: list[Run]) -> None:
        """Backward of ``loss`` (the sum of ``runs``' losses: this trainer's one run, or a
        population's group), per-agent clipping, the algorithm's hooks around RMSprop, and the
        divergence check."""
        for p, _ in self.params:
            if p.grad is not None:
                p.grad.zero_()
        loss.backward()
        self._clip(runs)
        for r in runs:
            self.algo.before_step(r, self.net)
        self._rmsprop_step(runs)
        for r in runs:
            self.algo.after_step(r, self.net)
            r.updates += 1
        if not all(bool(torch.isfinite(p).all()) for p, _ in self.params):
            for r in runs:
                self._check_finite(r)

    def _clip(self, runs: list[Run]) -> None:
        """Clip each agent's gradient to the run's global norm (``grad_clip``)."""
        per_agent_clip_([p for p, _ in self.params], self.run.config.grad_clip)

    @torch.no_grad()
    def _rmsprop_step(self, runs: list[Run]) -> None:
        """RMSprop (no momentum, not centred; the arithmetic of ``torch.optim.RMSprop``), the
        actor's and the critic's rates."""
        cfg = self.run.config
        lrs = self.run.learning_rates()
        for (p, is_critic), sq in zip(self.params, self._square_avg, strict=True):
            assert p.grad is not None
            rmsprop_(p, p.grad, sq, lrs[is_critic], cfg.rmsprop_alpha, cfg.rmsprop_eps)

    def _check_finite(self, run: Run) -> None:
        """Stop a run whose weights became non-finite (a NaN policy would act as "action 0"
        everywhere); its rows are zeroed so nothing non-finite stays in the network."""
        bad = [name for name, p in self.net.named_parameters()
               if not bool(torch.isfinite(p[run.rows]).all())]
        if bad:
            run.failed = (
                f"{self.algo.name} on {self.scenario_id}, seed {run.seed}: weights "
                f"{', '.join(bad)} became non-finite after {run.updates} updates ({run.steps} "
                "environment steps before this batch); lower the learning rates (actor_lr, "
                "critic_lr, lr_scale) or check the algorithm's options. The best checkpoint "
                "evaluated so far is kept."
            )
            with torch.no_grad():
                for p in self.net.parameters():
                    p[run.rows] = 0.0

    # -- what the layers above read
    def run_batch(self) -> list[tuple[int, float]]:
        """Train one batch; returns ``[(environment steps, mean training reward)]`` (mean over
        steps of the sum over agents). Raises :class:`TrainingDivergedError` if it diverged."""
        out: list[tuple[int, float]] = []

        def once(run: Run, steps: int, reward: float) -> bool:
            out.append((steps, reward))
            return False

        self.train(once)
        if self.run.failed is not None:
            raise TrainingDivergedError(self.run.failed)
        return out
