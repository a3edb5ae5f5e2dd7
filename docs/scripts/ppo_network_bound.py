"""What the shared-policy learner's networks alone allow: an upper bound on its training rate.

One update of ``marl.ppo`` with its default config (``PPOConfig()``: B = 64 episodes, T = 64
steps, N = 8 followers, 4 epochs of 8192-row minibatches, two hidden layers of 64) does, for
the ``B T = 4096`` environment steps it learns from, at least the networks' work that
:func:`marl.perf.shared_network_bound` times (also printed by ``cacc-bench perf --only train``
beside the learner's measured rate). This script prints it for other widths and epochs.

    .venv/bin/python docs/scripts/ppo_network_bound.py [--hidden 64] [--epochs 4]
"""

from __future__ import annotations

import argparse
import dataclasses

from marl.perf import shared_network_bound
from marl.ppo_nets import PPOConfig


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--hidden", type=int, default=PPOConfig.hidden)
    p.add_argument("--epochs", type=int, default=PPOConfig.epochs)
    args = p.parse_args()
    cfg = dataclasses.replace(PPOConfig(), hidden=args.hidden, epochs=args.epochs)
    rate = shared_network_bound(cfg)
    print(f"hidden {cfg.hidden}, epochs {cfg.epochs}, B {cfg.n_envs}, T {cfg.rollout_steps}: "
          f"the networks alone allow at most {rate:,.0f} environment steps/s")


if __name__ == "__main__":
    main()
