"""The MARL learner: on-policy A2C of N agents per platoon, K runs at once, in the order it runs.

Contents, top to bottom: **config** (:class:`A2CConfig`), **networks** (:class:`AgentNet` and its
two trunks, message exchange, bit counts, acting helpers for the benchmark), **algorithms** (the
:class:`Algorithm` record each algorithm file fills), **returns and losses** (pure functions),
**runs** (each run's own state, :class:`Run`), **the trainer** (:class:`Trainer`: rollout
collection, then the update: recompute, losses, per-agent clipping, RMSprop, the algorithm's
gradient compression and consensus), and **the driver** (:func:`run_population`, evaluation on the
validation seeds, checkpoint selection and writing).

Every algorithm file (``ia2c.py``, ``fprint.py``, ``dial.py``, ``commnet.py``, ``wac.py``,
``dcea.py``, ``bdc.py``) defines its config (a frozen subclass of :class:`A2CConfig`), its
network (a subclass of :class:`AgentNet`) and what it does around the update as plain functions,
gathered in its ``ALGORITHM`` (an :class:`Algorithm`); :func:`run_training` (or ``cacc-bench
train``) trains any of them: ``run_training(algorithm("bdc"), config, "catchup-v1")``, and
:func:`run_population` trains several seeds or configs at once (``docs/populations.md``).

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
from collections.abc import Callable, Sequence
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
from envs.platoon import PlatoonEnv, StepResult
from envs.scenarios import make_scenario
from marl.layers import BatchedLinear, BatchedLSTMCell, per_agent_clip_

N_ACTIONS = len(OVM_ACTIONS)
BLOCK_FLOATS = BLOCK_DIM
FLOAT_BITS = 32
COLLISION_VALUES: tuple[str, ...] = ("absorbing", "published")
ALGORITHM_NAMES: tuple[str, ...] = MARL_ALGORITHMS

State = dict[str, torch.Tensor]
ProgressFn = Callable[[int, int, dict[str, float]], None]


# ---------------------------------------------------------------------------- config
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
def shift_front(x: torch.Tensor, platoon_size: int | None = None) -> torch.Tensor:
    """What each agent gets from its front neighbour: ``out[i] = x[i-1]``, 0 for agent 0.

    ``x (A, ...)`` stacks ``A / platoon_size`` platoons (runs of a population) along the agent
    axis; nothing crosses from one platoon to the next (default: one platoon of ``A``)."""
    out = torch.zeros_like(x)
    size = platoon_size or x.shape[0]
    out.unflatten(0, (-1, size))[:, 1:] = x.unflatten(0, (-1, size))[:, :-1]
    return out


def shift_rear(x: torch.Tensor, platoon_size: int | None = None) -> torch.Tensor:
    """What each agent gets from its rear neighbour: ``out[i] = x[i+1]``, 0 for the last of
    each platoon (see :func:`shift_front`)."""
    out = torch.zeros_like(x)
    size = platoon_size or x.shape[0]
    out.unflatten(0, (-1, size))[:, :-1] = x.unflatten(0, (-1, size))[:, 1:]
    return out


def neighbour_action_onehot(actions: torch.Tensor, platoon_size: int | None = None) -> torch.Tensor:
    """``(A, B)`` actions -> ``(A, B, 8)``: front and rear neighbours' one-hot actions, within
    each platoon of ``platoon_size`` agents (default: one platoon)."""
    onehot = nn.functional.one_hot(actions, N_ACTIONS).to(torch.float32)
    return torch.cat(
        [shift_front(onehot, platoon_size), shift_rear(onehot, platoon_size)], dim=-1)


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
    platoon_size : int
        Agents per platoon: ``n_agents`` for one run; a population's stacked network holds
        ``n_agents / platoon_size`` runs' platoons, which never exchange anything.
    """

    msg_width: int = 0
    differentiable_messages: bool = False
    #: whether the critic shares nothing with the actor (its state is then advanced by the
    #: training update only, see :meth:`act_step` and :meth:`critic_features`)
    separate_critic: bool = False
    actor_head: BatchedLinear
    critic_head: BatchedLinear

    def __init__(self, n_agents: int, hidden: int, with_critic: bool) -> None:
        super().__init__()
        self.n_agents = n_agents
        self.platoon_size = n_agents
        self.hidden = hidden
        self.with_critic = with_critic

    def initial_state(self, batch: int) -> State:
        """Recurrent state at episode start."""
        z = torch.zeros(self.n_agents, batch, self.hidden, device=self.device)
        return {"h": z, "c": z.clone()}

    @property
    def device(self) -> torch.device:
        """Where the network's weights are."""
        return next(self.parameters()).device

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
        critic: bool = True,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], State]:
        """Acting step: ``obs (N, B, 15)`` -> logits ``(N, B, 4)``, features, new state.

        ``critic=False``: a network whose critic is separate (:attr:`separate_critic`) skips it
        and passes the critic's state through unchanged (training's acting: the update
        recomputes the critic)."""
        out, new = self.recur(self.encode(obs), state, front, rear)
        logits = self.logits(out)
        return logits, out, self.after_policy(new, logits)

    def critic_features(self, obs: torch.Tensor, state: State) -> tuple[dict[str, torch.Tensor], State]:
        """One step of a separate critic alone: features ``{"v": ...}`` and its new state."""
        raise NotImplementedError(f"{type(self).__name__} has no separate critic")

    def forward(
        self,
        state: State,
        obs: torch.Tensor,
        actions: torch.Tensor,
        messages: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, State]:
        """Training's recompute of an n-step segment, with gradient.

        ``state`` at its start, observations ``(A, T, B, 15)`` and the actions taken
        ``(A, T, B)``; ``messages``: the (front, rear) messages received ``(A, T, B, W)`` where
        gradients do not flow through them (None: re-derived from the recomputed states, or no
        messages). Returns logits ``(A, T, B, 4)``, values ``(A, T, B)`` and the recurrent
        state after the segment. Non-recurrent layers run once over the whole segment.
        """
        a, t_len, b = actions.shape
        enc = {k: v.reshape(a, t_len, b, -1)
               for k, v in self.encode(obs.reshape(a, t_len * b, OBS_DIM)).items()}
        out, state = self.recur_segment(enc, state, messages)
        flat = {k: v.reshape(a, t_len * b, -1) for k, v in out.items()}
        logits = self.logits(flat).reshape(a, t_len, b, N_ACTIONS)
        nb = neighbour_action_onehot(actions.reshape(a, t_len * b), self.platoon_size)
        return logits, self.value(flat, nb).reshape(a, t_len, b), state

    def recur_segment(
        self,
        enc: dict[str, torch.Tensor],
        state: State,
        messages: tuple[torch.Tensor, torch.Tensor] | None,
    ) -> tuple[dict[str, torch.Tensor], State]:
        """The recurrent part of :meth:`forward` over a segment: encodings ``(A, T, B, F)`` ->
        features ``(A, T, B, H)`` and the state after. Here :meth:`recur` step by step (messages
        re-derived from the states where gradients flow through them); FPrint, WAC, DCEA and BDC,
        whose recurrence is a plain LSTM on precomputed gates, run it as one
        :meth:`marl.layers.BatchedLSTMCell.segment` (IA2C does not: slower, docs/populations.md)."""
        # unbind, not enc[k][:, t]: the backward of T selects would allocate and zero-fill a
        # full-size gradient per step; unbind's backward stacks once
        enc_t = {k: v.unbind(1) for k, v in enc.items()}
        received = None if messages is None else (messages[0].unbind(1), messages[1].unbind(1))
        outs = []
        for t in range(len(next(iter(enc_t.values())))):
            front: torch.Tensor | None
            rear: torch.Tensor | None
            if self.differentiable_messages:
                front, rear = exchange(self, state)
            elif received is not None:
                front, rear = received[0][t], received[1][t]
            else:
                front = rear = None
            out, state = self.recur({k: v[t] for k, v in enc_t.items()}, state, front, rear)
            outs.append(out)
        return {k: torch.stack([o[k] for o in outs], 1) for k in outs[0]}, state

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

    def recur_segment(self, enc, state, messages):
        if self.differentiable_messages or messages is None:
            # IA2C, DIAL, CommNet: step by step (IA2C: measured faster than as a segment)
            return super().recur_segment(enc, state, messages)
        gates = enc["gx"]
        if messages is not None:  # received inputs (FPrint): their gates for all steps at once
            a, t_len, b, _ = gates.shape
            extra = self.message_gates(state, messages[0].reshape(a, t_len * b, -1),
                                       messages[1].reshape(a, t_len * b, -1))
            if extra is not None:
                gates = gates + extra.reshape(a, t_len, b, -1)
        hs, (h, c) = self.lstm.segment(gates, (state["h"], state["c"]))
        new = dict(state)
        new["h"], new["c"] = h, c
        return {"h": hs, "v": hs}, new


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

    separate_critic = True

    def recur_segment(self, enc, state, messages):
        hs, (h, c) = self.lstm.segment(enc["gx"], (state["h"], state["c"]))
        new = {"h": h, "c": c}
        out = {"h": hs}
        if self.with_critic:
            chs, (ch, cc) = self.critic_lstm.segment(enc["cgx"], (state["ch"], state["cc"]))
            new["ch"], new["cc"] = ch, cc
            out["v"] = chs
        return out, new

    def act_step(self, obs, state, front, rear, critic=True):
        if critic or not self.with_critic:
            return super().act_step(obs, state, front, rear)
        h, c = self.lstm.step_from_gates(
            self.lstm.input_gates(torch.relu(self.fc(obs))), (state["h"], state["c"]))
        new = dict(state)
        new["h"], new["c"] = h, c
        out = {"h": h}
        logits = self.logits(out)
        return logits, out, self.after_policy(new, logits)

    def critic_features(self, obs, state):
        gates = self.critic_lstm.input_gates(torch.relu(self.critic_fc(obs)))
        ch, cc = self.critic_lstm.step_from_gates(gates, (state["ch"], state["cc"]))
        return {"v": ch}, {"ch": ch, "cc": cc}

    def shared_critic_parameters(self, whole_critic: bool = False) -> list[nn.Parameter]:
        """What neighbours exchange: the critic LSTM (published) or the whole critic."""
        if whole_critic:
            return self.critic_parameters()
        return list(self.critic_lstm.parameters())


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
    return shift_front(msg, net.platoon_size), shift_rear(msg, net.platoon_size)


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


