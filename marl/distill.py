"""``distill``: the shared actor of :mod:`marl.ppo` trained by imitation of a model-based expert.

Behaviour cloning, then DAgger (Ross, Gordon and Bagnell, AISTATS 2011), on training episodes
only (seeds ``1e7 (seed + 1) + k``; the validation seeds choose the round that is kept, the
evaluation seeds are never seen):

1. round 0 drives the platoon with the expert and records its commands (behaviour cloning);
2. every later round ``k`` drives it with the current policy's mode, except the first
   ``beta^k`` share of its episodes, which the expert still drives (DAgger's mixture, ``beta``
   = 0.5), while the expert, fed the same states through its own V2V channels, labels what it
   would command; the labels are added to the data set and the actor is fitted again on all
   of it. The observation statistics are those of round 0 throughout (a fit that shifted them
   as crashed episodes entered the data set once turned a good round into 31 collisions of 32).

The fit is the mean of the policy's Gaussian in command space, ``c + h tanh(mean)`` against the
expert's command (squared error), and its standard deviation in ``z`` is the residuals' RMS in
command space over the squash's slope at zero, ``h`` (so "actions as trained" are the fitted
Gaussian; the maximum-likelihood value in ``z`` is dominated by the few labels at the bounds,
where ``atanh`` diverges). It is the reference of what this network can represent, and of how
fast a learned controller is beside the solver it copies. The expert comes from the layer above
(:func:`commands.train.model_expert` builds ``mpc``): here it is any ``make_expert(env) ->
act(state) -> (B, N) commands``.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv, PlatoonState
from envs.scenarios import Scenario, as_scenario, check_vehicles
from infra.errors import ConfigError
from infra.limits import training_episode_seeds
from marl.acting import agent_inputs
from marl.layers import module_tensors
from marl.ppo import Evaluator, PPOResult, beats, validation
from marl.ppo_nets import (
    PPOConfig,
    SharedActor,
    as_shipped,
    check_counts,
    check_finite_weights,
    check_learning_rate,
)

if TYPE_CHECKING:
    from marl.checkpoint import Snapshots

#: ``make_expert(env)`` after ``env.reset(seeds)``: the expert's ``act(state) -> (B, N)``.
ExpertFactory = Callable[[PlatoonEnv], Callable[[PlatoonState], np.ndarray]]


@dataclass(frozen=True)
class DistillConfig:
    """Hyper-parameters of the imitation.

    Attributes
    ----------
    expert : str
        Name of the expert controller (recorded; the factory is given to :func:`distill`).
    rounds : int
        Data-collection rounds: the first by the expert (behaviour cloning), the rest DAgger.
    beta : float
        DAgger's mixture: in round ``k`` the expert drives the first ``beta^k`` share of the
        episodes (0: the policy drives every episode after round 0).
    episodes_per_round : int
        Training episodes collected per round.
    grad_steps, minibatch_rows, lr : int, int, float
        Adam steps on the whole data set after each round (the actor and its optimiser carry
        over from round to round), rows per step, learning rate.
    hidden : int
        Width of the actor (as :class:`marl.ppo.PPOConfig`, which checks it: the actor's
        config is built once, with this config, :meth:`actor_config`).
    """

    expert: str = "mpc"
    rounds: int = 5
    beta: float = 0.5
    episodes_per_round: int = 8
    grad_steps: int = 3000
    minibatch_rows: int = 1024
    lr: float = 1e-3
    hidden: int = 64

    def __post_init__(self) -> None:
        from infra.limits import MAX_EPISODES_PARALLEL

        self.actor_config()  # built, and its hidden size checked, once: here
        check_counts(self, rounds=10**6, episodes_per_round=MAX_EPISODES_PARALLEL,
                     grad_steps=10**6, minibatch_rows=10**6)
        if not 0 <= self.beta <= 1:
            raise ConfigError(f"beta must lie in [0, 1], got {self.beta}")
        check_learning_rate(self.lr)

    def actor_config(self) -> PPOConfig:
        """The actor's network settings (accel mode) as the shared learners write them."""
        return self._actor

    @functools.cached_property
    def _actor(self) -> PPOConfig:
        return PPOConfig(hidden=self.hidden)


