"""Acting with a learned policy: load or build its acting network, pick its actions (greedy, or
drawn from the episodes' own uniforms) and turn them into commands.

What :class:`controllers.policy.PolicyController` (the one controller of every learner) and the
trainers' rollouts share, and nothing of a learner: this module imports configs and networks
(:mod:`marl.config`, :mod:`marl.networks`, :mod:`marl.ppo_nets`), never a trainer. One acting
class per kind of network, :data:`ACTING` by the learner's family: :class:`PaperActing` (the
paper's per-agent recurrent networks) and :class:`SharedActing` (the shared learners' actor;
one per follower for ``ippo-bdc``). The controller keeps the closed loop's part (options,
checkpoint files, action uniforms, opening the channels).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
import torch

from envs import accel_mode
from envs.dynamics import OBS_DIM, action_to_command_mps2, agent_observations, vehicle_blocks
from envs.params import PlatoonParams
from envs.platoon import PlatoonState
from envs.vehicle_classes import class_features
from infra.errors import ConfigError
from marl.config import algorithm, config_from_dict
from marl.learners import LEARNERS, load
from marl.networks import AgentNet, State, exchange
from marl.ppo_nets import PPOConfig, SharedActor

#: A message a policy sends every step: name, floats, links (as :class:`controllers.base.Message`).
MessageSpec = tuple[str, int, str | tuple[tuple[int, int], ...]]
#: Agents and episodes' rows of the batch-invariance probe's random inputs (:meth:`Acting.probe`).
PROBE_AGENTS, PROBE_ROWS = 8, 64


def pad_rows(x: np.ndarray, lanes: int) -> np.ndarray:
    """``x (B, ...)`` with row 0 repeated up to ``lanes`` rows (as it is when ``B >= lanes``)."""
    return x if len(x) >= lanes else np.concatenate([x, np.repeat(x[:1], lanes - len(x), 0)])


def load_weights(data: dict[str, Any], build: Callable[[dict[str, Any]], Any]) -> Any:
    """The network ``build(config)`` makes from a loaded checkpoint dict's config, holding its
    weights (as float32), in evaluation mode; a config or weights that do not make it give a
    :class:`ConfigError`."""
    try:
        net = build(data["config"])
        net.load_state_dict({k: v.float() for k, v in data["weights"].items()}, strict=True)
    except (TypeError, ValueError, RuntimeError, KeyError) as exc:
        reason = " ".join(str(exc).split())[:200]
        raise ConfigError(f"a {data.get('algo')} checkpoint whose config or weights do not fit "
                          f"this learner ({reason}); train it again") from None
    net.eval()
    return net


class Acting:
    """A loaded policy acting in the closed loop, one subclass per kind of network.

    The controller calls :meth:`messages`, then :meth:`reset` once per batch of episodes and
    :meth:`act` every step; ``lanes`` (at least the batch size) is how many episodes' rows the
    network gets (see :func:`controllers.policy.rows_are_batch_invariant`).
    """

    #: Name of the per-episode uniform stream sampled actions are drawn from.
    stream: ClassVar[str]

    def __init__(self, algo: str, net: Any) -> None:
        self.algo, self.net = algo, net

    @classmethod
    def load(cls, algo: str, data: dict[str, Any]) -> Acting:
        """The policy of a checkpoint dict (what :func:`marl.checkpoint.load_checkpoint`
        returns)."""
        raise NotImplementedError

    @staticmethod
    def probe(algo: str, rows: list[int]) -> list[torch.Tensor]:
        """The network's outputs, rows first, for the rows ``rows`` of :data:`PROBE_ROWS`
        episodes' random inputs, with random weights (the same on every call)."""
        raise NotImplementedError

    def check_vehicles(self, n_vehicles: int) -> None:
        """Refuse a platoon size the network does not act at."""

    def messages(self, n_vehicles: int) -> list[MessageSpec]:
        """What every follower sends each step."""
        raise NotImplementedError

    def reset(self, ctx: Any, lanes: int) -> None:
        """Start a batch of episodes (``ctx``: the :class:`controllers.base.EpisodeContext`,
        its channels open)."""
        raise NotImplementedError

    def act(self, state: PlatoonState, observation: np.ndarray | None,
            uniforms: np.ndarray | None) -> np.ndarray:
        """This step's ``(B, N)`` commands; ``uniforms (lanes, N)``: None for the greedy
        action."""
        raise NotImplementedError


