"""What a residual on ``cacc`` learns on slowdown-v1 (docs/learned-control.md): the objective
PPO maximises against the benchmark's score.

Trains ``ippo`` with the ``cacc-exact`` prior for a number of steps (no validation, the last
weights), then scores the untrained actor (the prior plus its initial, near-zero residual) and
the trained one on the 32 validation seeds, greedy: the evaluation reward (mean over steps of
the sum over agents), the training reward's return discounted from the first step
(``gamma = 0.99``, the learner's), and the evaluation reward per 100 steps.

    .venv/bin/python docs/scripts/residual_objective.py 300000
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from envs.channel import ChannelConfig
from envs.params import VALIDATION_SEEDS, PlatoonParams
from envs.platoon import PlatoonEnv
from marl import ppo
from marl.acting import agent_inputs, to_command
from marl.ppo_nets import PPOConfig, SharedActor

SCENARIO = "slowdown-v1"


def score(actor: SharedActor, training: bool, gamma: float) -> tuple[float, float, np.ndarray]:
    """(mean reward, return discounted from step 0, per-step sums) on the validation seeds."""
    params = PlatoonParams()
    env = PlatoonEnv(SCENARIO, 8, params, training=training, action_mode="accel",
                     channel=ChannelConfig(0.0, 0.0, params.dt_s))
    obs, sc = env.reset(np.asarray(VALIDATION_SEEDS)), env.scenario
    rewards = []
    for _ in range(env.n_steps):
        x = agent_inputs(obs, "accel")
        with torch.no_grad():
            mean = actor(torch.from_numpy(x))
        res = env.step(to_command(actor, mean, env.state, params, x,
                                  (sc.target_gap_m, sc.target_speed_mps)))
        rewards.append(res.reward.copy())
        obs = res.observation
        if res.done.all():
            break
    r = np.array(rewards)  # (T, B, N)
    per_step = r.sum(-1).mean(1)
    discounted = float((r.sum(-1).mean(1) * gamma ** np.arange(len(r))).sum())
    return float(per_step.mean()), discounted, per_step


def main(steps: int) -> None:
    cfg = PPOConfig(algo="ippo", action_mode="accel", prior="cacc-exact", critic_warmup_updates=5,
                    lr=3e-4, init_log_std=-4.0, n_envs=64, eval_every_steps=10**7)
    torch.manual_seed(0)
    untrained = SharedActor(cfg, PlatoonParams(), 0)
    trained = ppo.train(SCENARIO, 8, 0, steps, cfg).actor
    for name, actor in (("untrained", untrained), ("trained", trained)):
        actor.eval()
        reward, _, per_step = score(actor, False, cfg.gamma)
        _, discounted, _ = score(actor, True, cfg.gamma)
        chunks = ", ".join(f"{per_step[i:i + 100].mean():.1f}" for i in range(0, len(per_step), 100))
        print(f"{name}: evaluation reward {reward:.1f}; training return discounted from step 0 "
              f"{discounted:.1f}; evaluation reward per 100 steps: {chunks}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 300_000)
