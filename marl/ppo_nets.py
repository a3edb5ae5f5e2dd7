"""The shared learners' config and networks (:mod:`marl.ppo`): :class:`PPOConfig` with the
hyper-parameters, the actor every follower shares (or one per follower, ``ippo-bdc``) and the
critic, and the weight checks the trainers share. Acting reads these without the trainer
(:mod:`marl.acting`)."""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass

import torch
from torch import nn

from envs.accel_mode import check_action_mode
from envs.channel import ChannelConfig
from envs.params import OVM_ACTIONS, PlatoonParams
from envs.scenarios import Scenario
from infra.errors import ConfigError, TrainingDivergedError
from marl.layers import BatchedLinear
from marl.learners import PPO_LEARNERS

#: Model-based priors a residual policy can add to (``PPOConfig.prior``).
PRIORS: tuple[str, ...] = ("", "cacc", "cacc-exact")

# ---------------------------------------------------------------------------- config
def check_counts(config: object, **highs: int) -> None:
    """The one rule for a config's counts (episodes, steps, rows, rounds): each in 1..its bound."""
    for name, high in highs.items():
        if not 1 <= getattr(config, name) <= high:
            raise ConfigError(f"{name} must lie in 1..{high:,}, got {getattr(config, name)}")


def check_learning_rate(lr: float) -> None:
    """The one rule for a shared learner's or the distiller's Adam learning rate: in (0, 1]
    (a larger step overflows Adam's float32 update or turns the weights non-finite)."""
    if not (math.isfinite(lr) and 0 < lr <= 1):
        raise ConfigError(f"lr must lie in (0, 1], got {lr}")


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
    prior : {"", "cacc", "cacc-exact"}
        ``"cacc"``: residual policy learning (Silver et al. 2018; Johannink et al., ICRA 2019):
        the command is ``clip(cacc(obs) + h tanh(z))``, Ploeg's CACC computed from the same
        observation (:func:`envs.accel_mode.cacc_from_observation`) plus the learned residual,
        which starts near zero (the shipped ``residual-cacc``); ``"cacc-exact"``: the same law
        given the state's unclipped relative speed and last command, so that it is the ``cacc``
        controller also where the observation's clip or the speed bound acts; ``""``:
        ``c + h tanh(z)`` (``accel`` only).
    critic_warmup_updates : int
        Updates at the start that fit only the critic (so a random critic's advantages do not
        move a policy that starts from a good prior).
    critic_time : bool
        The critic also reads the episode's elapsed fraction ``t / T`` (a time-aware value for
        a task with a time limit: Pardo et al., ICML 2018). The actor does not: the shipped
        policy acts on the observation alone.
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
    scenarios : str
        "": the training episodes run on the run's scenario. Otherwise a comma list of
        scenario labels (``catchup-v1,ring-v1``): each batch draws one uniformly (a ring keeps
        its own vehicle count); validation scores each (:meth:`validation_roads`).
    cav_share_min, cav_share_max : float
        1, 1: every follower automated. Otherwise each batch draws its share of automated
        followers uniformly from this range and places them at random (a seeded ``placement``
        drawn from the run's generator); the other seats are human drivers
        (:mod:`envs.humans`), whose agent-steps the policy never learns from.
    class_features : bool
        False (the default, every shipped policy): the networks read the observation alone.
        True: each follower's own class parameters are appended to its observation
        (:func:`envs.vehicle_classes.class_features`: lag, acceleration bound, mass; on the
        homogeneous string the published platoon's), and the acting controller feeds them
        the same way (the checkpoint's config records it).
    class_mixes : str
        "": the training episodes' vehicle classes are the scenarios' own. Otherwise
        arrangements of vehicle classes separated by ``;`` (``bus+van+car*6;truck+car*7``,
        each a multiset of the scenario option ``class_mix`` naming the run's N): each batch
        draws one uniformly and a ``class_seed`` from the run's generator (a class
        distribution); validation scores each road with the first at ``class_seed`` 0.
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
    critic_time: bool = False
    vehicles_min: int = 0
    vehicles_max: int = 0
    comm_delay_max_s: float = 0.0
    packet_loss_max: float = 0.0
    consensus_eps: float = 0.001
    qsgd_levels: int = 1
    qsgd_bucket: int = 128
    scenarios: str = ""
    cav_share_min: float = 1.0
    cav_share_max: float = 1.0
    class_features: bool = False
    class_mixes: str = ""

    def __post_init__(self) -> None:
        if self.algo not in PPO_LEARNERS:
            raise ConfigError(f"algo must be one of {', '.join(PPO_LEARNERS)}, got {self.algo!r}")
        check_action_mode(self.action_mode)
        from infra.limits import (
            MAX_EPISODES_PARALLEL,
            MAX_TRAIN_STEPS,
            check_delay,
            check_hidden,
            check_packet_loss,
            check_whole_steps,
        )

        check_hidden(self.hidden)
        check_counts(self, n_envs=MAX_EPISODES_PARALLEL, rollout_steps=10**4, epochs=1000,
                     minibatch_rows=10**7, eval_every_steps=MAX_TRAIN_STEPS)
        check_learning_rate(self.lr)
        big = float(torch.finfo(torch.float32).max)  # they bound float32 tensors
        for name in ("reward_clip", "obs_clip", "max_grad_norm"):
            if not 0 < getattr(self, name) <= big:
                raise ConfigError(f"{name} must lie in (0, {big:.3g}] (a float32), got "
                                  f"{getattr(self, name)}")
        if not -20 <= self.init_log_std <= 2:  # exp() of it a float32 holds, and a usable std
            raise ConfigError(f"init_log_std must lie in [-20, 2], got {self.init_log_std}")
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
            raise ConfigError("ippo-bdc has a network per follower: it trains at one N, one V2V "
                              "setting and one road (vehicles_min, vehicles_max, "
                              "comm_delay_max_s, packet_loss_max: 0; scenarios, class_mixes: "
                              "''; cav_share_min, cav_share_max: 1)")
        if not (0 < self.cav_share_min <= self.cav_share_max <= 1):
            raise ConfigError(f"cav_share_min and cav_share_max are shares of automated "
                              f"followers: 0 < cav_share_min <= cav_share_max <= 1, got "
                              f"{self.cav_share_min} and {self.cav_share_max}")
        if self.scenarios:
            from envs.scenarios import PLACEMENT_OPTIONS, SEAT_OPTIONS

            labels = [sc.label for sc in self.roads]  # built (and refused) here, once
            twice = sorted({lb for lb in labels if labels.count(lb) > 1})
            if twice:
                raise ConfigError(f"scenarios names {', '.join(twice)} more than once (each "
                                  "batch draws one of the list uniformly); name each once")
            drawn = (*SEAT_OPTIONS, *PLACEMENT_OPTIONS)
            for label in labels:
                if self.mixed_traffic and any(f"{k}=" in label for k in drawn):
                    raise ConfigError(f"scenarios: {label} sets its automated seats or their "
                                      "placement, which cav_share_min..cav_share_max draw at "
                                      "random; leave them out")
        if self.class_mixes:
            from envs.vehicle_classes import CLASS_OPTIONS

            if any(len(m) < 2 for m in self.mixes):  # parsed (and refused) here, once
                raise ConfigError(f"class_mixes={self.class_mixes!r}: each arrangement names "
                                  "the run's N >= 2 followers (bus+van+car*6;truck+car*7)")
            for label in [sc.label for sc in self.roads]:
                if any(f"{k}=" in label for k in CLASS_OPTIONS):
                    raise ConfigError(f"scenarios: {label} sets its vehicle classes, which "
                                      "class_mixes draws for every batch; leave them out")
        for high, low, check in (("comm_delay_max_s", "comm_delay_s", check_delay),
                                 ("packet_loss_max", "packet_loss", check_packet_loss)):
            if getattr(self, high):
                check(getattr(self, high), high)
                if getattr(self, high) < getattr(self, low):
                    raise ConfigError(f"{high} must be 0 or >= {low}")
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
        check_delay(self.comm_delay_s, "comm_delay_s")  # the channel's own rules
        check_packet_loss(self.packet_loss, "packet_loss")
        for name in ("comm_delay_s", "comm_delay_max_s"):
            check_whole_steps(getattr(self, name), name, PlatoonParams().dt_s)

    @property
    def randomised(self) -> bool:
        """Whether batches of training episodes draw their N, V2V setting, scenario or
        automated seats."""
        return bool(self.vehicles_min or self.vehicles_max or self.comm_delay_max_s
                    or self.packet_loss_max or self.scenarios or self.mixed_traffic
                    or self.class_mixes)

    @functools.cached_property
    def mixes(self) -> list[tuple[str, ...]]:
        """The arrangements ``class_mixes`` names, each its class names (none when empty)."""
        from envs.vehicle_classes import parse_class_sequence

        return [parse_class_sequence(m, "class_mixes") for m in self.class_mixes.split(";")
                ] if self.class_mixes else []

    @property
    def mixed_traffic(self) -> bool:
        """Whether batches draw a share of automated followers (the rest human-driven)."""
        return self.cav_share_min < 1

    @property
    def validation_channel(self) -> ChannelConfig:
        """V2V of validation (:func:`benchmark.policy_eval.validation_evaluator`): the training
        episodes' ``comm_delay_s`` and ``packet_loss`` in the ``accel`` mode; ideal in
        ``ovm-gain``, whose observation the training env forms without a channel."""
        if self.action_mode != "accel":
            return ChannelConfig()
        return ChannelConfig(self.comm_delay_s, self.packet_loss)

    @functools.cached_property
    def roads(self) -> list[Scenario]:
        """The scenarios ``scenarios`` names, built once (none when it is empty)."""
        from envs.scenarios import parse_scenarios

        return parse_scenarios(self.scenarios) if self.scenarios else []

    def validation_roads(self, scenario: Scenario) -> list[Scenario]:
        """The roads validation scores a policy on: the run's ``scenario``; with ``scenarios``
        each of them instead; on mixed traffic each with half its followers automated, placed
        at random (placement seed 0), and a ring also as it is (by default one automated
        vehicle among humans)."""
        roads = self.roads or [scenario]
        if self.class_mixes:  # the first arrangement, in the order of class_seed 0
            from envs.vehicle_classes import canonical_classes

            mix = canonical_classes(self.mixes[0])
            roads = [sc.derive(class_mix=mix, class_seed=0) for sc in roads]
        if not self.mixed_traffic:
            return roads
        return [road for sc in roads for road in ([sc] if sc.ring else []) + [
            sc.derive(cav_fraction=0.5, placement="random")]]

    @property
    def per_agent(self) -> bool:
        """One actor and critic per agent (``ippo-bdc``) instead of one shared by all."""
        return self.algo == "ippo-bdc"

    @property
    def obs_dim(self) -> int:
        """Floats per agent the networks read (the ``ovm-gain`` observation gets the position
        features appended; the ``accel`` one has them), plus the class features
        (``class_features``)."""
        from envs.vehicle_classes import CLASS_FEATURE_NAMES

        extra = len(CLASS_FEATURE_NAMES) if self.class_features else 0
        return (12 if self.action_mode == "accel" else 15 + 3) + extra


# ---------------------------------------------------------------------------- networks
class StackedLinear(BatchedLinear):
    """One linear layer per agent with the agent axis second to last: ``(..., N, n_in) ->
    (..., N, n_out)`` (one batched product; the agent axis stays where the consensus rules
    want it)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, d = x.shape[-2:]
        rows = x.reshape(-1, n, d).transpose(0, 1)  # (N, M, n_in)
        return super().forward(rows).transpose(0, 1).reshape(*x.shape[:-1], -1)


def _mlp(n_in: int, hidden: int, n_out: int, gain: float, n_agents: int = 0) -> nn.Sequential:
    """Two ReLU layers, orthogonal init (CleanRL's ``layer_init``), shared (``n_agents`` 0) or
    one per agent. ReLU, not CleanRL's tanh: this torch build's CPU tanh took 2.1 ms on a
    (8192, 64) batch against ReLU's 0.07 ms (one thread), most of a training step."""
    sizes = ((n_in, hidden), (hidden, hidden), (hidden, n_out))
    gains = (math.sqrt(2), math.sqrt(2), gain)
    if n_agents:  # each agent's weights drawn as an nn.Linear's, in order
        linears: list[nn.Module] = [StackedLinear(n_agents, a, b, g)
                                    for (a, b), g in zip(sizes, gains)]
    else:  # all built (their default init drawn), then re-initialised
        shared = [nn.Linear(a, b) for a, b in sizes]
        for layer, g in zip(shared, gains):
            nn.init.orthogonal_(layer.weight, g)
            nn.init.zeros_(layer.bias)
        linears = list(shared)
    return nn.Sequential(linears[0], nn.ReLU(), linears[1], nn.ReLU(), linears[2])


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
        self.class_features = bool(config.class_features)  # its input ends with them
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
    """Value of each agent: its observation (IPPO), or with the platoon's mean beside it (MAPPO),
    and (``critic_time``) the episode's elapsed fraction."""

    def __init__(self, config: PPOConfig, n_agents: int = 0) -> None:
        super().__init__()
        self.central = config.algo == "mappo"
        self.timed = bool(config.critic_time)
        n_in = config.obs_dim * (2 if self.central else 1) + (1 if self.timed else 0)
        self.body = _mlp(n_in, config.hidden, 1, 1.0, n_agents)

    def inputs(self, obs: torch.Tensor, elapsed: float = 0.0) -> torch.Tensor:
        """What the critic reads of ``obs (..., N, D)`` at the elapsed fraction ``elapsed`` of
        the episode: ``(..., N, D)`` or ``(..., N, 2 D)``, plus one column if timed."""
        x = obs
        if self.central:
            x = torch.cat([obs, obs.mean(dim=-2, keepdim=True).expand_as(obs)], dim=-1)
        if self.timed:
            x = torch.cat([x, torch.full((*obs.shape[:-1], 1), float(elapsed),
                                         dtype=obs.dtype)], dim=-1)
        return x

    def forward(self, obs: torch.Tensor, elapsed: float = 0.0) -> torch.Tensor:
        """``obs (..., N, D)`` -> values ``(..., N)``."""
        return self.body(self.inputs(obs, elapsed))[..., 0]


# ---------------------------------------------------------------------------- weights
def check_finite_weights(modules: tuple[torch.nn.Module, ...], run: str, after: str) -> None:
    """Stop a training whose weights became NaN or infinite (a NaN policy scores no collision
    and would be kept as the best snapshot): :class:`TrainingDivergedError`, nothing written."""
    if not all(bool(torch.isfinite(p).all()) for m in modules for p in m.parameters()):
        raise TrainingDivergedError(
            f"{run}: the weights became non-finite after {after}; nothing was written; lower "
            "the learning rate (--set lr=...) or check the other --set options")


def as_shipped(actor: SharedActor) -> SharedActor:
    """A copy of ``actor`` with its weights rounded through float16, as a checkpoint stores
    them: validation judges, and selection keeps, exactly what ships."""
    out = copy.deepcopy(actor)
    with torch.no_grad():
        for key, value in out.state_dict().items():
            if key != "obs_count":
                value.copy_(value.to(torch.float16).to(value.dtype))
    out.eval()
    return out
