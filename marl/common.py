"""Shared machinery of the MARL learners: the A2C config, network interface, rollout, update.

Every algorithm file (``ia2c.py``, ``fprint.py``, ``dial.py``, ``commnet.py``, ``wac.py``,
``dcea.py``, ``bdc.py``) defines its config (a frozen subclass of :class:`A2CConfig`), its
network (a subclass of :class:`AgentNet`) and its distinctive update hooks (an
:class:`Algorithm`) as its ``ALGORITHM``; :func:`run_training` (or ``cacc-bench train``) trains
any of them: ``run_training(algorithm("bdc"), config, "catchup-v1")``.

Layout: activations are agent-major ``(N, B, F)``; all N agents' networks run as one batched
tensor op (:mod:`marl.layers`). B episodes run in parallel in one batched
:class:`envs.platoon.PlatoonEnv` (``training=True, collision_mode="published"``); one batched
step of B active episodes counts as B environment steps.

Learner (published A2C, ``docs/spec/marl.md``): n-step segments (60 steps; every episode length and
every published collision end is a multiple of 60), bootstrap from V of the observation after
the segment (0 if terminal), truncated backprop through the LSTM within a segment, entropy
bonus, per-agent global grad-norm clip, RMSprop. The acting LSTM state advances exactly once per
observation: at a segment boundary the bootstrap forward is computed without gradient from the
detached state and the next segment recomputes that same transition with gradient, re-using the
actions sampled for the bootstrap.
"""

from __future__ import annotations

import csv
import dataclasses
import importlib
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from envs.dynamics import BLOCK_DIM, OBS_DIM
from envs.errors import ConfigError, TrainingDivergedError, UnknownNameError
from envs.naming import checkpoint_stem
from envs.params import EVAL_MODES, MARL_ALGORITHMS, OVM_ACTIONS, RewardWeights
from envs.platoon import PlatoonEnv
from envs.scenarios import make_scenario
from marl.layers import BatchedLinear, BatchedLSTMCell, per_agent_clip_
from marl.returns import nstep_returns, share_rewards

N_ACTIONS = len(OVM_ACTIONS)
BLOCK_FLOATS = BLOCK_DIM
FLOAT_BITS = 32
COLLISION_VALUES: tuple[str, ...] = ("absorbing", "published")
ALGORITHM_NAMES: tuple[str, ...] = MARL_ALGORITHMS

State = dict[str, torch.Tensor]
ProgressFn = Callable[[int, int, dict[str, float]], None]


