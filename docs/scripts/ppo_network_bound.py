"""What the shared-policy learner's networks alone allow: an upper bound on its training rate.

One update of ``marl.ppo`` with its default config (``PPOConfig()``: B = 64 episodes, T = 64
steps, N = 8 followers, 4 epochs of 8192-row minibatches, two hidden layers of 64) does, for
the ``B T = 4096`` environment steps it learns from, at least this: the rollout's acting
forward of actor and critic (T products of ``B N`` rows), then per minibatch the forward of both
networks, a PPO-shaped loss, the backward pass, the global norm clip and Adam. This script times
exactly that, with the project's own ``SharedActor`` and ``Critic`` on random inputs, no
environment, no returns, no bookkeeping, one torch thread; ``4096 / seconds per update`` is a
rate the learner cannot exceed on this machine with that config.

    .venv/bin/python docs/scripts/ppo_network_bound.py [--hidden 64] [--epochs 4]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import torch

from marl.ppo_nets import Critic, PPOConfig, SharedActor


def seconds_per_update(cfg: PPOConfig, n_vehicles: int = 8, repeats: int = 7) -> list[float]:
    """Wall seconds of the networks' work of one update, ``repeats`` times (the first one, a
    warm-up, dropped)."""
    g = torch.Generator().manual_seed(0)
    actor, critic = SharedActor(cfg), Critic(cfg)
    opt = torch.optim.Adam([*actor.parameters(), *critic.parameters()], lr=cfg.lr, eps=1e-5)
    rows = cfg.n_envs * cfg.rollout_steps * n_vehicles
    obs = torch.randn(cfg.rollout_steps, cfg.n_envs, n_vehicles, cfg.obs_dim, generator=g)
    flat = obs.reshape(rows, cfg.obs_dim)
    z = torch.randn(rows, generator=g)
    adv, ret = torch.randn(rows, generator=g), torch.randn(rows, generator=g)
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        with torch.no_grad():  # the rollout's acting: one step of B episodes at a time
            for t in range(cfg.rollout_steps):
                actor(obs[t])
                critic(obs[t])
        old_logp = torch.zeros(rows)
        for _ in range(cfg.epochs):
            order = torch.randperm(rows, generator=g)
            for start in range(0, rows, cfg.minibatch_rows):
                idx = order[start:start + cfg.minibatch_rows]
                out = actor(flat[idx])
                logp, ent = actor.log_prob_entropy(out, z[idx])
                ratio = (logp - old_logp[idx]).exp()
                pg = -torch.min(ratio * adv[idx], ratio.clamp(1 - cfg.clip_coef,
                                                              1 + cfg.clip_coef) * adv[idx]).mean()
                v = critic(flat[idx][:, None, :])[:, 0]
                loss = pg + cfg.vf_coef * ((v - ret[idx]) ** 2).mean() - cfg.ent_coef * ent.mean()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_([*actor.parameters(), *critic.parameters()],
                                               cfg.max_grad_norm)
                opt.step()
        times.append(time.perf_counter() - t0)
    return times[1:]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hidden", type=int, default=PPOConfig.hidden)
    p.add_argument("--epochs", type=int, default=PPOConfig.epochs)
    p.add_argument("--n-envs", type=int, default=PPOConfig.n_envs)
    p.add_argument("--rollout-steps", type=int, default=PPOConfig.rollout_steps)
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg = dataclasses.replace(PPOConfig(), hidden=args.hidden, epochs=args.epochs,
                              n_envs=args.n_envs, rollout_steps=args.rollout_steps)
    times = seconds_per_update(cfg)
    env_steps = cfg.n_envs * cfg.rollout_steps
    med = statistics.median(times)
    print(f"hidden {cfg.hidden}, epochs {cfg.epochs}, B {cfg.n_envs}, T {cfg.rollout_steps}: "
          f"networks' work per update {med * 1e3:.1f} ms (runs {min(times) * 1e3:.1f} to "
          f"{max(times) * 1e3:.1f}); at most {env_steps / med:,.0f} environment steps/s")


if __name__ == "__main__":
    main()