# ---------------------------------------------------------------------------- algorithms
def _nothing(*_: object) -> None:
    """No hook."""


@dataclass
class Algorithm:
    """An algorithm's distinctive parts as plain functions: its network and what it does around
    the update (each algorithm file builds one as its ``ALGORITHM``).

    Attributes
    ----------
    name : str
        Registered name.
    config_cls : type
        Its config, a frozen subclass of :class:`A2CConfig`.
    build_net : callable(config, n_agents, with_critic=True, generator=None) -> AgentNet
        The batched network of N agents.
    setup : callable(run)
        Once per run after the network exists; the run's own state of the algorithm goes into
        ``run.hook_state``.
    before_step : callable(run, net)
        After backward and per-agent clipping, before the optimiser step (e.g. QSGD), on the
        run's rows ``run.rows`` of ``net``.
    after_step : callable(run, net)
        After the optimiser step (e.g. a consensus round), on the run's rows of ``net``.
    """

    name: str
    config_cls: type[A2CConfig]
    build_net: Callable[..., AgentNet]
    setup: Callable[[Run], None] = _nothing
    before_step: Callable[[Run, AgentNet], None] = _nothing
    after_step: Callable[[Run, AgentNet], None] = _nothing


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


def stack_nets(algo: Algorithm, config: A2CConfig, nets: Sequence[AgentNet]) -> AgentNet:
    """One network of ``K N`` agents holding the K runs' networks' weights (and buffers) in
    order; its ``platoon_size`` is N."""
    n = nets[0].n_agents
    big = algo.build_net(config, n * len(nets), True, torch.Generator().manual_seed(0))
    parts = [dict(net.named_parameters()) | dict(net.named_buffers()) for net in nets]
    with torch.no_grad():
        for name, t in list(big.named_parameters()) + list(big.named_buffers()):
            t.copy_(torch.cat([part[name] for part in parts]))
    big.platoon_size = n
    return big