@dataclass(frozen=True)
class A2CConfig:
    """Hyper-parameters shared by every learner (paper values; published code's where silent).

    Attributes
    ----------
    n_step : int
        Steps per update segment (published 60).
    gamma : float
        Discount (paper 0.99).
    hidden : int
        Width of the FC encoder and the LSTM (paper 64).
    actor_lr, critic_lr : float
        RMSprop learning rates of actor and critic parameters (paper 5e-4 and 2.5e-4; a shared
        trunk learns at the actor rate).
    rmsprop_alpha, rmsprop_eps : float
        RMSprop smoothing and epsilon (published 0.99, 1e-5).
    entropy_coef, value_coef : float
        Loss weights (published 0.05 and 0.5).
    grad_clip : float
        Global grad-norm clip per agent (published 40).
    reward_scale : float
        Rewards are multiplied by this for learning (published 1/800 IA2C family, 1/5000
        DIAL/CommNet).
    reward_alpha : float or None
        Reward sharing: agent i learns from ``sum_j alpha^|i-j| r_j`` (0 local, 1 global). None
        (default): the published config's value for the scenario family and the algorithm's
        family (:attr:`PUBLISHED_REWARD_ALPHA`; the IA2C family uses 1 on catchup and 0 on
        slowdown, DIAL and CommNet 1 everywhere, the consensus family WAC, DCEA and BDC 0
        everywhere), resolved when training starts and recorded in
        the checkpoint.
    entropy_coef_final : float or None
        Entropy coefficient reached at the end of the run, linearly from ``entropy_coef``
        (None: constant, as published; default 0.005, a departure).
    return_norm : bool
        Divide the (scaled, shared) rewards by the running standard deviation of the discounted
        return before the update (off by default, as published).
    collision_value : {"absorbing", "published"}
        What an episode ended early by the published collision rule is worth afterwards:
        ``published`` 0 (terminal); ``absorbing`` (default, a departure) the collision penalty at
        every step to the scheduled end, folded into the last step's return.
    advantage_norm : bool
        Standardise each agent's advantages over the running entries of every segment before
        the policy loss (:func:`normalise_advantages`; off by default, as published).
    episodes_parallel : int
        B episodes stepped together (sample budget counts all of them).
    lr_scale : float
        Multiplier on both learning rates (4.0 with B = 8; 1.0: the paper's per-update rates).
    eval_every_steps : int
        Environment steps between evaluations on the validation seeds, in both modes (learning
        curve and checkpoint selection: the kept snapshot is the evaluated one with the fewest
        collisions, then the best reward, in ``selection_mode``; a tie goes to the later one).
    selection_mode : {"sampled", "greedy"}
        Evaluation mode in which the kept snapshot is chosen on the validation seeds (the mode
        the policy controller is evaluated in; default ``sampled``, the policy as trained).
    reward_w_gap, reward_w_speed, reward_w_accel, reward_w_safety, reward_w_power : float
        Weights w1..w5 of the **training** reward (paper: -1, -1, -0.1, -5, -10; power in kW).
        The benchmark always scores with the paper's weights; other values are a documented
        shaping of the learning signal, recorded in the checkpoint.
    power_baseline_kw : float or None
        Constant power subtracted from every running agent's power for learning: the power term
        becomes ``w5 (P - P0)``. 0 (default): the paper's term. None: the cruise power
        ``P(v*, 0)`` at the scenario's target speed, resolved when training starts and recorded.
    min_active_fraction : float
        At an n-step boundary, when fewer than this fraction of the B episodes are still running,
        the rest are truncated (bootstrapped) and a new batch starts (0, default: never).

    Why each departure exists and what the options measured: ``docs/learner-options.md``.
    """

    n_step: int = 60
    gamma: float = 0.99
    hidden: int = 64
    actor_lr: float = 5e-4
    critic_lr: float = 2.5e-4
    rmsprop_alpha: float = 0.99
    rmsprop_eps: float = 1e-5
    entropy_coef: float = 0.05
    value_coef: float = 0.5
    grad_clip: float = 40.0
    reward_scale: float = 1.0 / 800.0
    reward_alpha: float | None = None
    entropy_coef_final: float | None = 0.005
    return_norm: bool = False
    collision_value: str = "absorbing"
    advantage_norm: bool = False
    episodes_parallel: int = 8
    lr_scale: float = 4.0
    eval_every_steps: int = 20_000
    selection_mode: str = "sampled"
    reward_w_gap: float = -1.0
    reward_w_speed: float = -1.0
    reward_w_accel: float = -0.1
    reward_w_safety: float = -5.0
    reward_w_power: float = -10.0
    power_baseline_kw: float | None = 0.0
    min_active_fraction: float = 0.0

    def __post_init__(self) -> None:
        if self.n_step < 1 or self.hidden < 1 or self.episodes_parallel < 1:
            raise ConfigError("n_step, hidden and episodes_parallel must be >= 1")
        if not 0 < self.gamma <= 1:
            raise ConfigError(f"gamma must lie in (0, 1], got {self.gamma}")
        if self.reward_alpha is not None and not 0 <= self.reward_alpha <= 1:
            raise ConfigError(f"reward_alpha must lie in [0, 1], got {self.reward_alpha}")
        if self.entropy_coef_final is not None and self.entropy_coef_final < 0:
            raise ConfigError(f"entropy_coef_final must be >= 0, got {self.entropy_coef_final}")
        if self.collision_value not in COLLISION_VALUES:
            raise ConfigError(
                f"collision_value must be one of {', '.join(COLLISION_VALUES)}, "
                f"got {self.collision_value!r}"
            )
        if self.selection_mode not in EVAL_MODES:
            raise ConfigError(
                f"selection_mode must be one of {', '.join(EVAL_MODES)}, got {self.selection_mode!r}"
            )
        for name in ("reward_w_gap", "reward_w_speed", "reward_w_accel", "reward_w_safety",
                     "reward_w_power"):
            if getattr(self, name) > 0:
                raise ConfigError(f"{name} is a cost weight and must be <= 0, got {getattr(self, name)}")
        if self.power_baseline_kw is not None and not math.isfinite(self.power_baseline_kw):
            raise ConfigError(f"power_baseline_kw must be finite, got {self.power_baseline_kw}")
        for name in ("actor_lr", "critic_lr", "reward_scale", "grad_clip", "lr_scale"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}")

    #: Published reward sharing (``coop_gamma`` of the published configs) by scenario family
    #: (the scenario id up to its first ``-``); other scenarios use :attr:`DEFAULT_REWARD_ALPHA`.
    PUBLISHED_REWARD_ALPHA: ClassVar[dict[str, float]] = {"catchup": 1.0, "slowdown": 0.0}
    DEFAULT_REWARD_ALPHA: ClassVar[float] = 1.0

    def resolved(self, scenario_id: str) -> A2CConfig:
        """This config with ``reward_alpha`` and ``power_baseline_kw`` filled in for
        ``scenario_id`` (where they were None)."""
        out: A2CConfig = self
        if out.reward_alpha is None:
            family = scenario_id.split("-")[0]
            alpha = self.PUBLISHED_REWARD_ALPHA.get(family, self.DEFAULT_REWARD_ALPHA)
            out = dataclasses.replace(out, reward_alpha=alpha)
        if out.power_baseline_kw is None:
            from envs.energy import load_power_polynomial

            v_star = make_scenario(scenario_id).target_speed_mps
            p0 = float(load_power_polynomial()(np.array([v_star]), np.array([0.0]))[0])
            out = dataclasses.replace(out, power_baseline_kw=round(p0, 6))
        return out

    def reward_weights(self) -> RewardWeights:
        """The training reward's weights (the benchmark scores with ``RewardWeights()``)."""
        return RewardWeights(
            gap=self.reward_w_gap,
            speed=self.reward_w_speed,
            accel=self.reward_w_accel,
            safety=self.reward_w_safety,
            power=self.reward_w_power,
        )

    def entropy_at(self, fraction: float) -> float:
        """Entropy coefficient after ``fraction`` (0..1) of the run."""
        if self.entropy_coef_final is None:
            return self.entropy_coef
        f = min(max(fraction, 0.0), 1.0)
        return self.entropy_coef + (self.entropy_coef_final - self.entropy_coef) * f


# ---------------------------------------------------------------------------- networks
def shift_front(x: torch.Tensor) -> torch.Tensor:
    """What each agent gets from its front neighbour: ``out[i] = x[i-1]``, 0 for agent 0."""
    out = torch.zeros_like(x)
    out[1:] = x[:-1]
    return out


def shift_rear(x: torch.Tensor) -> torch.Tensor:
    """What each agent gets from its rear neighbour: ``out[i] = x[i+1]``, 0 for the last."""
    out = torch.zeros_like(x)
    out[:-1] = x[1:]
    return out


