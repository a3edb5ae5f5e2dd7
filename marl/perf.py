"""Training throughput of the MARL learners (called by ``cacc-bench perf``)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from marl.ppo_nets import PPOConfig


def train_throughput(
    algo: str,
    steps: int = 20_000,
    n_vehicles: int = 8,
    scenario_id: str = "catchup-v1",
    episodes_parallel: int | None = None,
    cpu_time: bool = False,
    population: int = 1,
    device: str = "cpu",
) -> float:
    """Environment steps per second of training ``algo`` from scratch, one process, one thread.

    Steps are counted across the parallel episodes (an active episode's step is one environment
    step), as for the training budget. Nothing is written and no evaluation runs.

    Parameters
    ----------
    cpu_time : bool
        Divide by this process's CPU time instead of the wall clock (for busy shared machines).
    population : int
        Train this many seeds (0, 1, ...) at once as one population, ``steps`` each; the rate
        is the population's total.
    device : str
        Where the networks train (``cpu`` or ``cuda[:K]``; the environments stay on the CPU).
    """
    from marl.config import algorithm
    from marl.selection import run_population

    torch.set_num_threads(1)
    a = algorithm(algo)
    cfg = (
        a.config_cls()
        if episodes_parallel is None
        else a.config_cls(episodes_parallel=episodes_parallel)
    )
    clock = time.process_time if cpu_time else time.perf_counter
    t0 = clock()
    # the first ``steps`` of a run with the paper's budget (the entropy schedule of 6e5 steps)
    results = run_population(a, [cfg] * population, scenario_id, n_vehicles, steps,
                             list(range(population)), None, schedule_steps=600_000,
                             device=device)
    return sum(r.steps for r in results) / max(clock() - t0, 1e-9)


def shared_network_bound(config: PPOConfig | None = None, n_vehicles: int = 8,
                         repeats: int = 6) -> float:
    """Environment steps per second that a shared-policy learner's networks alone allow: one
    update's rollout forwards, then per minibatch forward, PPO loss, backward, norm clip and Adam
    (:class:`marl.ppo_nets.SharedActor` and :class:`~marl.ppo_nets.Critic` on random inputs; no
    environment, returns or bookkeeping), one torch thread; the median of ``repeats`` updates
    after a warm-up. No learner with ``config`` (default :class:`~marl.ppo_nets.PPOConfig`)
    trains faster on this machine."""
    import statistics

    from marl.ppo_nets import Critic, PPOConfig, SharedActor

    cfg = PPOConfig() if config is None else config
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        g = torch.Generator().manual_seed(0)
        actor, critic = SharedActor(cfg), Critic(cfg)
        params = [*actor.parameters(), *critic.parameters()]
        opt = torch.optim.Adam(params, lr=cfg.lr, eps=1e-5)
        rows = cfg.n_envs * cfg.rollout_steps * n_vehicles
        obs = torch.randn(cfg.rollout_steps, cfg.n_envs, n_vehicles, cfg.obs_dim, generator=g)
        flat = obs.reshape(rows, cfg.obs_dim)
        z, adv, ret = (torch.randn(rows, generator=g) for _ in range(3))
        old_logp = torch.zeros(rows)
        times = []
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            with torch.no_grad():  # the rollout's acting, one step of B episodes at a time
                for t in range(cfg.rollout_steps):
                    actor(obs[t])
                    critic(obs[t])
            for _ in range(cfg.epochs):
                order = torch.randperm(rows, generator=g)
                for start in range(0, rows, cfg.minibatch_rows):
                    idx = order[start:start + cfg.minibatch_rows]
                    logp, ent = actor.log_prob_entropy(actor(flat[idx]), z[idx])
                    ratio = (logp - old_logp[idx]).exp()
                    clipped = ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef)
                    pg = -torch.min(ratio * adv[idx], clipped * adv[idx]).mean()
                    v = critic(flat[idx][:, None, :])[:, 0]
                    loss = (pg + cfg.vf_coef * ((v - ret[idx]) ** 2).mean()
                            - cfg.ent_coef * ent.mean())
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    torch.nn.utils.clip_grad_norm_(params, cfg.max_grad_norm)
                    opt.step()
            times.append(time.perf_counter() - t0)
        return cfg.n_envs * cfg.rollout_steps / statistics.median(times[1:])
    finally:
        torch.set_num_threads(threads)
