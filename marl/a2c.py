"""The learner: on-policy A2C of N agents per platoon, in the order it runs.

Read top to bottom, as a CleanRL file: **config** (:class:`marl.config.A2CConfig`, shared with
the acting side, and the training device), **networks** (:mod:`marl.networks`: N agents batched
as one module), **rollout** (each run's own state, :class:`Run`, and what a segment records,
:class:`Segment`), **returns** (reward sharing and n-step returns), **loss** (the three A2C
terms), and **update** (:class:`Learner`: recompute the segment with gradient, loss, backward,
per-agent clipping, the algorithm's hooks, RMSprop, the divergence check).

The layers around it: :mod:`marl.population` steps K runs at once through batched envs and calls
this update (:class:`marl.population.Trainer`; K = 1 is one run); :mod:`marl.selection` trains
with validation and checkpoint selection (:func:`marl.selection.run_training`,
:func:`marl.selection.run_population`); :mod:`marl.acting` acts from a checkpoint. Every
algorithm file (``ia2c.py`` ... ``bdc.py``) fills an :class:`marl.config.Algorithm`;
``run_training(algorithm("bdc"), config, "catchup-v1")`` trains any of them.

Learner (published A2C, ``docs/spec/marl.md``): n-step segments (60 steps; every episode length and
every published collision end is a multiple of 60), bootstrap from V of the observation after
the segment (0 if terminal), truncated backprop through the LSTM within a segment, entropy
bonus, per-agent global grad-norm clip, RMSprop. The acting LSTM state advances exactly once per
observation: at a segment boundary the bootstrap forward is computed without gradient from the
detached state and the next segment recomputes that same transition with gradient, re-using the
actions sampled for the bootstrap. B episodes run in parallel in one batched
:class:`envs.platoon.PlatoonEnv` (``training=True, collision_mode="published"``); one batched
step of B active episodes counts as B environment steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from envs.errors import ConfigError
from envs.platoon import PlatoonEnv
from marl.config import A2CConfig, Algorithm
from marl.layers import per_agent_clip_
from marl.networks import AgentNet, State, neighbour_action_onehot


# ---------------------------------------------------------------------------- config
# :class:`marl.config.A2CConfig`: every hyper-parameter, with the paper's values as defaults (its
# own module, shared with the acting side, which never loads this learner); each algorithm's
# config subclasses it. Here: where the learner trains.
def training_device(name: str | torch.device) -> torch.device:
    """The torch device a :class:`marl.population.Trainer` trains on: ``cpu`` (default), ``cuda`` or
    ``cuda:K``. Raises :class:`ConfigError` for another name or a GPU this machine lacks."""
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise ConfigError(f"--device {name!r}: expected cpu, cuda or cuda:K") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise ConfigError(f"--device {name}: training runs on cpu or cuda, not {device.type}")
    if not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: this torch ({torch.__version__}) sees no CUDA GPU; "
                          "train on the CPU (--device cpu, the default) or install a CUDA build "
                          "of torch on a GPU machine")
    index = 0 if device.index is None else device.index
    if index >= torch.cuda.device_count():
        raise ConfigError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA "
                          f"device(s), numbered from 0")
    return torch.device("cuda", index)


# ---------------------------------------------------------------------------- networks
# :mod:`marl.networks`: N agents' actor-critics batched as one module
# (:class:`marl.networks.AgentNet`): the shared trunk of IA2C, FPrint, DIAL and CommNet, and the
# separate actor and critic of WAC, DCEA and BDC.


# ---------------------------------------------------------------------------- rollout
@dataclass
class Run:
    """One training run of a :class:`marl.population.Trainer`: everything of its own.

    A population shares only the stacked network tensors (each run owns the agent rows
    ``rows``); its random stream, environment, optimiser rates, return statistics, step counts,
    bit tallies and algorithm state (``hook_state``) are its own, used in the order a run alone
    uses them, so each run trains exactly as it would alone.
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
    #: the run's step budget (entropy schedule); :func:`run_population` sets it
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
        base = 10_000_000 * (self.seed + 1)
        seeds = base + self.episode_counter + np.arange(batch)
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
    return (adv - mean) / (var.sqrt() + 1e-8)