def neighbour_action_onehot(actions: torch.Tensor) -> torch.Tensor:
    """``(N, B)`` actions -> ``(N, B, 8)``: front and rear neighbours' one-hot actions."""
    onehot = nn.functional.one_hot(actions, N_ACTIONS).to(torch.float32)
    return torch.cat([shift_front(onehot), shift_rear(onehot)], dim=-1)


class AgentNet(nn.Module):
    """N agents' actor-critic networks, batched. Subclasses define the distinctive parts.

    A step is split so that training can batch the non-recurrent layers over a whole segment:
    :meth:`encode` (per-step inputs, any number of rows), :meth:`recur` (the recurrent part,
    one step, where received messages enter), then :meth:`logits` and :meth:`value` (heads, any
    number of rows). ``out`` dicts hold ``h`` (actor features) and ``v`` (critic features).

    Attributes
    ----------
    msg_width : int
        Floats each agent broadcasts per step besides its 5-float vehicle block (0, 4 or 64).
    differentiable_messages : bool
        Whether gradients flow through messages (DIAL, CommNet): the training recompute then
        re-derives messages from the recomputed states instead of re-using the received ones.
    with_critic : bool
        Whether the critic is built (not for acting from a checkpoint).
    """

    msg_width: int = 0
    differentiable_messages: bool = False
    actor_head: BatchedLinear
    critic_head: BatchedLinear

    def __init__(self, n_agents: int, hidden: int, with_critic: bool) -> None:
        super().__init__()
        self.n_agents = n_agents
        self.hidden = hidden
        self.with_critic = with_critic

    def initial_state(self, batch: int) -> State:
        """Recurrent state at episode start."""
        z = torch.zeros(self.n_agents, batch, self.hidden)
        return {"h": z, "c": z.clone()}

    def message(self, state: State) -> torch.Tensor | None:
        """What every agent broadcasts this step, ``(N, B, msg_width)`` (None: nothing)."""
        return None

    def encode(self, obs: torch.Tensor) -> dict[str, torch.Tensor]:
        """Non-recurrent encoding of observations ``(N, M, 15)``."""
        raise NotImplementedError

    def recur(
        self,
        enc: dict[str, torch.Tensor],
        state: State,
        front: torch.Tensor | None,
        rear: torch.Tensor | None,
    ) -> tuple[dict[str, torch.Tensor], State]:
        """One recurrent step from the encoding and the received messages ``(N, B, W)``."""
        raise NotImplementedError

    def logits(self, out: dict[str, torch.Tensor]) -> torch.Tensor:
        """Action logits ``(N, M, 4)``."""
        return self.actor_head(out["h"])

    def value(self, out: dict[str, torch.Tensor], nb_actions: torch.Tensor) -> torch.Tensor:
        """State value ``(N, M)`` from critic features and neighbours' one-hot actions."""
        return self.critic_head(torch.cat([out["v"], nb_actions], dim=-1)).squeeze(-1)

    def after_policy(self, state: State, logits: torch.Tensor) -> State:
        """Update the state with this step's policy (FPrint keeps it as its fingerprint)."""
        return state

    def act_step(
        self,
        obs: torch.Tensor,
        state: State,
        front: torch.Tensor | None,
        rear: torch.Tensor | None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], State]:
        """Acting step: ``obs (N, B, 15)`` -> logits ``(N, B, 4)``, features, new state."""
        out, new = self.recur(self.encode(obs), state, front, rear)
        logits = self.logits(out)
        return logits, out, self.after_policy(new, logits)

    def actor_parameters(self) -> list[nn.Parameter]:
        """Parameters learning at the actor rate (everything but :meth:`critic_parameters`)."""
        critic = {id(p) for p in self.critic_parameters()}
        return [p for p in self.parameters() if id(p) not in critic]

    def critic_parameters(self) -> list[nn.Parameter]:
        """Parameters learning at the critic rate (names starting with ``critic``)."""
        return [p for n, p in self.named_parameters() if n.startswith("critic")]

    def acting_state_dict(self) -> dict[str, torch.Tensor]:
        """The weights needed to act (what a checkpoint stores): all but the critic's."""
        return {k: v for k, v in self.state_dict().items() if not k.startswith("critic")}


