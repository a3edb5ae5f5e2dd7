"""The one training loop of the paper's seven algorithms: on-policy A2C of K runs at once (a
single run is a population of one), each exactly as it would train alone, in the order it runs.

Read top to bottom, as a CleanRL file: **config** (:class:`marl.config.A2CConfig`), **networks**
(:mod:`marl.networks`; K runs' stacked as one by :func:`stack_nets`), **rollout** state
(:class:`Run`, :class:`Segment`, :class:`Batch`), **returns**, **loss** (:func:`segment_loss`),
then the :class:`Trainer`: its rollout loop (:meth:`Trainer.train`) and its **update**
(recompute with gradient, loss, backward, per-agent clipping, the algorithm's hooks, RMSprop).
Around it: :mod:`marl.selection` (validation and checkpoint selection), :mod:`marl.acting`
(acting from a checkpoint). Each algorithm file (``ia2c.py`` ... ``bdc.py``) fills an
:class:`marl.config.Algorithm`.

Published A2C (``docs/spec/marl.md``): n-step segments (60 steps; every episode length and
published collision end is a multiple of 60), bootstrap from V of the next observation (0 if
terminal), truncated backprop through the LSTM within a segment, entropy bonus, per-agent
grad-norm clip, RMSprop. The acting LSTM state advances once per observation: at a segment
boundary the next segment starts from the state the bootstrap used, acting again with the
updated weights. B episodes run in one batched :class:`envs.platoon.PlatoonEnv`
(``training=True, collision_mode="published"``); a step of B active episodes counts as B steps.

K runs (``docs/populations.md``) are one network of ``K N`` agents (every layer is per agent,
:mod:`marl.layers`): each step acts for all runs in one forward, each update is one backward of
the runs whose segments ended, and what crosses agents (messages, the critics' neighbour
actions, consensus, reward sharing) stays inside a run's platoon. Each run steps its own env,
ends its own segments and batches, draws from its own generator in the order it would alone and
keeps its own statistics and optimiser state (tested to the last bit against runs alone).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from envs.dynamics import OBS_DIM
from envs.params import RewardWeights
from envs.platoon import PlatoonEnv, StepResult
from envs.scenarios import Scenario, make_scenario
from infra.errors import ConfigError, TrainingDivergedError
from infra.limits import training_episode_seeds
from marl.checkpoint import plain_state, restore_state
from marl.config import A2CConfig, Algorithm, training_device
from marl.layers import module_tensors, per_agent_clip_, rmsprop_, sqrt
from marl.networks import AgentNet, State, exchange, neighbour_action_onehot

# ---------------------------------------------------------------------------- config
# :class:`marl.config.A2CConfig`: every hyper-parameter, the paper's values as defaults.

#: Structural fields every run of a population shares (they shape the stacked tensors and the
#: segment loop); the others may differ from run to run.
POPULATION_SHARED_FIELDS: tuple[str, ...] = ("hidden", "n_step", "episodes_parallel")


# ---------------------------------------------------------------------------- networks
# :mod:`marl.networks`: N agents' actor-critics batched as one module.
def stack_nets(algo: Algorithm, config: A2CConfig, nets: Sequence[AgentNet]) -> AgentNet:
    """One network of ``K N`` agents holding the K runs' networks' weights (and buffers) in
    order; its ``platoon_size`` is N (one run: its own network)."""
    if len(nets) == 1:
        return nets[0]
    n = nets[0].n_agents
    big = algo.build_net(config, n * len(nets), True, torch.Generator().manual_seed(0))
    parts = [module_tensors(net) for net in nets]
    with torch.no_grad():
        for name, t in module_tensors(big).items():
            t.copy_(torch.cat([part[name] for part in parts]))
    big.platoon_size = n
    return big


# ---------------------------------------------------------------------------- rollout
@dataclass
class Run:
    """One training run: everything of its own.

    Its random stream, environment settings, optimiser rates, return statistics, step counts,
    bit tallies and algorithm state (``hook_state``); the runs of a :class:`Trainer` share only
    the stacked network tensors, each owning its agent rows ``rows``, so each run trains exactly
    as it would alone.
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
        scheduled steps left (:func:`absorbing_value`; 0 under ``collision_value="published"``)."""
        cfg = self.config
        if cfg.collision_value == "published":
            return 0.0
        return absorbing_value(self.env.weights.collision, cfg.gamma, remaining_steps)


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
    """A run's batch of B episodes in progress: the batched env they run in (rows ``rows``; the
    runs whose batches start together share one), which still run, their training reward and
    length so far, its open segment (started at step ``seg_start`` of the loop) and whether it
    is over."""

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

    def record(self, run: Run, res: StepResult) -> None:
        """Record the batch's rows of its env's step ``res`` (rewards with the run's baseline
        term, terminals, absorbing values) in the batch and its open segment."""
        sg, act = self.seg, self.active
        done, collided, reward = res.done[self.rows], res.collided[self.rows], res.reward[self.rows]
        self.t_episode += 1
        sg.masks.append(act.copy())
        sg.terms.append(done & act)
        if run.baseline_reward:
            running = act & ~collided
            sg.rews.append(reward + run.baseline_reward * running[:, None])
        else:
            sg.rews.append(reward)
        crashed = done & collided & act
        sg.absorbed.append(
            run.absorbing_value(run.env.n_steps - self.t_episode) * crashed
            if crashed.any() else np.zeros(len(act))
        )
        self.steps += int(act.sum())
        self.ep_reward += np.where(act, sg.rews[-1].sum(1), 0.0)
        self.ep_len += act
        self.active = ~done
        self.done = bool(done.all())


# ---------------------------------------------------------------------------- returns and loss
def absorbing_value(penalty: float, gamma: float, remaining: int) -> float:
    """What a collided state is worth with ``remaining`` scheduled steps left: the collision
    ``penalty`` at each of them, discounted by ``gamma``."""
    if remaining <= 0:
        return 0.0
    return penalty * remaining if gamma == 1 else penalty * (1 - gamma**remaining) / (1 - gamma)


def sharing_matrix(n_agents: int, alpha: float, dtype: torch.dtype = torch.float32,
                   device: torch.device | str = "cpu") -> torch.Tensor:
    """``(N, N)`` weights ``alpha^|i-j|`` (alpha = 0: own reward only, alpha = 1: global sum)."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"reward-sharing alpha must lie in [0, 1], got {alpha}")
    idx = torch.arange(n_agents, device=device)
    dist = (idx[:, None] - idx[None, :]).abs().to(dtype)  # alpha = 0: 0^0 = 1, the identity
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
    backward hands the network a contiguous gradient, so a run rounds alike in every group.)"""
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
    """On-policy A2C of K runs of one algorithm at once (K = 1: one run): the rollout loop
    (:meth:`train`), then the update of each ended segment (:meth:`_update`).

    Parameters
    ----------
    algo : Algorithm
    config : A2CConfig or sequence of them
        One config for every run, or one per run (equal in :data:`POPULATION_SHARED_FIELDS`).
    scenario_id : str
        The scenario's id (it names the checkpoints).
    n_vehicles : int
    seed : int or sequence of int
        The runs' seeds (one int: one run): each run's initial weights, its actions' uniforms
        and its episodes' seeds.
    device : str or torch.device
        Where the network, its gradients and optimiser state live (:func:`training_device`);
        the environments, the random streams and the checkpoints stay on the CPU, so the same
        seed draws the same actions' uniforms on every device.
    scenario : Scenario, optional
        The scenario, when the caller built it already.
    """

    def __init__(
        self,
        algo: Algorithm,
        config: A2CConfig | Sequence[A2CConfig],
        scenario_id: str,
        n_vehicles: int,
        seed: int | Sequence[int],
        device: str | torch.device = "cpu",
        scenario: Scenario | None = None,
    ) -> None:
        seeds = [int(seed)] if isinstance(seed, int | np.integer) else [int(s) for s in seed]
        configs = [config] * len(seeds) if isinstance(config, A2CConfig) else list(config)
        if not seeds or len(configs) != len(seeds):
            raise ConfigError(
                f"a population needs one config per seed (got {len(configs)} configs for "
                f"{len(seeds)} seeds)")
        # built once (or by the caller), for the config and every env of every run
        self.scenario = make_scenario(scenario_id) if scenario is None else scenario
        resolved = [c.resolved(self.scenario) for c in configs]
        for f in POPULATION_SHARED_FIELDS:
            values = {getattr(c, f) for c in resolved}
            if len(values) > 1:
                raise ConfigError(
                    f"the runs of one population must share {f} (got {sorted(values)}); "
                    "train them in separate populations")
        torch.set_num_threads(1)
        self.device = training_device(device)
        self.algo, self.scenario_id, self.n_vehicles = algo, scenario_id, n_vehicles
        self.shape = resolved[0]  # the structural fields (hidden, n_step, episodes_parallel)
        n = n_vehicles
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
        with torch.device("cpu"):
            self.net = stack_nets(algo, self.shape, nets).to(self.device)
        #: (parameter, is_critic): actor parameters, then the critic's
        self.params = [(p, False) for p in self.net.actor_parameters()] + [
            (p, True) for p in self.net.critic_parameters()]
        self._square_avg = [torch.zeros_like(p) for p, _ in self.params]  # RMSprop's state
        for run in self.runs:
            algo.setup(run)

    # -- rollout
    def train(self, on_batch: Callable[[Run, int, float], bool],
              runs: Sequence[Run] | None = None) -> None:
        """Train ``runs`` (default all) batch after batch of B episodes, an update of a run every
        n steps, until ``on_batch`` says stop for each.

        The runs run free: every step acts for the whole stack at once, and each run steps its
        own env, ends its own segments (an update of exactly its rows) and batches, and starts
        its next batch at once. ``on_batch(run, steps, mean_training_reward)`` is called when a
        run's batch ended (after ``run.steps`` counts it) and returns whether the run goes on.
        A run that diverges stops there (``run.failed`` says why).
        """
        live = list(self.runs if runs is None else runs)
        b = self.shape.episodes_parallel
        # each run's latest observation (N, B, 15); an idle run's are acted on and ignored
        obs = [torch.zeros(self.n_vehicles, b, OBS_DIM, device=self.device) for _ in self.runs]
        batch = self._start_batches(live, obs, 0)
        state = self.net.initial_state(b)
        cur: dict[str, Any] | None = self._act(torch.cat(obs), state, live)
        #: per step since ``base``: the state acted from and what the act gave
        history: list[tuple[State, dict[str, Any]]] = []
        base = tick = 0
        while True:
            assert cur is not None
            history.append((state, cur))
            state = cur["state"]
            # 1. every live run steps its env: some segments (``ending``) and batches (``over``)
            # end at this step (a finished batch's segment bootstraps from 0)
            ending, over = self._step_envs(live, batch, cur["actions"], obs)
            # 2. act on the next observations, with the weights before any update; a critic
            # sharing the actor's trunk bootstraps a segment that ends mid-batch from it (a
            # separate critic's bootstrap comes from its recompute, in the update)
            going = [r for r in live if r.index not in over]
            cur = self._act(torch.cat(obs), state, going) if going else None
            boot = [r for r in ending if r.index not in over]
            if boot and not self.net.separate_critic:
                assert cur is not None
                with torch.no_grad():
                    values = self.net.value(cur["out"], neighbour_action_onehot(
                        cur["actions"], self.net.platoon_size))
                for r in boot:
                    batch[r.index].seg.bootstrap = values[r.rows].T
            # 3. one update per segment length of the runs whose segment ended (a segment of T
            # steps is the last T of ``history``)
            by_length: dict[int, list[Run]] = {}
            for r in ending:
                by_length.setdefault(len(batch[r.index].seg.rews), []).append(r)
            critic_after: dict[int, State] = {}
            for t_len, group in sorted(by_length.items()):
                critic_after |= self._update(group, history[-t_len:],
                                             [batch[r.index].seg for r in group], cur)
            # 4. each of them opens its next segment from the same observation and state,
            # acting again with its new weights (a separate critic's state: its recompute's
            # end), unless its batch is over: every episode ended, the run diverged, or most
            # episodes ended (published collision rule) and the rest, their last segment
            # bootstrapped, are truncated instead of stepping finished episodes
            reacting = []
            for r in ending:
                bt = batch[r.index]
                if (r.failed is not None or r.index in over
                        or bt.active.sum() < r.config.min_active_fraction * b):
                    over.add(r.index)
                else:
                    bt.seg, bt.seg_start = Segment(), tick + 1
                    reacting.append(r)
            if reacting:
                if critic_after:
                    state = {k: v.clone() for k, v in state.items()}
                    for r in reacting:
                        for k, v in critic_after[r.index].items():
                            state[k][r.rows] = v
                assert cur is not None
                cur = _merge_rows(cur, self._act(cur["obs"], state, reacting), reacting)
            # 5. runs whose batch ended report it; those that go on start their next batch
            restarting = []
            for r in live:
                if r.index not in over:
                    continue
                bt = batch.pop(r.index)
                if r.failed is not None:
                    continue
                r.steps += bt.steps
                r.episodes += b
                if on_batch(r, bt.steps, float((bt.ep_reward / np.maximum(bt.ep_len, 1)).mean())):
                    restarting.append(r)
            live = [r for r in live if r.index not in over] + restarting
            if not live:
                return
            if restarting:
                state, cur = self._restart(restarting, batch, obs, state, cur, tick + 1)
            tick += 1
            oldest = min(batch[r.index].seg_start for r in live)
            del history[: oldest - base]  # no open segment needs those steps
            base = oldest

    @torch.no_grad()
    def _act(self, obs: torch.Tensor, state: State, sampling: Sequence[Run]) -> dict[str, Any]:
        """No-grad acting step of the whole stack: observations ``(K N, B, 15)``, messages
        received, logits, actions sampled (Gumbel-max with the runs' uniforms), next state. Only
        the runs in ``sampling`` draw their actions (the others' rows are computed and
        ignored)."""
        net = self.net
        front, rear = exchange(net, state)
        logits, out, new = net.act_step(obs, state, front, rear, critic=not net.separate_critic)
        shape = (self.n_vehicles,) + tuple(logits.shape[1:])
        drawing = {r.index for r in sampling}
        u = torch.cat([r.uniforms(shape) if r.index in drawing
                       else torch.full(shape, 0.5, device="cpu") for r in self.runs])
        actions = (logits - torch.log(-torch.log(u.to(self.device)))).argmax(-1)
        return {"obs": obs, "front": front, "rear": rear, "out": out, "logits": logits,
                "actions": actions, "state": new}

    def _step_envs(
        self, live: list[Run], batch: dict[int, Batch], actions: torch.Tensor,
        obs: list[torch.Tensor],
    ) -> tuple[list[Run], set[int]]:
        """Step every live run's env with its rows of ``actions`` and store its next
        observation in ``obs``; returns the runs whose segment ends at this step and the indices
        of those whose batch ends (a finished batch's segment bootstraps from 0)."""
        ending: list[Run] = []
        over: set[int] = set()
        sharing: dict[int, list[Run]] = {}  # env -> its live runs
        actions = actions.cpu()
        for r in live:
            sharing.setdefault(id(batch[r.index].env), []).append(r)
        for group in sharing.values():
            env = batch[group[0].index].env
            # rows of runs that left this env (their batch ended) step on with action 0, ignored
            acts = np.zeros((env.batch_size, self.n_vehicles), dtype=np.int64)
            for r in group:
                acts[batch[r.index].rows] = actions[r.rows].T.numpy()
            res = env.step_actions(acts)
            for r in group:
                bt = batch[r.index]
                bt.record(r, res)
                if bt.done:
                    over.add(r.index)
                    bt.seg.bootstrap = torch.zeros(self.shape.episodes_parallel, self.n_vehicles,
                                                   device=self.device)
                    ending.append(r)
                else:
                    assert res.observation is not None
                    obs[r.index] = self._observation(res.observation[bt.rows])
                    if len(bt.seg.rews) == self.shape.n_step:
                        ending.append(r)
        return ending, over

    def _start_batches(self, runs: list[Run], obs: list[torch.Tensor], tick: int
                       ) -> dict[int, Batch]:
        """Start the next batch of each run in ``runs`` at step ``tick``: the runs with the same
        reward weights share one batched env of their K B episodes (each episode depends on its
        own seed only, so a run's rows equal its env alone; one step of a shared env costs about
        what one run's costs)."""
        b, n = self.shape.episodes_parallel, self.n_vehicles
        by_weights: dict[RewardWeights, list[Run]] = {}
        for r in runs:
            by_weights.setdefault(r.env.weights, []).append(r)
        out = {}
        for weights, group in by_weights.items():
            env = self._make_env(weights)
            obs_np = env.reset(np.concatenate([r.training_seeds(b) for r in group]))
            assert obs_np is not None
            for j, r in enumerate(group):
                rows = slice(j * b, (j + 1) * b)
                obs[r.index] = self._observation(obs_np[rows])
                r.return_acc = torch.zeros(b, n, device=self.device)
                out[r.index] = Batch(env, rows, np.ones(b, dtype=bool), np.zeros(b),
                                     np.zeros(b), seg_start=tick)
        return out

    def _restart(
        self, restarting: list[Run], batch: dict[int, Batch], obs: list[torch.Tensor],
        state: State, cur: dict[str, Any] | None, tick: int,
    ) -> tuple[State, dict[str, Any]]:
        """Start the next batch of each run in ``restarting`` at step ``tick``: new episodes,
        the initial recurrent state on its rows, and its first act."""
        initial = self.net.initial_state(self.shape.episodes_parallel)
        state = {k: v.clone() for k, v in state.items()}
        batch |= self._start_batches(restarting, obs, tick)
        for r in restarting:
            for k, v in state.items():
                v[r.rows] = initial[k][r.rows]
        new = self._act(torch.cat(obs), state, restarting)
        return state, new if cur is None else _merge_rows(cur, new, restarting)

    def _observation(self, obs_np: np.ndarray) -> torch.Tensor:
        """Env observations ``(B, N, 15)`` -> agent-major ``(N, B, 15)``."""
        return torch.from_numpy(obs_np).transpose(0, 1).contiguous().to(self.device)

    def _make_env(self, weights: RewardWeights) -> PlatoonEnv:
        """A batched training env of the scenario (published collision rule, ``weights``)."""
        return PlatoonEnv(self.scenario, self.n_vehicles, training=True,
                          collision_mode="published", weights=weights)

    # -- update
    def _update(self, group: list[Run], record: list[tuple[State, dict[str, Any]]],
                segs: list[Segment], nxt: dict[str, Any] | None) -> dict[int, State]:
        """One update of the runs in ``group``, whose segments ``segs`` have the same length T
        (``record``: the segment's steps, the state acted from and the act): one recompute with
        gradient on their rows, each run's loss, one backward, clipping, the algorithm's hooks
        and RMSprop. With a separate critic, the bootstrap of a segment whose batch goes on is
        computed here from the recompute's critic state and ``nxt`` (the act on the next
        observation), with the weights before the update; returns that critic state after the
        segment per such run."""
        logits, values, actions, rows, after = self._recompute(group, record)
        critic_after = self._critic_bootstrap(group, segs, rows, after, nxt)
        losses = [segment_loss(r, sg, logits, values, actions, rw)
                  for r, sg, rw in zip(group, segs, rows, strict=True)]
        # each run's gradient is its own loss's (the sum's derivative is 1 for each)
        self._optimise(sum(losses[1:], losses[0]), group)
        return critic_after

    def _recompute(self, group: list[Run], record: list[tuple[State, dict[str, Any]]]
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[slice], State]:
        """Re-run the group's segment with gradient on the group's rows only: logits
        ``(A, T, B, 4)``, values and actions ``(A, T, B)`` of its ``A`` agents, each run's rows
        among them, and the recurrent state after the segment (those rows)."""
        net, seg_state, acts = self.net, record[0][0], [h[1] for h in record]
        obs = torch.stack([a["obs"] for a in acts], 1)
        actions = torch.stack([a["actions"] for a in acts], 1)
        msgs = None  # messages received, where gradients do not flow through them
        if not net.differentiable_messages and acts[0]["front"] is not None:
            msgs = (torch.stack([a["front"] for a in acts], 1),
                    torch.stack([a["rear"] for a in acts], 1))
        if len(group) == len(self.runs):
            logits, values, after = net(seg_state, obs, actions, msgs)
            return logits, values, actions, [r.rows for r in group], after
        idx = torch.cat([torch.arange(r.rows.start, r.rows.stop, device=self.device)
                         for r in group])

        def pick(t: torch.Tensor) -> torch.Tensor:
            return t.index_select(0, idx)

        if msgs is not None:
            msgs = (pick(msgs[0]), pick(msgs[1]))
        tensors = {name: pick(t) for name, t in module_tensors(net).items()}
        logits, values, after = torch.func.functional_call(net, tensors, (
            {k: pick(v) for k, v in seg_state.items()}, pick(obs), pick(actions), msgs))
        n = self.n_vehicles
        rows = [slice(j * n, (j + 1) * n) for j in range(len(group))]
        return logits, values, pick(actions), rows, after

    @torch.no_grad()
    def _critic_bootstrap(
        self, group: list[Run], segs: list[Segment], rows: list[slice], after: State,
        nxt: dict[str, Any] | None,
    ) -> dict[int, State]:
        """For a separate critic, each run of the group whose batch goes on: its segment's
        bootstrap (the critic one step on from the segment's end, on the next observation, in
        one critic step of the whole stack) and its critic state at the segment's end."""
        net = self.net
        if not net.separate_critic:
            return {}
        going = [(r, sg, rw) for r, sg, rw in zip(group, segs, rows, strict=True)
                 if sg.bootstrap is None]
        if not going:
            return {}
        assert nxt is not None
        b = self.shape.episodes_parallel
        start = {k: torch.zeros(net.n_agents, b, net.hidden, device=self.device)
                 for k in ("ch", "cc")}
        for r, _, rw in going:
            for k in start:
                start[k][r.rows] = after[k][rw]
        out, _ = net.critic_features(nxt["obs"], start)
        values = net.value(out, neighbour_action_onehot(nxt["actions"], net.platoon_size))
        for r, sg, _ in going:
            sg.bootstrap = values[r.rows].T
        return {r.index: {k: after[k][rw].detach().clone() for k in ("ch", "cc")}
                for r, _, rw in going}

    def _optimise(self, loss: torch.Tensor, group: list[Run]) -> None:
        """Backward of ``loss`` (the sum of the group's losses), each agent's gradient clipped to
        its run's global norm (the other rows have none), the algorithm's hooks around RMSprop,
        and the divergence check."""
        params = [p for p, _ in self.params]
        for p in params:
            if p.grad is not None:
                p.grad.zero_()
        loss.backward()
        clips = {r.config.grad_clip for r in group}
        per_agent_clip_(params, clips.pop() if len(clips) == 1 else torch.tensor(
            [r.config.grad_clip for r in self.runs], device=self.device
        ).repeat_interleave(self.n_vehicles))  # a config population: each run its own norm
        for r in group:
            self.algo.before_step(r, self.net)
        self._rmsprop(group)
        for r in group:
            self.algo.after_step(r, self.net)
            r.updates += 1
        if not all(bool(torch.isfinite(p).all()) for p in params):
            for r in group:
                self._check_finite(r)

    @torch.no_grad()
    def _rmsprop(self, group: list[Run]) -> None:
        """RMSprop (no momentum, not centred; the arithmetic of ``torch.optim.RMSprop``) on the
        group's rows, each run with its own actor and critic rates, smoothing and epsilon (one
        step of the whole stack when every run updates with the same settings)."""
        settings = {(r.learning_rates(), r.config.rmsprop_alpha, r.config.rmsprop_eps)
                    for r in group}
        whole = len(group) == len(self.runs) and len(settings) == 1
        for (p, is_critic), sq in zip(self.params, self._square_avg, strict=True):
            assert p.grad is not None
            if whole:
                (lrs, alpha, eps), = settings
                rmsprop_(p, p.grad, sq, lrs[is_critic], alpha, eps)
                continue
            for r in group:
                cfg = r.config
                rmsprop_(p[r.rows], p.grad[r.rows], sq[r.rows], r.learning_rates()[is_critic],
                         cfg.rmsprop_alpha, cfg.rmsprop_eps)

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
    def run_batch(self, runs: Sequence[Run] | None = None) -> list[tuple[int, float]]:
        """Run one batch of B episodes of every run in ``runs`` (default all), with an update of
        each run every n steps.

        Returns per run the environment steps taken and the mean training reward (the
        learner's own, shaped when the config says so; mean over steps of the sum over agents,
        as the paper reports). Raises :class:`TrainingDivergedError` if a run diverged.
        """
        taking = list(self.runs if runs is None else runs)
        out: dict[int, tuple[int, float]] = {}

        def once(run: Run, steps: int, reward: float) -> bool:
            out[run.index] = (steps, reward)
            return False

        self.train(once, taking)
        failed = [r.failed for r in taking if r.failed is not None]
        if failed:
            raise TrainingDivergedError("; ".join(failed))
        return [out[r.index] for r in taking]

    def run_state(self, run: Run) -> dict[str, Any]:
        """Everything ``run`` continues from bit for bit once one of its batches ended (where
        :meth:`train` calls ``on_batch``; its next batch starts from new episodes): its rows of
        the weights, buffers and RMSprop's averages, its random stream, counters, return
        statistics, bit tallies and the algorithm's state (:mod:`marl.checkpoint`'s
        snapshots). Nothing else carries over: a run draws only from its own generator, its
        episodes' streams from their seeds."""
        name = {id(p): n for n, p in self.net.named_parameters()}
        return {
            "seed": run.seed,
            "tensors": {n: t[run.rows].detach().cpu().clone()
                        for n, t in module_tensors(self.net).items()},
            "square_avg": {name[id(p)]: sq[run.rows].cpu().clone()
                           for (p, _), sq in zip(self.params, self._square_avg, strict=True)},
            "generator": run.generator.get_state(),
            "counters": [run.steps, run.episodes, run.updates, run.episode_counter],
            "return_stats": list(run.return_stats),
            "bits": dict(run.bits),
            "hook_state": plain_state(run.hook_state, (run.generator,)),
        }

    @torch.no_grad()
    def restore_run(self, run: Run, state: dict[str, Any]) -> None:
        """Continue ``run`` from :meth:`run_state`'s ``state`` (before :meth:`train`)."""
        name = {id(p): n for n, p in self.net.named_parameters()}
        mine = module_tensors(self.net)
        saved, squares = state["tensors"], state["square_avg"]
        if state["seed"] != run.seed or saved.keys() != mine.keys() or any(
                saved[n].shape != mine[n][run.rows].shape for n in mine):
            raise ConfigError(f"the snapshot of seed {state['seed']} is not this {self.algo.name} "
                              f"run's (seed {run.seed}, N = {self.n_vehicles}); remove it to "
                              "train from the start")
        for n, t in mine.items():
            t[run.rows] = saved[n].to(self.device)
        for (p, _), sq in zip(self.params, self._square_avg, strict=True):
            sq[run.rows] = squares[name[id(p)]].to(self.device)
        run.generator.set_state(state["generator"])
        run.steps, run.episodes, run.updates, run.episode_counter = state["counters"]
        run.return_stats = tuple(state["return_stats"])  # type: ignore[assignment]
        run.bits = dict(state["bits"])
        run.hook_state = restore_state(run.hook_state, state["hook_state"], (run.generator,),
                                       self.device)


def _merge_rows(base: dict[str, Any], new: dict[str, Any], runs: Sequence[Run]) -> dict[str, Any]:
    """``base`` (an act's output, nested dicts of ``(A, ...)`` tensors) with the rows of
    ``runs`` taken from ``new``."""

    def merge(x: Any, y: Any) -> Any:
        if x is None:
            return None
        if isinstance(x, dict):
            return {k: merge(x[k], y[k]) for k in x}
        out = x.clone()
        for r in runs:
            out[r.rows] = y[r.rows]
        return out

    return {k: merge(base[k], new[k]) for k in base}