# ---------------------------------------------------------------------------- update
class Learner:
    """The update of one segment of a group of runs (one run, or several of a population whose
    segments end at the same step with the same length): recompute with gradient, each run's
    loss, one backward, per-agent clipping, the algorithm's hooks and RMSprop on each run's rows.

    :class:`marl.population.Trainer` holds the state it reads (the stacked network, the runs,
    the optimiser's running averages) and calls :meth:`_update` when segments end.
    """

    algo: Algorithm
    scenario_id: str
    n_vehicles: int
    device: torch.device
    #: the runs' networks stacked along the agent axis (``K N`` agents)
    net: AgentNet
    runs: list[Run]
    #: the fields the runs share (:data:`marl.population.POPULATION_SHARED_FIELDS`)
    shape: A2CConfig
    #: (parameter, is_critic): actor parameters, then the critic's
    params: list[tuple[nn.Parameter, bool]]
    _square_avg: list[torch.Tensor]

    def _recompute(
        self, group: list[Run], seg_state: State, record: list[dict[str, Any]]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[slice], State]:
        """Re-run the group's segment with gradient on the group's rows only: logits
        ``(A, T, B, 4)``, values and actions ``(A, T, B)`` of its ``A`` agents, each run's rows
        among them, and the recurrent state after the segment (those rows)."""
        net = self.net
        obs = torch.stack([r["obs"] for r in record], 1)
        actions = torch.stack([r["actions"] for r in record], 1)
        msgs = None
        if not net.differentiable_messages and record[0]["front"] is not None:
            msgs = (torch.stack([r["front"] for r in record], 1),
                    torch.stack([r["rear"] for r in record], 1))
        if len(group) == len(self.runs):
            logits, values, after = net(seg_state, obs, actions, msgs)
            return logits, values, actions, [r.rows for r in group], after
        idx = torch.cat([torch.arange(r.rows.start, r.rows.stop, device=self.device)
                         for r in group])

        def pick(t: torch.Tensor) -> torch.Tensor:
            return t.index_select(0, idx)

        tensors = {name: pick(t) for name, t in [*net.named_parameters(), *net.named_buffers()]}
        logits, values, after = torch.func.functional_call(net, tensors, (
            {k: pick(v) for k, v in seg_state.items()}, pick(obs), pick(actions),
            None if msgs is None else (pick(msgs[0]), pick(msgs[1]))))
        n = self.n_vehicles
        rows = [slice(j * n, (j + 1) * n) for j in range(len(group))]
        return logits, values, pick(actions), rows, after

    def _loss(self, run: Run, seg: Segment, logits: torch.Tensor, values: torch.Tensor,
              actions: torch.Tensor, rows: slice) -> torch.Tensor:
        """The run's A2C loss over its segment from its ``rows`` of the recompute."""
        cfg = run.config
        def tensor(parts: list[np.ndarray], dtype: torch.dtype | None = torch.float32
                   ) -> torch.Tensor:
            return torch.from_numpy(np.stack(parts)).to(self.device, dtype)

        mask = tensor(seg.masks).unsqueeze(-1)  # (T, B, 1)
        term = tensor(seg.terms, None)
        reward = tensor(seg.rews)
        # R_t = r_t + gamma V_absorbing at a step that ended the episode by collision
        extra = tensor(seg.absorbed)  # (T, B)
        reward = reward + cfg.gamma * extra.unsqueeze(-1)
        assert cfg.reward_alpha is not None and seg.bootstrap is not None
        reward = share_rewards(reward * cfg.reward_scale, cfg.reward_alpha)
        if cfg.return_norm:
            reward = reward / run.return_scale(reward, term, mask)
        returns = nstep_returns(reward, seg.bootstrap, term, cfg.gamma)  # (T, B, N)
        terms_ = a2c_losses(
            logits[rows].permute(1, 0, 2, 3), actions[rows].permute(1, 0, 2),
            values[rows].permute(1, 0, 2), returns, mask, cfg.advantage_norm)
        ent_coef = cfg.entropy_at(run.steps / run.total_steps if run.total_steps else 0.0)
        return terms_["policy"] + cfg.value_coef * terms_["value"] - ent_coef * terms_["entropy"]

    def _update(
        self, group: list[Run], seg_state: State, record: list[dict[str, Any]],
        segs: list[Segment], nxt: dict[str, Any] | None,
    ) -> dict[int, State]:
        """One update of every run in ``group`` (their segments have the same length).

        With a separate critic, the bootstrap of a run whose batch goes on is computed here from
        the recompute's critic state and ``nxt`` (the act on the next observation), with the
        weights before the update; returns those runs' critic state after the segment."""
        logits, values, actions, rows, after = self._recompute(group, seg_state, record)
        critic_after = self._critic_bootstrap(group, segs, rows, after, nxt)
        losses = [self._loss(r, sg, logits, values, actions, rw)
                  for r, sg, rw in zip(group, segs, rows, strict=True)]
        loss = losses[0]
        for other in losses[1:]:  # each run's gradient is its own loss's (the sum's is 1 each)
            loss = loss + other
        for p, _ in self.params:
            if p.grad is not None:
                p.grad.zero_()
        loss.backward()
        params = [p for p, _ in self.params]
        clips = {r.config.grad_clip for r in group}
        if len(clips) == 1:
            per_agent_clip_(params, clips.pop())
        else:  # a config population: each run clips at its own norm (other rows have no grad)
            per_agent_clip_(params, torch.tensor(
                [r.config.grad_clip for r in self.runs], device=self.device
            ).repeat_interleave(self.n_vehicles))
        for r in group:
            self.algo.before_step(r, self.net)
        self._rmsprop_step(group)
        for r in group:
            self.algo.after_step(r, self.net)
            r.updates += 1
        if not all(bool(torch.isfinite(p).all()) for p, _ in self.params):
            for r in group:
                self._check_finite(r)
        return critic_after

    @torch.no_grad()
    def _critic_bootstrap(
        self, group: list[Run], segs: list[Segment], rows: list[slice], after: State,
        nxt: dict[str, Any] | None,
    ) -> dict[int, State]:
        """For a separate critic: each continuing run's bootstrap (its critic one step on from
        the segment's end, on the next observation) and its critic state at the segment's end."""
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

    @torch.no_grad()
    def _rmsprop_step(self, group: list[Run]) -> None:
        """RMSprop (no momentum, not centred; the arithmetic of ``torch.optim.RMSprop``) on the
        rows of the runs in ``group``, each with its own rates, smoothing and epsilon."""
        settings = {(r.learning_rates(), r.config.rmsprop_alpha, r.config.rmsprop_eps)
                    for r in group}
        whole = len(group) == len(self.runs) and len(settings) == 1
        for (p, is_critic), sq in zip(self.params, self._square_avg, strict=True):
            assert p.grad is not None
            if whole:
                (lrs, alpha, eps), = settings
                _rmsprop_(p, p.grad, sq, lrs[is_critic], alpha, eps)
                continue
            for r in group:
                cfg = r.config
                _rmsprop_(p[r.rows], p.grad[r.rows], sq[r.rows], r.learning_rates()[is_critic],
                          cfg.rmsprop_alpha, cfg.rmsprop_eps)

    def _check_finite(self, run: Run) -> None:
        """Stop a run whose weights became NaN or infinite (a NaN policy would otherwise act as
        "action 0" everywhere: the argmax of NaN logits); the other runs go on. Its rows are
        zeroed so nothing non-finite stays in the stack."""
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


def _rmsprop_(
    param: torch.Tensor, grad: torch.Tensor, square_avg: torch.Tensor, lr: float, alpha: float,
    eps: float,
) -> None:
    """One RMSprop step in place, in the operation order of ``torch.optim.RMSprop``."""
    square_avg.mul_(alpha).addcmul_(grad, grad, value=1 - alpha)
    avg = square_avg.sqrt().add_(eps)
    param.addcdiv_(grad, avg, value=-lr)