# ---------------------------------------------------------------------------- returns and losses
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


# ---------------------------------------------------------------------------- runs
@dataclass
class Run:
    """One training run of a :class:`Trainer`: everything of its own.

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
class _Segment:
    """One run's part of an n-step segment: per step its rewards ``(B, N)``, running mask,
    terminal flags, absorbing values ``(B,)``; and the bootstrap values ``(B, N)``."""

    rews: list[np.ndarray] = field(default_factory=list)
    masks: list[np.ndarray] = field(default_factory=list)
    terms: list[np.ndarray] = field(default_factory=list)
    absorbed: list[np.ndarray] = field(default_factory=list)
    bootstrap: torch.Tensor | None = None


@dataclass
class _Batch:
    """A run's batch in progress: the batched env its B episodes run in (rows ``rows``, shared
    with the runs whose batch started at the same step), which of them still run, their
    training reward and length so far, its open segment (started at step ``seg_start`` of the
    loop) and whether it is over."""

    env: PlatoonEnv
    rows: slice
    active: np.ndarray
    ep_reward: np.ndarray
    ep_len: np.ndarray
    seg_start: int = 0
    seg: _Segment = field(default_factory=_Segment)
    steps: int = 0
    t_episode: int = 0
    done: bool = False


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


def training_device(name: str | torch.device) -> torch.device:
    """The torch device a :class:`Trainer` trains on: ``cpu`` (default), ``cuda`` or
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


#: Structural fields every run of a population shares (they shape the stacked tensors and the
#: segment loop); the others may differ from run to run.
POPULATION_SHARED_FIELDS: tuple[str, ...] = ("hidden", "n_step", "episodes_parallel")