# ---------------------------------------------------------------------------- the paper's
def untrained_net(algo: str, n_vehicles: int, seed: int) -> AgentNet:
    """``algo``'s acting network (no critic) of ``n_vehicles`` agents with freshly initialised
    weights from ``seed`` and the default config (the "untrained policy" reference)."""
    spec = algorithm(algo)
    gen = torch.Generator().manual_seed(seed)
    return spec.build_net(spec.config_cls(), n_vehicles, with_critic=False, generator=gen)


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


def exchange_with_neighbours(channel: Any, payload: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Send every follower's ``(B, N, W)`` to both neighbours over ``channel`` (links
    ``"neighbours"``); what arrived from the front and from the rear, ``(B, N, W)`` each (0
    where nothing can: follower 1's front, follower N's rear)."""
    b, n, w = payload.shape
    sent = np.zeros((b, n + 1, w))
    sent[:, 1:] = payload
    held = channel.transmit(sent)
    front, rear = np.zeros((b, n, w)), np.zeros((b, n, w))
    front[:, 1:] = held[:, : n - 1]  # (i-1 -> i) for i = 2..N
    rear[:, :-1] = held[:, n - 1:]  # (i+1 -> i) for i = 1..N-1
    return front, rear


class PaperActing(Acting):
    """The paper's per-agent recurrent policies: each follower sends its 5-float vehicle block
    to both neighbours (the observation's neighbour blocks are rebuilt from what arrived) and,
    for FPrint, DIAL and CommNet, the learned message (4 or 64 floats); the action is one of
    the published OVM gain pairs."""

    stream = "policy-actions"
    net: AgentNet

    @classmethod
    def load(cls, algo: str, data: dict[str, Any]) -> Acting:
        spec = algorithm(algo)
        return cls(algo, load_weights(data, lambda saved: spec.build_net(
            config_from_dict(spec, saved), int(data["n_vehicles"]), with_critic=False)))

    @staticmethod
    @torch.no_grad()
    def probe(algo: str, rows: list[int]) -> list[torch.Tensor]:
        net = untrained_net(algo, PROBE_AGENTS, 0)
        gen = torch.Generator().manual_seed(1)
        obs = torch.randn(PROBE_AGENTS, PROBE_ROWS, OBS_DIM, generator=gen)[:, rows].contiguous()
        state = {k: torch.randn(v.shape, generator=gen)[:, rows].contiguous()
                 for k, v in net.initial_state(PROBE_ROWS).items()}
        logits, _, new = net.act_step(obs, state, *exchange(net, state))
        return [logits.transpose(0, 1), *(v.transpose(0, 1) for v in new.values())]

    def messages(self, n_vehicles: int) -> list[MessageSpec]:
        blocks: MessageSpec = (f"{self.algo}-blocks", 5, "neighbours")
        width = self.net.msg_width
        return [blocks, (f"{self.algo}-messages", width, "neighbours")] if width else [blocks]

    def reset(self, ctx: Any, lanes: int) -> None:
        self.lanes, self.params = lanes, ctx.params
        self.state = self.net.initial_state(lanes)
        self.block_channel = ctx.channel(f"{self.algo}-blocks")
        self.msg_channel = ctx.channel(f"{self.algo}-messages") if self.net.msg_width else None

    def act(self, state: PlatoonState, observation: np.ndarray | None,
            uniforms: np.ndarray | None) -> np.ndarray:
        if observation is None:
            raise ConfigError(f"{self.algo} needs the agent observations (needs_observation)")
        b = len(observation)
        own = observation[:, :, :5]
        obs = np.concatenate([own, *exchange_with_neighbours(self.block_channel, own)], axis=-1)
        messages: tuple[torch.Tensor | None, torch.Tensor | None] = (None, None)
        message = self.net.message(self.state)  # (N, lanes, W); None without a message
        if self.msg_channel is not None and message is not None:
            sent = message[:, :b].detach().numpy().transpose(1, 0, 2)
            messages = tuple(  # type: ignore[assignment]
                torch.from_numpy(pad_rows(x, self.lanes).transpose(1, 0, 2).astype(np.float32))
                .contiguous() for x in exchange_with_neighbours(self.msg_channel, sent))
        actions, self.state = policy_actions(
            self.net, pad_rows(obs.astype(np.float32), self.lanes), self.state, messages,
            uniforms)
        return action_to_command_mps2(
            actions[:b], state.gap_m, state.speed_mps, state.pred_speed_mps, self.params)


# ---------------------------------------------------------------------------- the shared
def agent_inputs(obs: np.ndarray | None, action_mode: str,
                 features: np.ndarray | None = None) -> np.ndarray:
    """What the networks read from the env's observation ``(B, N, D)``: the ``accel`` one as it
    is, the ``ovm-gain`` one with the position features appended (float32); then, for a policy
    trained with ``class_features``, each follower's ``features (N, F)``
    (:func:`envs.vehicle_classes.class_features`)."""
    if obs is None:
        raise ValueError("the env does not observe (observe=False)")
    b, n, _ = obs.shape
    if action_mode == "accel":
        out = np.ascontiguousarray(obs, dtype=np.float32)
    else:
        pos = np.broadcast_to(accel_mode.position_features(n)[None].astype(np.float32), (b, n, 3))
        out = np.concatenate([obs.astype(np.float32), pos], axis=-1)
    if features is None:
        return out
    extra = np.broadcast_to(features[None].astype(np.float32), (b, n, features.shape[-1]))
    return np.concatenate([out, extra], axis=-1)


def to_command(actor: SharedActor, action: torch.Tensor, state: PlatoonState | None,
               params: PlatoonParams, obs: np.ndarray | None = None,
               targets: tuple[float, float] | None = None) -> np.ndarray:
    """The ``(B, N)`` acceleration commands of the actions in ``state``: ``c + h tanh(z)``, the
    residual ``clip(prior(obs) + h tanh(z))`` of an actor with a prior (``obs``: the raw
    ``accel`` observation, ``targets``: the scenario's target gap and speed), or the published
    OVM command of the gain indices (the trainer and the controller both act through this)."""
    if actor.continuous:
        if not actor.prior:
            return actor.command(action).numpy().astype(np.float64)
        if obs is None or targets is None:
            raise ValueError("an actor with a prior acts on the observation and the targets")
        exact = {}
        if actor.prior == "cacc-exact":  # the unclipped dv and the last command of the state
            if state is None:
                raise ValueError("the cacc-exact prior reads the platoon's state")
            exact = {"relative_speed_mps": state.pred_speed_mps - state.speed_mps,
                     "last_command_mps2": state.command_mps2}
        base = accel_mode.cacc_from_observation(obs, targets[0], targets[1], params, **exact)
        residual = (actor.half_range * torch.tanh(action)).numpy().astype(np.float64)
        return np.clip(base + residual, params.accel_min_mps2, params.accel_max_mps2)
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


def load_actor(data: dict[str, Any], params: PlatoonParams = PlatoonParams()) -> SharedActor:
    """The actor of a loaded checkpoint dict (:func:`load_weights`)."""
    acting = ("algo", "action_mode", "hidden", "obs_clip", "prior",  # what its shape and acting
              "class_features")                                       # read

    def build(saved: dict[str, Any]) -> SharedActor:
        config = PPOConfig(**{k: v for k, v in saved.items() if k in acting})
        return SharedActor(config, params, int(data["n_vehicles"]) if config.per_agent else 0)

    return load_weights(data, build)


class SharedActing(Acting):
    """A shared learner's actor (``ippo``, ``mappo``, ``distill``; ``ippo-bdc``: one network per
    follower), at any N: every follower runs it on its own observation, whose position features
    (first, last, ``i / N``) tell it where it is. ``accel`` actions: the command is the actor's
    acceleration, its V2V the predecessor's command and the leader's planned acceleration and
    speed with ``cacc``'s timing (:mod:`envs.accel_mode`); ``ovm-gain``: the gain index becomes
    the published OVM command, its V2V each follower's vehicle block to both neighbours."""

    stream = "shared-policy-actions"
    net: SharedActor

    @classmethod
    def load(cls, algo: str, data: dict[str, Any]) -> Acting:
        return cls(algo, load_actor(data))

    @staticmethod
    @torch.no_grad()
    def probe(algo: str, rows: list[int]) -> list[torch.Tensor]:
        cfg = PPOConfig(algo="ippo-bdc" if LEARNERS[algo].per_agent else "ippo")
        with torch.random.fork_rng(devices=[]):  # random weights, the caller's generator intact
            torch.manual_seed(0)
            actor = SharedActor(cfg, n_agents=PROBE_AGENTS if cfg.per_agent else 0)
            for p in actor.body.parameters():
                p.add_(0.1 * torch.randn(p.shape))
        obs = torch.randn(PROBE_ROWS, PROBE_AGENTS, cfg.obs_dim, dtype=torch.float64,
                          generator=torch.Generator().manual_seed(1))
        return [actor(obs[rows].contiguous())]

    def check_vehicles(self, n_vehicles: int) -> None:
        if self.net.n_agents and n_vehicles != self.net.n_agents:
            raise ConfigError(
                f"{self.algo} has one network per follower, trained for N = "
                f"{self.net.n_agents}; run it with --vehicles {self.net.n_agents} (the "
                "shared policies ippo, mappo and distill act at any N)")

    def messages(self, n_vehicles: int) -> list[MessageSpec]:
        if not self.net.continuous:
            return [(f"{self.algo}-blocks", 5, "neighbours")]
        (name, width), (lname, lwidth) = accel_mode.PRED_MESSAGE, accel_mode.LEADER_MESSAGE
        return [(name, width, "predecessor"),
                (lname, lwidth, tuple(accel_mode.leader_links(n_vehicles)))]

    def reset(self, ctx: Any, lanes: int) -> None:
        self.lanes, self.params = lanes, ctx.params
        self.targets = (ctx.target_gap_m, ctx.target_speed_mps)
        b, n = ctx.batch_size, ctx.n_vehicles
        # a policy trained with class features reads each follower's own (the published
        # platoon's on the homogeneous string); one trained without runs without them
        self.features = (class_features(ctx.scenario.vehicle_arrays(n, ctx.params), n, ctx.params)
                         if self.net.class_features else None)
        if self.net.continuous:
            self.pred_channel = ctx.channel(accel_mode.PRED_MESSAGE[0])
            self.leader_channel = ctx.channel(accel_mode.LEADER_MESSAGE[0])
            self.pred_held, self.leader_held = np.zeros((b, n)), np.zeros((b, n, 2))
        else:
            self.block_channel = ctx.channel(f"{self.algo}-blocks")

    def _observation(self, state: PlatoonState) -> np.ndarray:
        p, (gap, speed) = self.params, self.targets
        if self.net.continuous:
            return accel_mode.accel_observations(
                state.gap_m, state.speed_mps, state.pred_speed_mps, state.applied_accel_mps2,
                state.realised_accel_mps2, self.pred_held, self.leader_held, gap, speed, p)
        own = vehicle_blocks(state.gap_m, state.speed_mps, state.pred_speed_mps,
                             state.applied_accel_mps2, gap, speed, p).astype(np.float32)
        obs = agent_observations(own)
        obs[:, :, 5:10], obs[:, :, 10:15] = exchange_with_neighbours(self.block_channel, own)
        return agent_inputs(obs, "ovm-gain")

    def act(self, state: PlatoonState, observation: np.ndarray | None,
            uniforms: np.ndarray | None) -> np.ndarray:
        obs = self._observation(state)
        b = len(obs)
        x = obs if self.features is None else np.concatenate(
            [obs, np.broadcast_to(self.features[None], (b, *self.features.shape))], axis=-1)
        with torch.no_grad():
            out = self.net(torch.from_numpy(np.ascontiguousarray(pad_rows(x, self.lanes))))
            action = sample_with_uniforms(self.net, out, uniforms)[:b]
            command = self.commands(action, state, obs)
        if self.net.continuous:
            self.pred_held, self.leader_held = (x.copy() for x in accel_mode.transmit_accel_messages(
                self.pred_channel, self.leader_channel, command, state.leader_accel_now_mps2,
                state.leader_speed_now_mps, self.targets[1], self.params))
        return command

    def commands(self, action: torch.Tensor, state: PlatoonState, obs: np.ndarray) -> np.ndarray:
        """The ``(B, N)`` commands of the actor's ``action`` (:func:`to_command`)."""
        return to_command(self.net, action, state, self.params, obs, self.targets)


def acting(algo: str) -> type[Acting]:
    """The acting class of the learner ``algo`` (its entry in :data:`marl.learners.LEARNERS`)."""
    return load(LEARNERS[algo].acting)  # type: ignore[no-any-return]
