"""Acting, validation and loading of the shared learners' actors (:mod:`marl.ppo`): what the
trainer, the validation and the controller share, without the trainer."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch

from envs.accel_mode import position_features
from envs.channel import ChannelConfig
from envs.params import VALIDATION_SEEDS, PlatoonParams, check_decision_seeds
from envs.platoon import PlatoonEnv, PlatoonState
from envs.scenarios import Scenario
from envs.streams import episode_uniforms
from infra.errors import ConfigError, TrainingDivergedError
from marl.ppo_nets import PPOConfig, SharedActor

#: Uniform stream of sampled evaluation actions (per episode, step and agent).
ACTION_STREAM = "shared-policy-actions"


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

        exact = {}
        if actor.prior == "cacc-exact":  # the unclipped dv and the last command of the state
            if state is None:
                raise ValueError("the cacc-exact prior reads the platoon's state")
            exact = {"relative_speed_mps": state.pred_speed_mps - state.speed_mps,
                     "last_command_mps2": state.command_mps2}
        base = cacc_from_observation(obs, targets[0], targets[1], params, **exact)
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


# ---------------------------------------------------------------------------- checkpoint
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