def distill(
    scenario: str | Scenario,
    make_expert: ExpertFactory,
    n_vehicles: int = 8,
    seed: int = 0,
    config: DistillConfig = DistillConfig(),
    params: PlatoonParams = PlatoonParams(),
    log: Callable[[str], None] | None = None,
    evaluate: Evaluator | None = None,
    max_steps: int | None = None,
    snapshots: Snapshots | None = None,
) -> PPOResult:
    """Distil the expert into the shared actor on ``scenario`` with N followers.

    Collects ``config.rounds`` rounds of ``episodes_per_round`` episodes, or stops collecting
    once ``max_steps`` environment steps are collected (``--steps``; None: no cap): that round
    is fitted on what it holds and is the last. Returns the round whose actor has the fewest
    validation collisions, then the best validation reward (actions sampled as trained, scored
    by ``evaluate``), as :class:`marl.ppo.PPOResult` (``steps``: environment steps collected);
    the last round when ``evaluate`` is None. With ``snapshots`` it continues from the run's
    snapshot file where there is one, and keeps one there after a round every so often (the
    actor, Adam's state, the data set, the generators, the curve and the kept round).
    """
    cfg, sc = config, as_scenario(scenario)
    n = check_vehicles(n_vehicles)
    torch.manual_seed(int(seed))
    gen = torch.Generator().manual_seed(int(seed))
    actor_cfg = cfg.actor_config()
    actor = SharedActor(actor_cfg, params)
    opt = torch.optim.Adam(actor.body.parameters(), lr=cfg.lr)
    obs_rows: list[torch.Tensor] = []
    label_rows: list[torch.Tensor] = []
    curve: list[dict[str, float]] = []
    best: dict[str, float] = {}
    best_state = as_shipped(actor).state_dict()
    steps, first, before_s = 0, 0, 0.0
    state = snapshots.read() if snapshots is not None else None
    if state is not None:
        assert snapshots is not None
        with torch.no_grad():
            for k, t in module_tensors(actor).items():
                t.copy_(state["actor"][k])
        opt.load_state_dict(state["optimiser"])
        obs_rows, label_rows = [state["data"][0]], [state["data"][1]]
        curve, best, best_state = state["curve"], state["best"], state["best_state"]
        steps, first, before_s = state["steps"], state["round"], state["elapsed_s"]
        gen.set_state(state["generator"])
        from marl.checkpoint import set_process_rng_state

        set_process_rng_state(state["process_rng"])
        if log:
            log(f"resumed from {snapshots.path}: round {first}, {steps} steps")
    t0 = time.perf_counter()
    for rnd in range(first, cfg.rounds):
        if max_steps is not None and steps >= max_steps:
            break
        env = PlatoonEnv(sc, n, params, action_mode="accel", channel=ChannelConfig())
        seeds = training_episode_seeds(seed, rnd * cfg.episodes_per_round,
                                       cfg.episodes_per_round)
        obs = env.reset(seeds)
        expert = make_expert(env)
        n_expert = int(math.floor(cfg.episodes_per_round * cfg.beta**rnd))
        for _ in range(env.n_steps):
            s = env.state
            assert s is not None
            live = torch.from_numpy(~s.done)
            label = expert(s)
            x = torch.from_numpy(agent_inputs(obs, "accel"))
            obs_rows.append(x[live].reshape(-1, x.shape[-1]))
            label_rows.append(torch.from_numpy(np.asarray(label, dtype=np.float32))[live].reshape(-1))
            steps += int(live.sum())
            command = np.asarray(label, dtype=np.float64).copy()
            if rnd > 0:
                with torch.no_grad():
                    mine = actor.command(actor(x)).numpy().astype(np.float64)
                command[n_expert:] = mine[n_expert:]
            res = env.step(command)
            obs = res.observation
            if res.done.all() or (max_steps is not None and steps >= max_steps):
                break
        data_x, data_u = torch.cat(obs_rows), torch.cat(label_rows)
        if rnd == 0:
            with torch.no_grad():
                actor.obs_mean.copy_(data_x.double().mean(0))
                actor.obs_var.copy_(data_x.double().var(0, unbiased=False))
        _fit(actor, opt, data_x, data_u, cfg, gen)
        check_finite_weights((actor,), f"distill {cfg.expert} on {sc.id}, seed {seed}",
                             f"round {rnd}")
        shipped = as_shipped(actor)
        if evaluate is None:
            best_state = shipped.state_dict()
        else:
            score = validation(evaluate, shipped)
            curve.append({"steps": float(steps), **score})
            if log:
                log(f"distill {cfg.expert} {sc.id} seed {seed}: round {rnd} ({len(data_u)} "
                    f"labels), validation reward {score['reward']:.1f}, collisions "
                    f"{score['collisions']:.0f}")
            if beats(score, best):
                best = {"steps": float(steps), "round": float(rnd), **score}
                best_state = shipped.state_dict()
        last = rnd + 1 == cfg.rounds or (max_steps is not None and steps >= max_steps)
        if snapshots is not None and not last and snapshots.due():
            from marl.checkpoint import process_rng_state

            snapshots.write(steps, {
                "actor": {k: t.detach().clone() for k, t in module_tensors(actor).items()},
                "optimiser": opt.state_dict(), "data": [data_x, data_u],
                "curve": curve, "best": best, "best_state": best_state, "steps": steps,
                "round": rnd + 1, "generator": gen.get_state(),
                "process_rng": process_rng_state(),
                "elapsed_s": before_s + time.perf_counter() - t0})
    actor.load_state_dict(best_state)
    rate = steps / max(before_s + time.perf_counter() - t0, 1e-9)
    return PPOResult(actor, steps, curve, best, rate, actor_cfg)


def _fit(actor: SharedActor, opt: torch.optim.Optimizer, x: torch.Tensor, u: torch.Tensor,
         cfg: DistillConfig, gen: torch.Generator) -> None:
    """``grad_steps`` Adam steps of squared command error on random minibatches; the log std set
    from the residuals (see the module's text)."""
    nx = actor.normalise(x)
    rows = len(u)
    for _ in range(cfg.grad_steps):
        idx = torch.randint(rows, (min(cfg.minibatch_rows, rows),), generator=gen)
        loss = (actor.command(actor.policy(nx[idx])) - u[idx]).pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    with torch.no_grad():  # residual RMS in command space over the squash's slope at zero
        rms = float((actor.command(actor.policy(nx)) - u).pow(2).mean().sqrt())
        actor.log_std.fill_(math.log(rms / float(actor.half_range) + 1e-6))
