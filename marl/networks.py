"""The agents' networks: N agents' actor-critics batched as one module, message exchange and
the bits each agent sends.

:class:`AgentNet` splits a step so that training can batch the non-recurrent layers over a
segment; :class:`SharedTrunkNet` is the published IA2C trunk (FPrint, DIAL and CommNet add their
messages to it) and :class:`SeparateActorCriticNet` the consensus learners' separate actor and
critic (WAC, DCEA, BDC). Activations are agent-major ``(N, B, F)``; every layer is per agent
(:mod:`marl.layers`), so a population's runs stack along the agent axis and exchange nothing.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from envs.dynamics import BLOCK_DIM, OBS_DIM
from envs.params import OVM_ACTIONS
from marl.layers import BatchedLinear, BatchedLSTMCell

N_ACTIONS = len(OVM_ACTIONS)
FLOAT_BITS = 32

State = dict[str, torch.Tensor]


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
        return {"h": h, "v": h}, {**state, "h": h, "c": c}

    def recur_segment(self, enc, state, messages):
        if self.differentiable_messages or messages is None:
            # IA2C, DIAL, CommNet: step by step (IA2C: measured faster than as a segment)
            return super().recur_segment(enc, state, messages)
        gates = enc["gx"]  # received inputs (FPrint): their gates for all steps at once
        a, t_len, b, _ = gates.shape
        extra = self.message_gates(state, messages[0].reshape(a, t_len * b, -1),
                                   messages[1].reshape(a, t_len * b, -1))
        if extra is not None:
            gates = gates + extra.reshape(a, t_len, b, -1)
        hs, (h, c) = self.lstm.segment(gates, (state["h"], state["c"]))
        return {"h": hs, "v": hs}, {**state, "h": h, "c": c}


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
            state |= {k: torch.zeros_like(state["h"]) for k in ("ch", "cc")}
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
        new = {**state, "h": h, "c": c}
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
    return (BLOCK_DIM + net.msg_width) * FLOAT_BITS


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