class SharedTrunkNet(AgentNet):
    """FC 64 (ReLU) -> LSTM 64 shared by an actor head and a critic head (published IA2C).

    Subclasses add message inputs in :meth:`lstm_input`.
    """

    def __init__(
        self,
        n_agents: int,
        hidden: int = 64,
        with_critic: bool = True,
        lstm_in: int | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__(n_agents, hidden, with_critic)
        g = generator
        self.fc = BatchedLinear(n_agents, OBS_DIM, hidden, math.sqrt(2.0), g)
        self.lstm = BatchedLSTMCell(n_agents, lstm_in or hidden, hidden, g)
        self.actor_head = BatchedLinear(n_agents, hidden, N_ACTIONS, 0.01, g)
        if with_critic:
            self.critic_head = BatchedLinear(n_agents, hidden + 2 * N_ACTIONS, 1, 1.0, g)

    def encode(self, obs):
        x = torch.relu(self.fc(obs))
        return {"gx": self.lstm.input_gates(x, slice(0, self.hidden))}

    def message_gates(
        self, state: State, front: torch.Tensor | None, rear: torch.Tensor | None
    ) -> torch.Tensor | None:
        """Extra LSTM input gates from the received messages (None: no messages)."""
        return None

    def recur(self, enc, state, front, rear):
        gates = enc["gx"]
        extra = self.message_gates(state, front, rear)
        if extra is not None:
            gates = gates + extra
        h, c = self.lstm.step_from_gates(gates, (state["h"], state["c"]))
        new = dict(state)
        new["h"], new["c"] = h, c
        return {"h": h, "v": h}, new


class SeparateActorCriticNet(AgentNet):
    """Separate actor (FC -> LSTM -> logits) and critic (FC -> LSTM -> value) per agent.

    Used by the consensus learners (WAC, DCEA, BDC): the critic's LSTM is what neighbours share.
    """

    def __init__(
        self,
        n_agents: int,
        hidden: int = 64,
        with_critic: bool = True,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__(n_agents, hidden, with_critic)
        g = generator
        self.fc = BatchedLinear(n_agents, OBS_DIM, hidden, math.sqrt(2.0), g)
        self.lstm = BatchedLSTMCell(n_agents, hidden, hidden, g)
        self.actor_head = BatchedLinear(n_agents, hidden, N_ACTIONS, 0.01, g)
        if with_critic:
            self.critic_fc = BatchedLinear(n_agents, OBS_DIM, hidden, math.sqrt(2.0), g)
            self.critic_lstm = BatchedLSTMCell(n_agents, hidden, hidden, g)
            self.critic_head = BatchedLinear(n_agents, hidden + 2 * N_ACTIONS, 1, 1.0, g)

    def initial_state(self, batch: int) -> State:
        state = super().initial_state(batch)
        if self.with_critic:
            state["ch"] = torch.zeros_like(state["h"])
            state["cc"] = torch.zeros_like(state["h"])
        return state

    def encode(self, obs):
        enc = {"gx": self.lstm.input_gates(torch.relu(self.fc(obs)))}
        if self.with_critic:
            enc["cgx"] = self.critic_lstm.input_gates(torch.relu(self.critic_fc(obs)))
        return enc

    def recur(self, enc, state, front, rear):
        h, c = self.lstm.step_from_gates(enc["gx"], (state["h"], state["c"]))
        new = {"h": h, "c": c}
        out = {"h": h}
        if self.with_critic:
            ch, cc = self.critic_lstm.step_from_gates(enc["cgx"], (state["ch"], state["cc"]))
            new["ch"], new["cc"] = ch, cc
            out["v"] = ch
        return out, new

    def shared_critic_parameters(self, whole_critic: bool = False) -> list[nn.Parameter]:
        """What neighbours exchange: the critic LSTM (published) or the whole critic."""
        if whole_critic:
            return self.critic_parameters()
        return list(self.critic_lstm.parameters())


# ---------------------------------------------------------------------------- algorithm
class Algorithm:
    """An algorithm's distinctive parts: its network and its hooks around the update.

    Subclasses set ``name``, ``config_cls`` and implement :meth:`build_net`; the hooks default
    to nothing.
    """

    name: str = "a2c"
    config_cls: type[A2CConfig] = A2CConfig

    def build_net(
        self,
        config: Any,
        n_agents: int,
        with_critic: bool = True,
        generator: torch.Generator | None = None,
    ) -> AgentNet:
        """The batched network of N agents."""
        raise NotImplementedError

    def setup(self, trainer: Trainer) -> None:
        """Called once after the network and optimiser exist."""

    def before_step(self, trainer: Trainer) -> None:
        """After backward and per-agent clipping, before the optimiser step (e.g. QSGD)."""

    def after_step(self, trainer: Trainer) -> None:
        """After the optimiser step (e.g. a consensus round)."""


def execution_bits_per_agent_step(net: AgentNet) -> int:
    """V2V bits one agent sends per step at execution: its vehicle block plus its message."""
    return (BLOCK_FLOATS + net.msg_width) * FLOAT_BITS


#: Bits of one action index (4 actions) sent to the neighbours for their critics in training.
ACTION_BITS = 2


def training_step_bits_per_agent(net: AgentNet) -> int:
    """Bits one agent sends per environment step **in training**, beyond the consensus rounds.

    Received by its front and rear neighbours: everything it sends at execution
    (:func:`execution_bits_per_agent_step`), its action index for their critics (2 bits, one
    broadcast), and, where gradients flow through messages (DIAL, CommNet), the gradient of its
    own loss with respect to each neighbour's message (``msg_width`` floats to each of the two,
    one at the ends of the chain: counted as two).
    """
    grad = 2 * net.msg_width * FLOAT_BITS if net.differentiable_messages else 0
    return execution_bits_per_agent_step(net) + ACTION_BITS + grad


def exchange(net: AgentNet, state: State) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """Training-time message passing (instant, lossless): front and rear neighbours' messages."""
    msg = net.message(state)
    if msg is None:
        return None, None
    return shift_front(msg), shift_rear(msg)


# ---------------------------------------------------------------------------- trainer
@dataclass
class TrainResult:
    """What :func:`run_training` returns."""

    algo: str
    scenario: str
    n_vehicles: int
    seed: int
    steps: int
    episodes: int
    wall_s: float
    env_steps_per_s: float
    bits: dict[str, float]
    curve: list[dict[str, float]] = field(default_factory=list)
    checkpoint: Path | None = None
    final_checkpoint: Path | None = None
    curve_csv: Path | None = None


class Trainer:
    """On-policy A2C over a batched env; algorithm hooks add the distinctive parts."""

    def __init__(
        self,
        algo: Algorithm,
        config: A2CConfig,
        scenario_id: str,
        n_vehicles: int,
        seed: int,
    ) -> None:
        torch.set_num_threads(1)
        self.algo = algo
        self.config = config = config.resolved(scenario_id)
        self.scenario_id = scenario_id
        self.n_vehicles = n_vehicles
        self.seed = seed
        self.generator = torch.Generator().manual_seed(seed)
        self.env = PlatoonEnv(
            make_scenario(scenario_id), n_vehicles, training=True, collision_mode="published",
            weights=config.reward_weights(),
        )
        assert config.power_baseline_kw is not None  # resolved above
        #: per running agent and step, added to the env's reward: ``-w5 P0`` (0 as published)
        self._baseline_reward = -config.reward_w_power * config.power_baseline_kw
        self.net = algo.build_net(config, n_vehicles, True, self.generator)
        self.optimizer = torch.optim.RMSprop(
            [
                {"params": self.net.actor_parameters(), "lr": config.actor_lr * config.lr_scale},
                {"params": self.net.critic_parameters(), "lr": config.critic_lr * config.lr_scale},
            ],
            alpha=config.rmsprop_alpha,
            eps=config.rmsprop_eps,
        )
        self.params = [p for g in self.optimizer.param_groups for p in g["params"]]
        self.steps = 0
        #: the run's step budget (entropy schedule); :func:`run_training` sets it
        self.total_steps = 0
        self.episodes = 0
        self.updates = 0
        #: training bits over the run, per agent: consensus messages sent to the neighbours,
        #: and the payload of QSGD-compressed gradients that are applied locally (sent nowhere)
        self.bits: dict[str, float] = {"consensus": 0.0, "qsgd_local": 0.0}
        self._episode_counter = 0
        #: running (count, mean, sum of squared deviations) of discounted returns (return_norm)
        self._return_stats: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._return_acc = torch.zeros(0)
        algo.setup(self)

    # -- sampling
    def _sample(self, logits: torch.Tensor) -> torch.Tensor:
        u = torch.rand(logits.shape, generator=self.generator).clamp_(1e-12, 1.0)
        return (logits - torch.log(-torch.log(u))).argmax(-1)

    def _training_seeds(self, batch: int) -> np.ndarray:
        base = 10_000_000 * (self.seed + 1)
        seeds = base + self._episode_counter + np.arange(batch)
        self._episode_counter += batch
        return seeds

    @torch.no_grad()
    def _act(self, obs_np: np.ndarray, state: State) -> dict[str, Any]:
        """No-grad acting step: observation, messages received, logits, actions, next state."""
        obs = torch.from_numpy(obs_np).transpose(0, 1).contiguous()
        front, rear = exchange(self.net, state)
        logits, out, new = self.net.act_step(obs, state, front, rear)
        actions = self._sample(logits)
        return {
            "obs": obs,
            "front": front,
            "rear": rear,
            "out": out,
            "logits": logits,
            "actions": actions,
            "state": new,
        }

    def run_batch(self) -> tuple[int, float]:
        """Run B episodes to the end with an update every n steps.

        Returns the environment steps taken and the mean training reward (the learner's own,
        shaped when the config says so; mean over steps of the
        sum over agents, as the paper reports).
        """
        cfg, net, env = self.config, self.net, self.env
        b = cfg.episodes_parallel
        obs_np = env.reset(self._training_seeds(b))
        self._return_acc = torch.zeros(b, self.n_vehicles)
        assert obs_np is not None
        state = net.initial_state(b)
        cur = self._act(obs_np, state)
        active = np.ones(b, dtype=bool)
        ep_reward = np.zeros(b)
        ep_len = np.zeros(b)
        steps = 0
        t_episode = 0  # steps since reset (all B episodes start together)
        finished = False
        while not finished:
            seg_state = state
            record: list[dict[str, Any]] = []
            rews, masks, terms, absorbed = [], [], [], []
            for _ in range(cfg.n_step):
                record.append(cur)
                res = env.step_actions(cur["actions"].T.numpy())
                t_episode += 1
                state = cur["state"]
                masks.append(active.copy())
                terms.append(res.done & active)
                if self._baseline_reward:
                    running = active & ~res.collided
                    rews.append(res.reward + self._baseline_reward * running[:, None])
                else:
                    rews.append(res.reward)
                crashed = res.done & res.collided & active
                absorbed.append(
                    self._absorbing_value(env.n_steps - t_episode) * crashed
                    if crashed.any() else np.zeros(b)
                )
                steps += int(active.sum())
                ep_reward += np.where(active, rews[-1].sum(1), 0.0)
                ep_len += active
                active = ~res.done
                if res.done.all():
                    finished = True
                    break
                assert res.observation is not None
                cur = self._act(res.observation, state)
            if finished:
                bootstrap = torch.zeros(b, self.n_vehicles)
            else:
                with torch.no_grad():
                    nb = neighbour_action_onehot(cur["actions"])
                    bootstrap = net.value(cur["out"], nb).T
            self._update(seg_state, record, rews, masks, terms, bootstrap, absorbed)
            if not finished and active.sum() < cfg.min_active_fraction * b:
                # most episodes ended (published collision rule): truncate the rest (their last
                # segment was bootstrapped) instead of stepping finished episodes
                finished = True
            if not finished:
                # act on the next observation with the updated weights (same state, no re-advance)
                cur = self._act(cur["obs"].transpose(0, 1).numpy(), state)
        self.steps += steps
        self.episodes += b
        return steps, float((ep_reward / np.maximum(ep_len, 1)).mean())

    @torch.no_grad()
    def _return_scale(
        self, reward: torch.Tensor, term: torch.Tensor, mask: torch.Tensor
    ) -> torch.Tensor:
        """Running standard deviation of the discounted return (``return_norm``).

        The return of every agent of every running episode is accumulated step by step across
        segments (``G <- gamma G + r``, reset at episode end) and its mean and variance are
        merged into running totals (Chan et al.), as Stable-Baselines3's reward normalisation.
        """
        cfg = self.config
        acc = self._return_acc
        rets = []
        for t in range(reward.shape[0]):
            acc = acc * cfg.gamma + reward[t]
            rets.append(acc)
            acc = acc * (~term[t]).to(acc.dtype).unsqueeze(-1)
        self._return_acc = acc
        x = torch.stack(rets)[mask.expand_as(reward) > 0].to(torch.float64)
        if x.numel():
            n_b, mean_b, var_b = float(x.numel()), float(x.mean()), float(x.var(unbiased=False))
            n_a, mean_a, m2_a = self._return_stats
            n = n_a + n_b
            delta = mean_b - mean_a
            m2 = m2_a + var_b * n_b + delta * delta * n_a * n_b / n
            self._return_stats = (n, mean_a + delta * n_b / n, m2)
        n, _, m2 = self._return_stats
        std = math.sqrt(m2 / n) if n > 0 else 1.0
        return torch.tensor(max(std, 1e-6), dtype=reward.dtype)

    def _absorbing_value(self, remaining_steps: int) -> float:
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

    def _recompute(
        self, seg_state: State, record: list[dict[str, Any]]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Re-run the segment with gradient: logits ``(T, N, B, 4)``, values ``(T, N, B)``,
        actions ``(T, N, B)``. Non-recurrent layers run once over the whole segment."""
        net = self.net
        t_len = len(record)
        n, b = self.n_vehicles, self.config.episodes_parallel
        obs = torch.stack([r["obs"] for r in record], 1).reshape(n, t_len * b, OBS_DIM)
        enc = {k: v.reshape(n, t_len, b, -1) for k, v in net.encode(obs).items()}
        # unbind, not enc[k][:, t]: the backward of T selects would allocate and zero-fill a
        # full-size gradient per step (measured: 85 % of BDC's training time); unbind's backward
        # stacks once
        enc_t = {k: v.unbind(1) for k, v in enc.items()}
        state = seg_state
        outs = []
        for t in range(t_len):
            if net.differentiable_messages:
                front, rear = exchange(net, state)
            else:
                front, rear = record[t]["front"], record[t]["rear"]
            out, state = net.recur({k: v[t] for k, v in enc_t.items()}, state, front, rear)
            outs.append(out)
        flat = {k: torch.stack([o[k] for o in outs], 1).reshape(n, t_len * b, -1) for k in outs[0]}
        actions = torch.stack([r["actions"] for r in record], 1).reshape(n, t_len * b)
        logits = net.logits(flat).reshape(n, t_len, b, N_ACTIONS)
        nb = neighbour_action_onehot(actions)
        values = net.value(flat, nb).reshape(n, t_len, b)
        return (
            logits.permute(1, 0, 2, 3),
            values.permute(1, 0, 2),
            actions.reshape(n, t_len, b).permute(1, 0, 2),
        )

    def _update(
        self, seg_state, record, rews, masks, terms, bootstrap: torch.Tensor, absorbed
    ) -> None:
        cfg = self.config
        logits, values, actions = self._recompute(seg_state, record)
        mask = torch.from_numpy(np.stack(masks)).to(torch.float32).unsqueeze(-1)  # (T, B, 1)
        term = torch.from_numpy(np.stack(terms))
        reward = torch.from_numpy(np.stack(rews)).to(torch.float32)
        # R_t = r_t + gamma V_absorbing at a step that ended the episode by collision
        extra = torch.from_numpy(np.stack(absorbed)).to(torch.float32)  # (T, B)
        reward = reward + cfg.gamma * extra.unsqueeze(-1)
        assert cfg.reward_alpha is not None  # resolved in __init__
        reward = share_rewards(reward * cfg.reward_scale, cfg.reward_alpha)
        if cfg.return_norm:
            reward = reward / self._return_scale(reward, term, mask)
        returns = nstep_returns(reward, bootstrap, term, cfg.gamma)  # (T, B, N)
        terms_ = a2c_losses(logits, actions, values, returns, mask, cfg.advantage_norm)
        ent_coef = cfg.entropy_at(self.steps / self.total_steps if self.total_steps else 0.0)
        loss = terms_["policy"] + cfg.value_coef * terms_["value"] - ent_coef * terms_["entropy"]
        self.optimizer.zero_grad(set_to_none=False)
        loss.backward()
        per_agent_clip_(self.params, cfg.grad_clip)
        self.algo.before_step(self)
        self.optimizer.step()
        self.algo.after_step(self)
        self.updates += 1
        self._check_finite()

    def _check_finite(self) -> None:
        """Stop with a clear error when any weight became NaN or infinite (a NaN policy would
        otherwise act as "action 0" everywhere: the argmax of NaN logits)."""
        bad = [n for n, p in self.net.named_parameters() if not bool(torch.isfinite(p).all())]
        if bad:
            raise TrainingDivergedError(
                f"{self.algo.name} on {self.scenario_id}: weights {', '.join(bad)} became "
                f"non-finite after {self.updates} updates ({self.steps} environment steps "
                "before this batch); lower the learning rates (actor_lr, critic_lr, lr_scale) "
                "or check the algorithm's options. The best checkpoint evaluated so far is kept."
            )


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


# ---------------------------------------------------------------------------- acting
def sample_from_logits(logits: torch.Tensor, uniforms: np.ndarray) -> np.ndarray:
    """Inverse-CDF draws from ``softmax(logits)``: logits ``(N, B, A)``, uniforms ``(B, N)`` in
    [0, 1) -> actions ``(B, N)`` (the first action whose cumulative probability exceeds u)."""
    probs = torch.softmax(logits.to(torch.float64), -1).permute(1, 0, 2).numpy()  # (B, N, A)
    cdf = np.cumsum(probs, axis=-1)
    actions = (uniforms[..., None] >= cdf[..., :-1]).sum(-1)
    return actions.astype(np.int64)


@torch.no_grad()
def policy_actions(
    net: AgentNet,
    obs_np: np.ndarray,
    state: State,
    messages: tuple | None = None,
    uniforms: np.ndarray | None = None,
) -> tuple[np.ndarray, State]:
    """Actions ``(B, N)`` for observations ``(B, N, 15)``: greedy (argmax) when ``uniforms`` is
    None, else drawn from the policy with one uniform ``(B, N)`` per agent
    (:func:`sample_from_logits`). Messages default to instant, lossless exchange."""
    obs = torch.from_numpy(np.ascontiguousarray(obs_np, dtype=np.float32)).transpose(0, 1)
    front, rear = exchange(net, state) if messages is None else messages
    logits, _, state = net.act_step(obs.contiguous(), state, front, rear)
    if uniforms is None:
        return logits.argmax(-1).T.numpy(), state
    return sample_from_logits(logits, uniforms), state


#: Signature of the validation evaluator :func:`run_training` takes: ``(net, mode)`` -> mean over
#: the validation episodes of ``reward`` and ``tracking_reward``, and ``collisions`` (a count).
#: The benchmark's own closed loop provides it (:func:`benchmark.policy_eval.validation_evaluator`).
Evaluator = Callable[["AgentNet", str], dict[str, float]]


# ---------------------------------------------------------------------------- driver
def algorithm(name: str) -> Algorithm:
    """The :class:`Algorithm` of a registered name (module ``marl.<name>``)."""
    if name not in ALGORITHM_NAMES:
        raise UnknownNameError("algorithm", name, ALGORITHM_NAMES)
    module = importlib.import_module(f"marl.{name}")
    return module.ALGORITHM


def config_from_dict(algo: Algorithm, values: dict[str, Any]) -> A2CConfig:
    """Rebuild an algorithm's config from a checkpoint's dict (unknown keys are an error)."""
    names = {f.name for f in dataclasses.fields(algo.config_cls)}
    extra = set(values) - names
    if extra:
        raise ConfigError(f"{algo.name} config has no fields {sorted(extra)}")
    return algo.config_cls(**values)


def run_training(
    algo: Algorithm,
    config: A2CConfig,
    scenario_id: str,
    n_vehicles: int = 8,
    total_steps: int = 600_000,
    seed: int = 0,
    out_dir: str | Path | None = None,
    progress: ProgressFn | None = None,
    log: Callable[[str], None] | None = None,
    schedule_steps: int | None = None,
    evaluate: Evaluator | None = None,
) -> TrainResult:
    """Train ``algo`` for ``total_steps`` environment steps; write checkpoints and curve CSV.

    Every ``config.eval_every_steps`` (and at the end) the policy is evaluated on the validation
    seeds in both modes by ``evaluate``; the snapshot kept as ``<stem>.pt`` is the best in
    ``config.selection_mode`` (fewest collisions, then mean reward; a tie goes to the later
    snapshot). The final weights are saved as ``<stem>.final.pt``.

    Parameters
    ----------
    schedule_steps : int, optional
        Run length the entropy schedule assumes (default ``total_steps``); the throughput
        measurement runs the first steps of a 6e5-step run with it.
    out_dir : path, optional
        Where ``<stem>.pt``, ``<stem>.final.pt`` and ``<stem>.curve.csv`` go (None: write
        nothing, no evaluation; used by the throughput measurement).
    progress : callable(steps, total_steps, info), optional
        Called after every batch of episodes.
    log : callable(str), optional
        Receives one line per evaluation and a summary.
    evaluate : callable(net, mode) -> dict, optional
        Validation evaluator (required with ``out_dir``): the benchmark's closed loop on the
        validation seeds, :func:`benchmark.policy_eval.validation_evaluator`.
    """
    make_scenario(scenario_id)  # fail early on an unknown id
    if out_dir is not None and evaluate is None:
        raise ConfigError(
            "run_training with an output folder needs a validation evaluator: pass "
            "evaluate=benchmark.policy_eval.validation_evaluator(algo, scenario, N)"
        )
    trainer = Trainer(algo, config, scenario_id, n_vehicles, seed)
    trainer.total_steps = schedule_steps or total_steps
    curve: list[dict[str, float]] = []
    next_eval = config.eval_every_steps if out_dir is not None else math.inf
    t0 = time.perf_counter()
    train_time = 0.0
    result = TrainResult(algo.name, scenario_id, n_vehicles, seed, 0, 0, 0.0, 0.0, {}, curve)
    best: tuple[float, float] = (-math.inf, -math.inf)
    select = trainer.config.selection_mode
    while trainer.steps < total_steps:
        tb = time.perf_counter()
        _, train_reward = trainer.run_batch()
        train_time += time.perf_counter() - tb
        row: dict[str, float] = {
            "episode": trainer.episodes,
            "steps": trainer.steps,
            "train_reward": train_reward,
            **{f"eval_{k}_{m}": math.nan for m in EVAL_MODES for k in CURVE_EVAL_KEYS},
        }
        curve.append(row)
        last = trainer.steps >= total_steps
        if trainer.steps >= next_eval or (out_dir is not None and last):
            assert evaluate is not None
            for mode in EVAL_MODES:
                ev = evaluate(trainer.net, mode)
                for k in CURVE_EVAL_KEYS:
                    row[f"eval_{k}_{mode}"] = float(ev[k])
            next_eval = trainer.steps + config.eval_every_steps
            # fewest collisions first: a colliding episode ends early, so its mean reward over
            # the steps it ran can look better than a safe one's; a tie keeps the later snapshot
            score = (-row[f"eval_collisions_{select}"], row[f"eval_reward_{select}"])
            better = score >= best
            best = max(best, score)
            _finish(result, trainer, time.perf_counter() - t0, train_time, out_dir, better)
            if log is not None:
                log(
                    f"steps {trainer.steps} episodes {trainer.episodes} train {train_reward:.2f} "
                    + " ".join(
                        f"{m} {row[f'eval_reward_{m}']:.2f} ({row[f'eval_collisions_{m}']:.0f} "
                        "collisions)" for m in EVAL_MODES
                    )
                    + (" [kept]" if better else "")
                    + f" consensus bits/agent {trainer.bits['consensus']:.0f}"
                )
        if progress is not None:
            progress(trainer.steps, total_steps, row)
    _finish(result, trainer, time.perf_counter() - t0, train_time, out_dir, False, final=True)
    if log is not None:
        log(
            f"done: {trainer.steps} steps in {result.wall_s:.0f} s "
            f"({result.env_steps_per_s:.0f} env steps/s training), execution "
            f"{result.bits['execution_bits_per_vehicle_per_s']:.0f} bit/vehicle/s, training bits "
            f"sent per agent: {result.bits['training_step_bits_per_agent_step']:.0f} per step "
            f"(blocks, messages, action for the critics, message gradients) and consensus "
            f"{result.bits['training_consensus_bits_per_agent']:.0f} in all "
            f"(QSGD applied locally: {result.bits['local_qsgd_payload_bits_per_agent']:.0f} "
            f"bits of payload, not sent); checkpoint {result.checkpoint}"
        )
    return result


#: Validation numbers recorded per mode in the curve (``eval_<key>_<mode>``).
CURVE_EVAL_KEYS: tuple[str, ...] = ("reward", "collisions")


def _finish(
    result: TrainResult,
    trainer: Trainer,
    wall_s: float,
    train_s: float,
    out_dir: str | Path | None,
    save_weights: bool,
    final: bool = False,
) -> None:
    """Fill the result's numbers and (with an output folder) write the curve, the selected
    checkpoint when ``save_weights`` (a new best on the validation seeds) and, when ``final``,
    the final weights.

    Called at every evaluation, so an interrupted run leaves its best checkpoint so far.
    """
    from marl.checkpoint import save_checkpoint

    exec_bits = execution_bits_per_agent_step(trainer.net)
    result.steps, result.episodes = trainer.steps, trainer.episodes
    result.wall_s = wall_s
    result.env_steps_per_s = trainer.steps / max(train_s, 1e-9)
    result.bits = {
        "execution_bits_per_agent_step": float(exec_bits),
        "execution_bits_per_vehicle_per_s": exec_bits / trainer.env.params.dt_s,
        "training_step_bits_per_agent_step": float(training_step_bits_per_agent(trainer.net)),
        "training_consensus_bits_per_agent": trainer.bits["consensus"],
        "local_qsgd_payload_bits_per_agent": trainer.bits["qsgd_local"],
        "updates": float(trainer.updates),
    }
    if out_dir is None:
        return
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = checkpoint_stem(trainer.algo.name, trainer.scenario_id, trainer.n_vehicles, trainer.seed)
    curve = result.curve
    result.curve_csv = out / f"{stem}.curve.csv"
    write_curve(result.curve_csv, curve)
    mode = trainer.config.selection_mode
    evals = [r for r in curve if not math.isnan(r[f"eval_reward_{mode}"])]
    summary = {
        "final_train_reward": curve[-1]["train_reward"] if curve else math.nan,
        "final_eval_reward": evals[-1][f"eval_reward_{mode}"] if evals else math.nan,
        "best_eval_reward": max(r[f"eval_reward_{mode}"] for r in evals) if evals else math.nan,
        "wall_s": wall_s,
        "env_steps_per_s": result.env_steps_per_s,
        "selected_at_steps": float(trainer.steps),
        **{f"selected_eval_{k}_{m}": (evals[-1][f"eval_{k}_{m}"] if evals else math.nan)
           for m in EVAL_MODES for k in CURVE_EVAL_KEYS},
        **result.bits,
    }
    result.checkpoint = out / f"{stem}.pt"

    def save(path: Path) -> None:
        save_checkpoint(
            path,
            algo=trainer.algo.name,
            config=dataclasses.asdict(trainer.config),
            scenario=trainer.scenario_id,
            n_vehicles=trainer.n_vehicles,
            seed=trainer.seed,
            steps=trainer.steps,
            curve_summary={**summary, "total_steps": float(trainer.steps)},
            weights=trainer.net.acting_state_dict(),
        )

    if final:
        result.final_checkpoint = out / f"{stem}.final.pt"
        save(result.final_checkpoint)
    if save_weights:
        save(result.checkpoint)
    elif result.checkpoint.exists():  # keep the selected weights, refresh the run's totals
        data = torch.load(result.checkpoint, weights_only=True)
        kept = {k: v for k, v in data["curve_summary"].items() if k.startswith("selected_")}
        data["curve_summary"].update(summary)
        data["curve_summary"].update(kept)
        data["curve_summary"]["total_steps"] = float(trainer.steps)
        torch.save(data, result.checkpoint)


def write_curve(path: Path, curve: list[dict[str, float]]) -> None:
    """Learning curve CSV: episode, steps, train_reward (the learner's own, possibly shaped,
    reward), and per evaluation mode the validation reward and collisions (empty where not
    evaluated)."""
    evals = [f"eval_{k}_{m}" for m in EVAL_MODES for k in CURVE_EVAL_KEYS]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["episode", "steps", "train_reward", *evals])
        for r in curve:
            cells = ["" if math.isnan(r[k]) else f"{r[k]:.4f}" for k in evals]
            w.writerow([int(r["episode"]), int(r["steps"]), f"{r['train_reward']:.4f}", *cells])


def stderr_log(line: str) -> None:
    """Default log sink."""
    print(line, file=sys.stderr, flush=True)