# ---------------------------------------------------------------------------- the trainer
class Trainer:
    """On-policy A2C of K runs (a population; K = 1: one run) over batched envs.

    The K runs' agents are stacked as one network of ``K N`` agents (every layer is per agent,
    :mod:`marl.layers`), so each step acts for all runs in one forward and each update is one
    backward; everything that crosses agents (messages, the critic's neighbour actions,
    consensus, reward sharing) stays inside a run's platoon. Runs run free: each step acts
    for all of them, a run whose batch ended starts its next at once, and an update computes on
    the rows of the runs whose segment ended (:meth:`train`). Each run draws
    from its own generator in the order a run alone does, keeps its own environment, statistics
    and optimiser state, and so trains exactly as alone (tested to the last bit).

    Parameters
    ----------
    algo : Algorithm
    config : A2CConfig or sequence of them
        One config for every run, or one per run (equal in :data:`POPULATION_SHARED_FIELDS`).
    scenario_id : str
    n_vehicles : int
    seed : int or sequence of int
        The runs' seeds (one int: one run).
    device : str or torch.device
        Where the network, its gradients and optimiser state live (:func:`training_device`);
        the environments, the random streams and the checkpoints stay on the CPU, so the
        same seed draws the same actions' uniforms on every device.
    """

    def __init__(
        self,
        algo: Algorithm,
        config: A2CConfig | Sequence[A2CConfig],
        scenario_id: str,
        n_vehicles: int,
        seed: int | Sequence[int],
        device: str | torch.device = "cpu",
    ) -> None:
        torch.set_num_threads(1)
        self.device = training_device(device)
        seeds = [int(seed)] if isinstance(seed, int | np.integer) else [int(s) for s in seed]
        configs = (
            [config] * len(seeds) if isinstance(config, A2CConfig) else list(config)
        )
        if not seeds or len(configs) != len(seeds):
            raise ConfigError(
                f"a population needs one config per seed (got {len(configs)} configs for "
                f"{len(seeds)} seeds)")
        self.algo = algo
        self.scenario_id = scenario_id
        self.n_vehicles = n = n_vehicles
        resolved = [c.resolved(scenario_id) for c in configs]
        for f in POPULATION_SHARED_FIELDS:
            values = {getattr(c, f) for c in resolved}
            if len(values) > 1:
                raise ConfigError(
                    f"the runs of one population must share {f} (got {sorted(values)}); "
                    "train them in separate populations")
        self.shape = resolved[0]  # the shared structural fields
        self.runs: list[Run] = []
        nets = []
        for k, (s, cfg) in enumerate(zip(seeds, resolved, strict=True)):
            generator = torch.Generator().manual_seed(s)
            env = self._make_env(cfg.reward_weights())
            assert cfg.power_baseline_kw is not None  # resolved above
            run = Run(k, s, cfg, generator, env, slice(k * n, (k + 1) * n),
                      -cfg.reward_w_power * cfg.power_baseline_kw)
            with torch.device("cpu"):
                nets.append(algo.build_net(cfg, n, True, generator))
            self.runs.append(run)
        # built on the CPU from the CPU generators (the same initial weights on every device)
        with torch.device("cpu"):
            net = nets[0] if len(nets) == 1 else stack_nets(algo, resolved[0], nets)
        self.net = net.to(self.device)
        #: (parameter, is_critic): actor parameters, then the critic's
        self.params = [(p, False) for p in self.net.actor_parameters()] + [
            (p, True) for p in self.net.critic_parameters()]
        self._square_avg = [torch.zeros_like(p) for p, _ in self.params]
        self._views: dict[int, AgentNet] = {}
        for run in self.runs:
            algo.setup(run)

    # -- acting
    @torch.no_grad()
    def _act(self, obs: torch.Tensor, state: State, sampling: Sequence[Run]) -> dict[str, Any]:
        """No-grad acting step of the whole stack: observations ``(K N, B, 15)``, messages
        received, logits, actions, next state. Only the runs in ``sampling`` draw their actions
        (the others' rows are computed and ignored)."""
        net = self.net
        front, rear = exchange(net, state)
        logits, out, new = net.act_step(obs, state, front, rear,
                                        critic=not net.separate_critic)
        shape = (self.n_vehicles,) + tuple(logits.shape[1:])
        drawing = {r.index for r in sampling}
        parts = [r.uniforms(shape) if r.index in drawing else torch.full(shape, 0.5, device="cpu")
                 for r in self.runs]
        u = (parts[0] if len(parts) == 1 else torch.cat(parts)).to(self.device)
        actions = (logits - torch.log(-torch.log(u))).argmax(-1)
        return {"obs": obs, "front": front, "rear": rear, "out": out, "logits": logits,
                "actions": actions, "state": new}

    def _observation(self, obs_np: np.ndarray) -> torch.Tensor:
        """Env observations ``(B, N, 15)`` -> agent-major ``(N, B, 15)``."""
        return torch.from_numpy(obs_np).transpose(0, 1).contiguous().to(self.device)

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

        self.train(taking, once)
        failed = [r.failed for r in taking if r.failed is not None]
        if failed:
            raise TrainingDivergedError("; ".join(failed))
        return [out[r.index] for r in taking]

    def train(self, runs: Sequence[Run], on_batch: Callable[[Run, int, float], bool]) -> None:
        """Train ``runs`` batch after batch until ``on_batch`` says stop for each.

        The runs run free: every step acts for the whole stack at once, and each run steps its
        own env, ends its own segments (an update of exactly its rows) and batches, and starts
        its next batch at once. ``on_batch(run, steps, mean_training_reward)`` is called when a
        run's batch ended (after ``run.steps`` counts it) and returns whether the run goes on.
        A run that diverged stops there (``run.failed`` says why).
        """
        b = self.shape.episodes_parallel
        obs = [torch.zeros(self.n_vehicles, b, OBS_DIM, device=self.device)
               for _ in self.runs]  # idle runs: ignored
        state = self.net.initial_state(b)
        batch = self._start_batches(list(runs), obs, 0)
        live = list(runs)
        cur = self._act(self._stack(obs), state, live)
        #: per step since ``base``: the state acted from and what the act gave
        history: list[tuple[State, dict[str, Any]]] = []
        base = tick = 0
        while live:
            history.append((state, cur))
            next_state = cur["state"]
            # 1. every live run steps its env: some segments (``ending``) and batches (``over``)
            # end at this step
            ending, over = self._step_envs(live, batch, cur["actions"], obs)
            # 2. act on the next observations, with the weights before any update
            going = [r for r in live if r.index not in over]
            nxt = self._act(self._stack(obs), next_state, going) if going else None
            self._bootstrap_shared_critic(ending, over, batch, nxt)
            # 3. one update per segment length of the runs whose segment ended
            critic_after = self._update_ending(ending, batch, history, nxt)
            # 4. their next segments start from the same state, acting with the new weights
            reacting = self._next_segments(ending, over, batch, tick + 1)
            next_state, nxt = self._react(reacting, critic_after, next_state, nxt)
            # 5. runs whose batch ended report it; those that go on start their next batch
            restarting = self._end_batches(live, over, batch, on_batch)
            live = [r for r in live if r.index not in over] + restarting
            if restarting:
                next_state, nxt = self._restart(restarting, batch, obs, next_state, nxt, tick + 1)
            if not live:
                break
            assert nxt is not None
            state, cur = next_state, nxt
            tick += 1
            oldest = min(batch[r.index].seg_start for r in live)
            del history[: oldest - base]  # no open segment needs those steps
            base = oldest

    def _step_envs(
        self, live: list[Run], batch: dict[int, _Batch], actions: torch.Tensor,
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
                bt = self._record(r, batch[r.index], res)
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

    @torch.no_grad()
    def _bootstrap_shared_critic(
        self, ending: list[Run], over: set[int], batch: dict[int, _Batch],
        nxt: dict[str, Any] | None,
    ) -> None:
        """A critic that shares the actor's trunk bootstraps a segment that ended mid-batch from
        the act on the next observation (a separate critic's bootstrap comes from its recompute,
        in the update)."""
        net = self.net
        boot = [] if net.separate_critic else [r for r in ending if r.index not in over]
        if not boot:
            return
        assert nxt is not None
        values = net.value(nxt["out"], neighbour_action_onehot(nxt["actions"], net.platoon_size))
        for r in boot:
            batch[r.index].seg.bootstrap = values[r.rows].T

    def _update_ending(
        self, ending: list[Run], batch: dict[int, _Batch],
        record: list[tuple[State, dict[str, Any]]], nxt: dict[str, Any] | None,
    ) -> dict[int, State]:
        """Update the runs whose segment ended, one update per segment length (``record``: the
        steps kept, a segment of T steps being the last T); returns a separate critic's state
        after the segment per run."""
        by_length: dict[int, list[Run]] = {}
        for r in ending:
            by_length.setdefault(len(batch[r.index].seg.rews), []).append(r)
        critic_after: dict[int, State] = {}
        for t_len, group in sorted(by_length.items()):
            seg = record[-t_len:]
            critic_after |= self._update(group, seg[0][0], [h[1] for h in seg],
                                         [batch[r.index].seg for r in group], nxt)
        return critic_after

    def _next_segments(
        self, ending: list[Run], over: set[int], batch: dict[int, _Batch], tick: int
    ) -> list[Run]:
        """Open the next segment (from step ``tick``) of each run whose segment ended and whose
        batch goes on; a run that failed, or whose running episodes fell below
        ``min_active_fraction``, ends its batch instead (added to ``over``)."""
        reacting = []
        for r in ending:
            bt = batch[r.index]
            # most episodes ended (published collision rule): truncate the rest (their last
            # segment was bootstrapped) instead of stepping finished episodes
            if (r.failed is not None or r.index in over
                    or bt.active.sum() < r.config.min_active_fraction * self.shape.episodes_parallel):
                over.add(r.index)
                continue
            bt.seg, bt.seg_start = _Segment(), tick
            reacting.append(r)
        return reacting

    def _react(
        self, reacting: list[Run], critic_after: dict[int, State], next_state: State,
        nxt: dict[str, Any] | None,
    ) -> tuple[State, dict[str, Any] | None]:
        """Act again for the runs that start a new segment, on the same observation and state,
        with their updated weights (the other runs keep what they drew); a separate critic's
        state at the segment start is its recompute's end."""
        if not reacting:
            return next_state, nxt
        if critic_after:
            next_state = {k: v.clone() for k, v in next_state.items()}
            for r in reacting:
                for k, v in critic_after[r.index].items():
                    next_state[k][r.rows] = v
        assert nxt is not None
        return next_state, _merge_rows(nxt, self._act(nxt["obs"], next_state, reacting), reacting)

    def _end_batches(
        self, live: list[Run], over: set[int], batch: dict[int, _Batch],
        on_batch: Callable[[Run, int, float], bool],
    ) -> list[Run]:
        """Count and report each ended batch (``on_batch``); returns the runs that go on."""
        restarting = []
        for r in live:
            if r.index not in over:
                continue
            bt = batch.pop(r.index)
            if r.failed is not None:
                continue
            r.steps += bt.steps
            r.episodes += self.shape.episodes_parallel
            if on_batch(r, bt.steps, float((bt.ep_reward / np.maximum(bt.ep_len, 1)).mean())):
                restarting.append(r)
        return restarting

    def _restart(
        self, restarting: list[Run], batch: dict[int, _Batch], obs: list[torch.Tensor],
        next_state: State, nxt: dict[str, Any] | None, tick: int,
    ) -> tuple[State, dict[str, Any]]:
        """Start the next batch of each run in ``restarting`` at step ``tick``: new episodes,
        the initial recurrent state on its rows, and its first act."""
        initial = self.net.initial_state(self.shape.episodes_parallel)
        next_state = {k: v.clone() for k, v in next_state.items()}
        batch |= self._start_batches(restarting, obs, tick)
        for r in restarting:
            for k, v in next_state.items():
                v[r.rows] = initial[k][r.rows]
        new = self._act(self._stack(obs), next_state, restarting)
        return next_state, new if nxt is None else _merge_rows(nxt, new, restarting)

    def _make_env(self, weights: RewardWeights) -> PlatoonEnv:
        """A batched training env of the scenario (published collision rule, ``weights``)."""
        return PlatoonEnv(make_scenario(self.scenario_id), self.n_vehicles, training=True,
                          collision_mode="published", weights=weights)

    def _start_batches(self, runs: list[Run], obs: list[torch.Tensor], tick: int
                       ) -> dict[int, _Batch]:
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
                out[r.index] = _Batch(env, rows, np.ones(b, dtype=bool), np.zeros(b),
                                      np.zeros(b), seg_start=tick)
        return out

    def _record(self, r: Run, bt: _Batch, res: StepResult) -> _Batch:
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

    def _stack(self, parts: list[torch.Tensor]) -> torch.Tensor:
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    # -- learning
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

    def _loss(self, run: Run, seg: _Segment, logits: torch.Tensor, values: torch.Tensor,
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
        segs: list[_Segment], nxt: dict[str, Any] | None,
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
        self, group: list[Run], segs: list[_Segment], rows: list[slice], after: State,
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

    # -- one run's view
    def run_net(self, run: Run) -> AgentNet:
        """The run's acting network as its checkpoint stores it: N agents, no critic, weights
        rounded to the checkpoint's precision (validation scores what is saved, and a saved
        snapshot scores in the harness exactly what validation measured)."""
        from marl.checkpoint import WEIGHT_DTYPE

        view = self._views.get(run.index)
        if view is None:
            with torch.device("cpu"):  # validation and checkpoints on the CPU
                view = self.algo.build_net(run.config, self.n_vehicles, False,
                                           torch.Generator().manual_seed(0))
            view.requires_grad_(False)
            self._views[run.index] = view
        whole = dict(self.net.named_parameters())
        with torch.no_grad():
            for name, p in view.named_parameters():
                p.copy_(whole[name][run.rows].to(WEIGHT_DTYPE))
        return view


def _rmsprop_(
    param: torch.Tensor, grad: torch.Tensor, square_avg: torch.Tensor, lr: float, alpha: float,
    eps: float,
) -> None:
    """One RMSprop step in place, in the operation order of ``torch.optim.RMSprop``."""
    square_avg.mul_(alpha).addcmul_(grad, grad, value=1 - alpha)
    avg = square_avg.sqrt().add_(eps)
    param.addcdiv_(grad, avg, value=-lr)


# ---------------------------------------------------------------------------- the driver
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
    #: The kept snapshot's checkpoint contents, held in memory until the run finishes.
    kept: dict[str, Any] | None = field(default=None, repr=False)


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
    device: str | torch.device = "cpu",
) -> TrainResult:
    """Train ``algo`` for ``total_steps`` environment steps; write checkpoints and curve CSV.

    Every ``config.eval_every_steps`` (and at the end) the policy is evaluated on the validation
    seeds in both modes by ``evaluate``; the snapshot kept as ``<stem>.pt`` is the best in
    ``config.selection_mode`` (fewest collisions, then mean reward; a tie goes to the later
    snapshot). The final weights are saved as ``<stem>.final.pt``. One run of
    :func:`run_population`.

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
    device : str or torch.device
        Where to train (:func:`training_device`); validation and checkpoints stay on the CPU.
    """
    return run_population(algo, [config], scenario_id, n_vehicles, total_steps, [seed], out_dir,
                          progress, [log], schedule_steps, evaluate, device)[0]


def run_population(
    algo: Algorithm,
    configs: Sequence[A2CConfig],
    scenario_id: str,
    n_vehicles: int = 8,
    total_steps: int = 600_000,
    seeds: Sequence[int] = (0,),
    out_dir: str | Path | None = None,
    progress: ProgressFn | None = None,
    logs: Sequence[Callable[[str], None] | None] | None = None,
    schedule_steps: int | None = None,
    evaluate: Evaluator | None = None,
    device: str | torch.device = "cpu",
) -> list[TrainResult]:
    """Train K runs of ``algo`` at once (one :class:`Trainer`): run ``k`` with ``configs[k]`` and
    ``seeds[k]``, each evaluated, selected and saved exactly as :func:`run_training` alone.

    A run stops at its own budget; one whose weights become non-finite stops there while the
    others go on, and the error is raised after they finished (their checkpoints are written).
    ``logs[k]`` receives run k's lines; ``progress`` is called per run and batch. Wall time and
    throughput of each result are the population's (its steps over the population's time).
    """
    make_scenario(scenario_id)  # fail early on an unknown id
    if out_dir is not None and evaluate is None:
        raise ConfigError(
            "run_training with an output folder needs a validation evaluator: pass "
            "evaluate=benchmark.policy_eval.validation_evaluator(algo, scenario, N)"
        )
    if len({int(s) for s in seeds}) != len(seeds):
        raise ConfigError(f"the runs of a population need distinct seeds, got {list(seeds)}")
    trainer = Trainer(algo, list(configs), scenario_id, n_vehicles, list(seeds), device)
    runs = trainer.runs
    log_of = list(logs) if logs is not None else [None] * len(runs)
    for r in runs:
        r.total_steps = schedule_steps or total_steps
    curves: list[list[dict[str, float]]] = [[] for _ in runs]
    next_eval = [r.config.eval_every_steps if out_dir is not None else math.inf for r in runs]
    best = [(-math.inf, -math.inf) for _ in runs]
    results = [TrainResult(algo.name, scenario_id, n_vehicles, r.seed, 0, 0, 0.0, 0.0, {},
                           curves[r.index]) for r in runs]
    t0 = time.perf_counter()
    evaluating = 0.0  # seconds spent in validation, not training

    def on_batch(r: Run, steps: int, train_reward: float) -> bool:
        nonlocal evaluating
        k, cfg, log = r.index, r.config, log_of[r.index]
        row: dict[str, float] = {
            "episode": r.episodes,
            "steps": r.steps,
            "train_reward": train_reward,
            **{f"eval_{key}_{m}": math.nan for m in EVAL_MODES for key in CURVE_EVAL_KEYS},
        }
        curves[k].append(row)
        last = r.steps >= total_steps
        if r.steps >= next_eval[k] or (out_dir is not None and last):
            assert evaluate is not None
            te = time.perf_counter()
            net = trainer.run_net(r)
            for mode in EVAL_MODES:
                ev = evaluate(net, mode)
                for key in CURVE_EVAL_KEYS:
                    row[f"eval_{key}_{mode}"] = float(ev[key])
            next_eval[k] = r.steps + cfg.eval_every_steps
            # fewest collisions first: a colliding episode ends early, so its mean reward
            # over the steps it ran can look better than a safe one's; a tie keeps the
            # later snapshot
            select = cfg.selection_mode
            score = (-row[f"eval_collisions_{select}"], row[f"eval_reward_{select}"])
            better = score >= best[k]
            best[k] = max(best[k], score)
            now = time.perf_counter()
            _finish(results[k], trainer, r, net, now - t0, now - t0 - evaluating - (now - te),
                    out_dir, better)
            evaluating += time.perf_counter() - te
            if log is not None:
                log(
                    f"steps {r.steps} episodes {r.episodes} train {train_reward:.2f} "
                    + " ".join(
                        f"{m} {row[f'eval_reward_{m}']:.2f} "
                        f"({row[f'eval_collisions_{m}']:.0f} collisions)" for m in EVAL_MODES
                    )
                    + (" [kept]" if better else "")
                    + f" consensus bits/agent {r.bits['consensus']:.0f}"
                )
        if progress is not None:
            progress(r.steps, total_steps, row)
        return not last

    trainer.train(runs, on_batch)
    train_time = time.perf_counter() - t0 - evaluating
    wall = time.perf_counter() - t0
    for r in runs:
        if r.failed is not None:
            continue
        res = results[r.index]
        _finish(res, trainer, r, trainer.run_net(r), wall, train_time, out_dir, False, final=True)
        log = log_of[r.index]
        if log is not None:
            log(
                f"done: {r.steps} steps in {res.wall_s:.0f} s "
                f"({res.env_steps_per_s:.0f} env steps/s training"
                + (f", population of {len(runs)}" if len(runs) > 1 else "")
                + f"), execution "
                f"{res.bits['execution_bits_per_vehicle_per_s']:.0f} bit/vehicle/s, training "
                f"bits sent per agent: {res.bits['training_step_bits_per_agent_step']:.0f} per "
                f"step (blocks, messages, action for the critics, message gradients) and "
                f"consensus {res.bits['training_consensus_bits_per_agent']:.0f} in all "
                f"(QSGD applied locally: {res.bits['local_qsgd_payload_bits_per_agent']:.0f} "
                f"bits of payload, not sent); checkpoint {res.checkpoint}"
            )
    failed = [r.failed for r in runs if r.failed is not None]
    if failed:
        raise TrainingDivergedError("; ".join(failed))
    return results


#: Validation numbers recorded per mode in the curve (``eval_<key>_<mode>``).
CURVE_EVAL_KEYS: tuple[str, ...] = ("reward", "collisions")


def _finish(
    result: TrainResult,
    trainer: Trainer,
    run: Run,
    net: AgentNet,
    wall_s: float,
    train_s: float,
    out_dir: str | Path | None,
    save_weights: bool,
    final: bool = False,
) -> None:
    """Fill the run's result numbers; with an output folder, keep the snapshot in memory when
    ``save_weights`` (a new best on the validation seeds) and, when ``final``, write the run's
    files: the curve, the final weights (``net``: the run's acting network) and the kept
    snapshot with the run's totals.

    Nothing is written before the run finishes, and the three files are written to temporary
    files and renamed together (:class:`envs.atomic.StagedFiles`), so an interrupted or failed
    run leaves the files of an earlier run byte for byte as they were.
    """
    from envs.atomic import StagedFiles
    from marl.checkpoint import checkpoint_payload, write_payload

    exec_bits = execution_bits_per_agent_step(net)
    result.steps, result.episodes = run.steps, run.episodes
    result.wall_s = wall_s
    result.env_steps_per_s = run.steps / max(train_s, 1e-9)
    result.bits = {
        "execution_bits_per_agent_step": float(exec_bits),
        "execution_bits_per_vehicle_per_s": exec_bits / run.env.params.dt_s,
        "training_step_bits_per_agent_step": float(training_step_bits_per_agent(net)),
        "training_consensus_bits_per_agent": run.bits["consensus"],
        "local_qsgd_payload_bits_per_agent": run.bits["qsgd_local"],
        "updates": float(run.updates),
    }
    if out_dir is None:
        return
    out = Path(out_dir)
    stem = checkpoint_stem(trainer.algo.name, trainer.scenario_id, trainer.n_vehicles, run.seed)
    curve = result.curve
    result.curve_csv = out / f"{stem}.curve.csv"
    mode = run.config.selection_mode
    evals = [r for r in curve if not math.isnan(r[f"eval_reward_{mode}"])]
    summary = {
        "final_train_reward": curve[-1]["train_reward"] if curve else math.nan,
        "final_eval_reward": evals[-1][f"eval_reward_{mode}"] if evals else math.nan,
        "best_eval_reward": max(r[f"eval_reward_{mode}"] for r in evals) if evals else math.nan,
        "wall_s": wall_s,
        "env_steps_per_s": result.env_steps_per_s,
        "selected_at_steps": float(run.steps),
        **{f"selected_eval_{k}_{m}": (evals[-1][f"eval_{k}_{m}"] if evals else math.nan)
           for m in EVAL_MODES for k in CURVE_EVAL_KEYS},
        **result.bits,
    }
    result.checkpoint = out / f"{stem}.pt"

    def payload() -> dict[str, Any]:
        return checkpoint_payload(
            algo=trainer.algo.name,
            config=dataclasses.asdict(run.config),
            scenario=trainer.scenario_id,
            n_vehicles=trainer.n_vehicles,
            seed=run.seed,
            steps=run.steps,
            curve_summary={**summary, "total_steps": float(run.steps)},
            weights=net.acting_state_dict(),
        )

    if save_weights:
        result.kept = payload()
    if not final:
        return
    final_data = payload()
    kept = result.kept if result.kept is not None else final_data
    # the kept weights with the run's totals (its own selected_* numbers stay)
    totals = dict(kept["curve_summary"])
    selected = {k: v for k, v in totals.items() if k.startswith("selected_")}
    totals.update(final_data["curve_summary"])
    totals.update(selected)
    totals["total_steps"] = float(run.steps)
    kept = {**kept, "curve_summary": totals}
    result.final_checkpoint = out / f"{stem}.final.pt"
    out.mkdir(parents=True, exist_ok=True)
    with StagedFiles() as staged:
        staged.write_with(result.curve_csv, lambda tmp: _write_curve_file(tmp, curve))
        staged.write_with(result.final_checkpoint,
                          lambda tmp: write_payload(tmp, final_data, atomic=False))
        staged.write_with(result.checkpoint, lambda tmp: write_payload(tmp, kept, atomic=False))
        staged.commit()


def write_curve(path: Path, curve: list[dict[str, float]]) -> None:
    """Learning curve CSV: episode, steps, train_reward (the learner's own, possibly shaped,
    reward), and per evaluation mode the validation reward and collisions (empty where not
    evaluated). Written atomically."""
    from envs.atomic import write_with

    write_with(path, lambda tmp: _write_curve_file(tmp, curve))


def _write_curve_file(path: Path, curve: list[dict[str, float]]) -> None:
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
