"""IPPO and MAPPO with one policy shared by every follower, in either action mode.

Read top to bottom, as CleanRL's ``ppo_continuous_action.py`` reads: the config, the networks,
the rollout, the returns (GAE), the clipped PPO loss and the update, then validation and the
checkpoint. What is this project's own, and why it is written here rather than taken from a
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
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from envs.accel_mode import check_action_mode, position_features
from envs.channel import ChannelConfig, episode_uniforms
from envs.errors import ConfigError
from envs.params import OVM_ACTIONS, VALIDATION_SEEDS, PlatoonParams, check_decision_seeds
from envs.platoon import PlatoonEnv, PlatoonState
from envs.scenarios import Scenario, check_vehicles, make_scenario
from marl.consensus import bdc, consensus_round
from marl.quantize import ErrorFeedbackQSGD, qsgd_bits, ternary_bits

#: The learners of this file: one shared policy (``ippo``, ``mappo``), or one actor and critic
#: per agent whose critics agree by binary differential consensus (``ippo-bdc``).
SHARED_ALGORITHMS: tuple[str, ...] = ("ippo", "mappo", "ippo-bdc")
#: Model-based priors a residual policy can add to (``PPOConfig.prior``).
PRIORS: tuple[str, ...] = ("", "cacc")
#: Uniform stream of sampled evaluation actions (per episode, step and agent).
ACTION_STREAM = "shared-policy-actions"


# ---------------------------------------------------------------------------- config
@dataclass(frozen=True)
class PPOConfig:
    """Hyper-parameters (CleanRL's continuous-action PPO where the platoon does not differ).

    Attributes
    ----------
    algo : {"ippo", "mappo", "ippo-bdc"}
        Local critic or centralised (agent + platoon-mean observation) critic, one policy
        shared by all; or (``ippo-bdc``) BDC-MARL's scheme on this learner: an actor and a local
        critic per agent, the critics' weights brought together after every update by binary
        differential consensus with the front and rear neighbours, their gradients compressed
        by QSGD with error feedback (:mod:`marl.bdc`), so the policy is trained for one N.
    action_mode : {"accel", "ovm-gain"}
        The env's action mode (:mod:`envs.accel_mode`).
    n_envs : int
        Episodes stepped together (B).
    rollout_steps : int
        Steps per episode between updates (T); an update learns from ``B T N`` agent-steps.
    epochs, minibatch_rows : int
        Passes over a rollout, and agent-steps per gradient step.
    lr : float
        Adam learning rate, annealed linearly to 0 over the run.
    gamma, gae_lambda : float
        Discount and GAE's lambda.
    clip_coef, vf_coef, ent_coef, max_grad_norm : float
        PPO's ratio clip, value-loss weight, entropy bonus, global grad-norm clip.
    hidden : int
        Width of the two ReLU layers of actor and critic.
    init_log_std : float
        Initial log standard deviation of the Gaussian ``z`` (``accel``).
    reward_alpha : float
        Reward sharing: agent i learns from ``sum_j alpha^|i-j| r_j`` (0: its own reward, the
        default; 1: the platoon's), as the paper's learners' ``reward_alpha``.
    reward_clip, obs_clip : float
        Clip of the normalised reward and observation.
    comm_delay_s, packet_loss : float
        V2V of the training episodes (``accel``).
    eval_every_steps : int
        Environment steps between validations (the kept snapshot: fewest collisions on the
        validation seeds, then best reward, actions sampled as trained).
    prior : {"", "cacc"}
        ``"cacc"``: residual policy learning (Silver et al. 2018; Johannink et al., ICRA 2019):
        the command is ``clip(cacc(obs) + h tanh(z))``, Ploeg's CACC computed from the same
        observation (:func:`envs.accel_mode.cacc_from_observation`) plus the learned residual,
        which starts near zero; ``""``: ``c + h tanh(z)`` (``accel`` only).
    critic_warmup_updates : int
        Updates at the start that fit only the critic (so a random critic's advantages do not
        move a policy that starts from a good prior).
    vehicles_min, vehicles_max : int
        0, 0: every training episode has the run's N. Otherwise each batch of ``n_envs``
        episodes draws its N uniformly from ``vehicles_min`` (or the run's N) to
        ``vehicles_max`` (or the run's N) (domain randomisation; a rollout then ends where its
        episodes end; validation stays at the run's N).
    comm_delay_max_s, packet_loss_max : float
        Above ``comm_delay_s`` and ``packet_loss``: each batch of episodes draws its V2V delay
        (whole steps) and loss uniformly up to these (0: fixed).
    consensus_eps, qsgd_levels, qsgd_bucket : float, int, int
        ``ippo-bdc``: the consensus step (BDC's default), QSGD's levels on the critic gradients
        (0: off) and entries per QSGD bucket.
    """

    algo: str = "ippo"
    action_mode: str = "accel"
    n_envs: int = 64
    rollout_steps: int = 64
    epochs: int = 4
    minibatch_rows: int = 8192
    lr: float = 1e-3
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_coef: float = 0.2
    vf_coef: float = 0.5
    ent_coef: float = 0.0
    max_grad_norm: float = 0.5
    hidden: int = 64
    init_log_std: float = -1.5
    reward_alpha: float = 0.0
    reward_clip: float = 10.0
    obs_clip: float = 10.0
    comm_delay_s: float = 0.0
    packet_loss: float = 0.0
    eval_every_steps: int = 100_000
    prior: str = ""
    critic_warmup_updates: int = 0
    vehicles_min: int = 0
    vehicles_max: int = 0
    comm_delay_max_s: float = 0.0
    packet_loss_max: float = 0.0
    consensus_eps: float = 0.001
    qsgd_levels: int = 1
    qsgd_bucket: int = 128

    def __post_init__(self) -> None:
        if self.algo not in SHARED_ALGORITHMS:
            raise ConfigError(f"algo must be one of {', '.join(SHARED_ALGORITHMS)}, got {self.algo!r}")
        check_action_mode(self.action_mode)
        for name in ("n_envs", "rollout_steps", "epochs", "minibatch_rows", "hidden",
                     "eval_every_steps"):
            if not 1 <= getattr(self, name) <= 10**7:
                raise ConfigError(f"{name} must lie in 1..1e7, got {getattr(self, name)}")
        for name in ("lr", "reward_clip", "obs_clip", "max_grad_norm"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {getattr(self, name)}")
        if self.prior not in PRIORS:
            raise ConfigError(f"prior must be one of {PRIORS} ('' for none), got {self.prior!r}")
        if self.prior and self.action_mode != "accel":
            raise ConfigError("prior: a residual on an acceleration prior needs action_mode=accel")
        if not 0 <= self.critic_warmup_updates <= 10**6:
            raise ConfigError(f"critic_warmup_updates must lie in 0..1e6, got "
                              f"{self.critic_warmup_updates}")
        for name in ("vehicles_min", "vehicles_max"):
            if getattr(self, name) and not 2 <= getattr(self, name) <= 64:
                raise ConfigError(f"{name} must be 0 or lie in 2..64, got {getattr(self, name)}")
        if self.vehicles_min and self.vehicles_max and self.vehicles_min > self.vehicles_max:
            raise ConfigError("vehicles_min must not exceed vehicles_max")
        if self.randomised and self.per_agent:
            raise ConfigError("ippo-bdc has a network per follower: it trains at one N and one "
                              "V2V setting (vehicles_min, vehicles_max, comm_delay_max_s, packet_loss_max: 0)")
        if self.comm_delay_max_s:
            ChannelConfig(self.comm_delay_max_s, 0.0)
            if self.comm_delay_max_s < self.comm_delay_s:
                raise ConfigError("comm_delay_max_s must be 0 or >= comm_delay_s")
        if self.packet_loss_max:
            ChannelConfig(0.0, self.packet_loss_max)
            if self.packet_loss_max < self.packet_loss:
                raise ConfigError("packet_loss_max must be 0 or >= packet_loss")
        if not 0 < self.consensus_eps <= 0.5:
            raise ConfigError(f"consensus_eps must lie in (0, 0.5], got {self.consensus_eps}")
        if not (0 <= self.qsgd_levels <= 64 and 1 <= self.qsgd_bucket <= 10**6):
            raise ConfigError("qsgd_levels must lie in 0..64 and qsgd_bucket in 1..1e6")
        if not 0 <= self.reward_alpha <= 1:
            raise ConfigError(f"reward_alpha must lie in [0, 1], got {self.reward_alpha}")
        for name in ("gamma", "gae_lambda"):
            if not 0 < getattr(self, name) <= 1:
                raise ConfigError(f"{name} must lie in (0, 1], got {getattr(self, name)}")
        if not (0 < self.clip_coef < 1 and self.vf_coef >= 0 and self.ent_coef >= 0):
            raise ConfigError("clip_coef must lie in (0, 1); vf_coef and ent_coef must be >= 0")
        ChannelConfig(self.comm_delay_s, self.packet_loss)  # the channel's own checks

    @property
    def randomised(self) -> bool:
        """Whether batches of training episodes draw their N or V2V setting."""
        return bool(self.vehicles_min or self.vehicles_max or self.comm_delay_max_s
                    or self.packet_loss_max)

    @property
    def per_agent(self) -> bool:
        """One actor and critic per agent (``ippo-bdc``) instead of one shared by all."""
        return self.algo == "ippo-bdc"

    @property
    def obs_dim(self) -> int:
        """Floats per agent the networks read (the ``ovm-gain`` observation gets the position
        features appended; the ``accel`` one has them)."""
        return 12 if self.action_mode == "accel" else 15 + 3


# ---------------------------------------------------------------------------- networks
class StackedLinear(nn.Module):
    """One linear layer per agent: ``(..., N, n_in) -> (..., N, n_out)``, weights ``(N, n_in,
    n_out)`` (one batched product; the agent axis stays where the consensus rules want it)."""

    def __init__(self, n_agents: int, n_in: int, n_out: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(n_agents, n_in, n_out))
        self.bias = nn.Parameter(torch.zeros(n_agents, n_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, d = x.shape[-2:]
        rows = x.reshape(-1, n, d).transpose(0, 1)  # (N, M, n_in)
        out = torch.baddbmm(self.bias[:, None, :], rows, self.weight)
        return out.transpose(0, 1).reshape(*x.shape[:-1], -1)


def _mlp(n_in: int, hidden: int, n_out: int, gain: float, n_agents: int = 0) -> nn.Sequential:
    """Two ReLU layers, orthogonal init (CleanRL's ``layer_init``), shared (``n_agents`` 0) or
    one per agent. ReLU, not CleanRL's tanh: this torch build's CPU tanh took 2.1 ms on a
    (8192, 64) batch against ReLU's 0.07 ms (one thread), most of a training step."""
    def linear(a: int, b: int) -> nn.Module:
        return StackedLinear(n_agents, a, b) if n_agents else nn.Linear(a, b)

    layers = [linear(n_in, hidden), nn.ReLU(), linear(hidden, hidden), nn.ReLU(),
              linear(hidden, n_out)]
    for layer, g in zip(layers[::2], (math.sqrt(2), math.sqrt(2), gain)):
        if isinstance(layer, StackedLinear):
            with torch.no_grad():  # each agent's (n_in, n_out) as nn.Linear's (out, in)
                for i in range(layer.weight.shape[0]):
                    nn.init.orthogonal_(layer.weight[i].T, g)
            continue
        assert isinstance(layer, nn.Linear)
        nn.init.orthogonal_(layer.weight, g)
        nn.init.zeros_(layer.bias)
    return nn.Sequential(*layers)


class SharedActor(nn.Module):
    """The policy every follower shares: observation ``(..., D)`` -> action parameters.

    ``accel``: the Gaussian mean of ``z`` and a state-independent log std; the command is
    ``c + h tanh(z)`` with ``c, h`` the midpoint and half-range of the command bounds.
    ``ovm-gain``: logits of the four OVM gain pairs.
    """

    centre: torch.Tensor
    half_range: torch.Tensor
    obs_mean: torch.Tensor
    obs_var: torch.Tensor
    obs_count: torch.Tensor

    def __init__(self, config: PPOConfig, params: PlatoonParams = PlatoonParams(),
                 n_agents: int = 0) -> None:
        super().__init__()
        self.continuous = config.action_mode == "accel"
        self.prior = config.prior
        self.n_agents = n_agents  # 0: shared by every follower, else one network per agent
        n_out = 1 if self.continuous else len(OVM_ACTIONS)
        self.body = _mlp(config.obs_dim, config.hidden, n_out, 0.01, n_agents)
        self.log_std = nn.Parameter(torch.full((max(n_agents, 1),), float(config.init_log_std)))
        self.obs_clip = float(config.obs_clip)
        self.register_buffer("obs_mean", torch.zeros(config.obs_dim, dtype=torch.float64))
        self.register_buffer("obs_var", torch.ones(config.obs_dim, dtype=torch.float64))
        self.register_buffer("obs_count", torch.tensor(1e-4, dtype=torch.float64),
                             persistent=False)  # training only
        self.register_buffer("centre", torch.tensor((params.accel_max_mps2 + params.accel_min_mps2) / 2))
        self.register_buffer("half_range", torch.tensor((params.accel_max_mps2 - params.accel_min_mps2) / 2))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Gaussian mean of ``z`` ``(...)`` (``accel``) or logits ``(..., 4)`` of raw
        observations."""
        return self.policy(self.normalise(obs))

    def policy(self, nobs: torch.Tensor) -> torch.Tensor:
        """As :meth:`forward`, of normalised observations."""
        out = self.body(nobs)
        return out[..., 0] if self.continuous else out

    def normalise(self, obs: torch.Tensor) -> torch.Tensor:
        """``clip((obs - mean) / sqrt(var + 1e-8), -obs_clip, obs_clip)`` (float32)."""
        scale = (self.obs_var + 1e-8).rsqrt()
        return ((obs - self.obs_mean) * scale).float().clamp_(-self.obs_clip, self.obs_clip)

    @torch.no_grad()
    def update_obs_stats(self, obs: torch.Tensor) -> None:
        """Merge the rows ``(..., D)`` into the running mean and variance (Chan et al.)."""
        x = obs.reshape(-1, obs.shape[-1]).double()
        if not len(x):
            return
        n_b, mean_b, var_b = float(len(x)), x.mean(0), x.var(0, unbiased=False)
        n_a = float(self.obs_count)
        n = n_a + n_b
        delta = mean_b - self.obs_mean
        self.obs_var.copy_((self.obs_var * n_a + var_b * n_b + delta**2 * n_a * n_b / n) / n)
        self.obs_mean.add_(delta * n_b / n)
        self.obs_count.fill_(n)

    def command(self, z: torch.Tensor) -> torch.Tensor:
        """Acceleration command of the pre-squash sample ``z`` (m/s^2), inside the bounds."""
        return self.centre + self.half_range * torch.tanh(z)

    def log_prob_entropy(self, out: torch.Tensor, action: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
        """Log-probability of ``action`` (``z``, or the index) and the entropy (of ``z``'s
        Gaussian: the squash's Jacobian cancels in PPO's ratio)."""
        if self.continuous:
            std = self.log_std.exp()
            logp = -0.5 * ((action - out) / std) ** 2 - self.log_std - 0.5 * math.log(2 * math.pi)
            ent = (0.5 + 0.5 * math.log(2 * math.pi) + self.log_std).expand_as(out)
            return logp, ent
        logp_all = torch.log_softmax(out, dim=-1)
        logp = logp_all.gather(-1, action.long().unsqueeze(-1)).squeeze(-1)
        ent = -(logp_all.exp() * logp_all).sum(-1)
        return logp, ent


class Critic(nn.Module):
    """Value of each agent: its observation (IPPO), or with the platoon's mean beside it (MAPPO)."""

    def __init__(self, config: PPOConfig, n_agents: int = 0) -> None:
        super().__init__()
        self.central = config.algo == "mappo"
        self.body = _mlp(config.obs_dim * (2 if self.central else 1), config.hidden, 1, 1.0,
                         n_agents)

    def inputs(self, obs: torch.Tensor) -> torch.Tensor:
        """What the critic reads of ``obs (..., N, D)``: ``(..., N, D)`` or ``(..., N, 2 D)``."""
        if not self.central:
            return obs
        return torch.cat([obs, obs.mean(dim=-2, keepdim=True).expand_as(obs)], dim=-1)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """``obs (..., N, D)`` -> values ``(..., N)``."""
        return self.body(self.inputs(obs))[..., 0]


def agent_inputs(obs: np.ndarray | None, action_mode: str) -> np.ndarray:
    """What the networks read from the env's observation ``(B, N, D)``: the ``accel`` one as it
    is, the ``ovm-gain`` one with the position features appended (float32)."""
    if obs is None:
        raise ValueError("the env does not observe (observe=False)")
    if action_mode == "accel":
        return np.ascontiguousarray(obs, dtype=np.float32)
    b, n, _ = obs.shape
    pos = np.broadcast_to(position_features(n)[None].astype(np.float32), (b, n, 3))
    return np.concatenate([obs.astype(np.float32), pos], axis=-1)


def to_command(actor: SharedActor, action: torch.Tensor, state: PlatoonState | None,
               params: PlatoonParams, obs: np.ndarray | None = None,
               targets: tuple[float, float] | None = None) -> np.ndarray:
    """The ``(B, N)`` acceleration commands of the actions in ``state``: ``c + h tanh(z)``, the
    residual ``clip(prior(obs) + h tanh(z))`` of an actor with a prior (``obs``: the raw
    ``accel`` observation, ``targets``: the scenario's target gap and speed), or the published
    OVM command of the gain indices (the trainer, validation and the controller all act
    through this)."""
    if actor.continuous:
        if not actor.prior:
            return actor.command(action).numpy().astype(np.float64)
        if obs is None or targets is None:
            raise ValueError("an actor with a prior acts on the observation and the targets")
        from envs.accel_mode import cacc_from_observation

        base = cacc_from_observation(obs, targets[0], targets[1], params)
        residual = (actor.half_range * torch.tanh(action)).numpy().astype(np.float64)
        return np.clip(base + residual, params.accel_min_mps2, params.accel_max_mps2)
    from envs.dynamics import action_to_command_mps2

    assert state is not None
    return action_to_command_mps2(action.numpy().astype(np.int64), state.gap_m,
                                  state.speed_mps, state.pred_speed_mps, params)


def sample_with_uniforms(actor: SharedActor, out: torch.Tensor, uniforms: np.ndarray | None
                         ) -> torch.Tensor:
    """Evaluation actions: from the episodes' own uniforms ``(B, N)`` (inverse CDF: reruns and
    batches give the same actions), or the mode (``z = mean``, the argmax) when None."""
    if uniforms is None:
        return out if actor.continuous else out.argmax(-1)
    u = torch.from_numpy(np.clip(uniforms, 1e-12, 1 - 1e-12)).to(out.dtype)
    # in float32 ``1 - 1e-12`` rounds to 1, whose erfinv is inf (a command at the bound)
    u.clamp_(max=1.0 - torch.finfo(out.dtype).eps / 2)
    if actor.continuous:
        return out + actor.log_std.exp() * math.sqrt(2.0) * torch.erfinv(2 * u - 1)
    cdf = torch.softmax(out, dim=-1).cumsum(-1)
    return (cdf < u.unsqueeze(-1)).sum(-1).clamp_(max=out.shape[-1] - 1)


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
        seeds = 10_000_000 * (seed + 1) + episode + np.arange(b)
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
        buf_cobs = torch.zeros(t_len, b, n_r, d * (2 if critic.central else 1))
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
                buf_cobs[t] = critic.inputs(nobs)
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
                with torch.no_grad():  # truncated at the time limit: bootstrap from the last state
                    last = critic(actor.normalise(
                        torch.from_numpy(agent_inputs(res.observation, cfg.action_mode))))
            else:
                next_obs = torch.from_numpy(agent_inputs(res.observation, cfg.action_mode))
                last = None
            if ended.any():
                if last is None:
                    with torch.no_grad():
                        last = critic(actor.normalise(next_obs))
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
                with torch.no_grad():
                    buf_val[t_len] = critic(actor.normalise(obs))
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


def as_shipped(actor: SharedActor) -> SharedActor:
    """A copy of ``actor`` with its weights rounded through float16, as a checkpoint stores
    them: validation judges, and selection keeps, exactly what ships."""
    import copy

    out = copy.deepcopy(actor)
    with torch.no_grad():
        for key, value in out.state_dict().items():
            if key != "obs_count":
                value.copy_(value.to(torch.float16).to(value.dtype))
    out.eval()
    return out


def _absorbing(penalty: float, gamma: float, remaining: int) -> float:
    """The collision penalty at each of ``remaining`` steps, discounted."""
    if remaining <= 0:
        return 0.0
    return penalty * remaining if gamma == 1 else penalty * (1 - gamma**remaining) / (1 - gamma)


# ---------------------------------------------------------------------------- validation
@torch.no_grad()
def validation_score(actor: SharedActor, scenario: str | Scenario, n_vehicles: int,
                     params: PlatoonParams, config: PPOConfig,
                     seeds: tuple[int, ...] = VALIDATION_SEEDS) -> dict[str, float]:
    """Mean evaluation reward (sum over agents per step, as the benchmark's tables) and
    collisions on the validation seeds, actions sampled from the episodes' own uniforms."""
    check_decision_seeds(seeds, "marl.ppo.validation_score")
    env = PlatoonEnv(scenario, n_vehicles, params, action_mode=config.action_mode,
                     channel=ChannelConfig(config.comm_delay_s, config.packet_loss, params.dt_s))
    seeds_arr = np.asarray(seeds)
    obs = env.reset(seeds_arr)
    sc = env.scenario
    per_step = np.zeros((env.n_steps, len(seeds_arr)))
    steps = np.zeros(len(seeds_arr), dtype=np.int64)
    for t in range(env.n_steps):
        x = agent_inputs(obs, config.action_mode)
        out = actor(torch.from_numpy(x))
        u = episode_uniforms(seeds_arr, ACTION_STREAM, t, n_vehicles)
        action = sample_with_uniforms(actor, out, u)
        running = ~env.state.done  # type: ignore[union-attr]
        res = env.step(to_command(actor, action, env.state, env.params, x,
                                  (sc.target_gap_m, sc.target_speed_mps)))
        per_step[t] = np.ascontiguousarray(res.reward).sum(axis=1)
        steps += running
        obs = res.observation
        if res.done.all():
            break
    # each episode's mean over its own steps, as the benchmark's metrics take it
    rewards = [per_step[: steps[k], k].mean() for k in range(len(seeds_arr))]
    return {"reward": float(np.mean(rewards)),
            "collisions": float(env.state.collided.sum())}  # type: ignore[union-attr]


# ---------------------------------------------------------------------------- checkpoint
def save(result: PPOResult, path: str | Path, scenario: str, n_vehicles: int, seed: int) -> Path:
    """Write the acting weights (float16) and the config as a checkpoint."""
    from marl.checkpoint import save_checkpoint

    summary = {f"best_{k}": v for k, v in result.best.items()}
    summary["env_steps_per_s"] = result.env_steps_per_s
    summary.update({f"{k}_bits_per_agent": v for k, v in result.bits_per_agent.items()})
    return save_checkpoint(
        path, algo=result.config.algo, config=dataclasses.asdict(result.config),
        scenario=scenario, n_vehicles=n_vehicles, seed=seed, steps=result.steps,
        curve_summary=summary, weights=dict(result.actor.state_dict()))


def load_actor(data: dict[str, Any], params: PlatoonParams = PlatoonParams()) -> SharedActor:
    """The actor of a loaded checkpoint dict (float32 weights); a config or weights that do not
    make this learner's actor give a :class:`ConfigError`."""
    acting = ("algo", "action_mode", "hidden", "obs_clip", "prior")  # what the actor's shape and acting read
    try:
        config = PPOConfig(**{k: v for k, v in data["config"].items() if k in acting})
        actor = SharedActor(config, params, int(data["n_vehicles"]) if config.per_agent else 0)
        actor.load_state_dict({k: v.float() for k, v in data["weights"].items()}, strict=True)
    except (TypeError, ValueError, RuntimeError, KeyError) as exc:
        reason = " ".join(str(exc).split())[:200]
        raise ConfigError(f"a {data.get('algo')} checkpoint whose config or weights do not fit "
                          f"this learner ({reason}); train it again") from None
    actor.eval()
    return actor
