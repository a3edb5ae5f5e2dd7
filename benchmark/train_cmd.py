"""``cacc-bench train``: train one MARL algorithm on one scenario and store the policy.

Writes ``<out>/<algo>__<scenario>__n<N>__s<seed>.pt`` (checkpoint), ``.curve.csv`` (episode,
steps, training reward, evaluation reward) and ``.log`` (evaluations, bits communicated).
Shows a progress bar on a terminal and stays quiet otherwise.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from envs.errors import ConfigError, UnknownNameError

DEFAULT_OUT = "controllers/checkpoints"


def _parser() -> argparse.ArgumentParser:
    from marl.common import ALGORITHM_NAMES

    p = argparse.ArgumentParser(
        prog="cacc-bench train",
        description="Train a MARL algorithm (one agent per follower) on a scenario.",
    )
    p.add_argument("--algo", required=True, help=f"one of: {', '.join(ALGORITHM_NAMES)}")
    p.add_argument("--scenario", required=True, help="scenario id, e.g. catchup-v1")
    p.add_argument("--steps", type=int, default=600_000, help="environment steps (default 6e5)")
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    p.add_argument("--vehicles", type=int, default=8, help="followers N (default 8)")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    p.add_argument(
        "--episodes-parallel", type=int, default=None, help="B episodes stepped together"
    )
    return p


class _Bar:
    """A one-line progress bar on a terminal (nothing otherwise)."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.t0 = time.perf_counter()
        self.last_eval = float("nan")

    def __call__(self, steps: int, total: int, row: dict[str, float]) -> None:
        if row.get("eval_reward") == row.get("eval_reward"):  # not NaN
            self.last_eval = row["eval_reward"]
        if not self.enabled:
            return
        frac = min(steps / max(total, 1), 1.0)
        rate = steps / max(time.perf_counter() - self.t0, 1e-9)
        eta = (total - steps) / max(rate, 1e-9)
        bar = "#" * int(30 * frac)
        sys.stderr.write(
            f"\r[{bar:<30}] {100 * frac:5.1f}% {steps}/{total} steps {rate:.0f}/s "
            f"eta {eta:.0f}s train {row['train_reward']:.1f} eval {self.last_eval:.1f}  "
        )
        sys.stderr.flush()
        if steps >= total:
            sys.stderr.write("\n")


def main(argv: list[str]) -> int:
    """Entry point: ``cacc-bench train --algo NAME --scenario ID [...]``."""
    from envs.scenarios import make_scenario
    from marl.common import ALGORITHM_NAMES, algorithm, checkpoint_stem, run_training

    args = _parser().parse_args(argv)
    if args.algo not in ALGORITHM_NAMES:
        raise UnknownNameError("algorithm", args.algo, ALGORITHM_NAMES)
    make_scenario(args.scenario)  # UnknownNameError for an unknown id
    if args.steps < 1:
        raise ConfigError(f"--steps must be >= 1, got {args.steps}")
    algo = algorithm(args.algo)
    options = {}
    if args.episodes_parallel is not None:
        options["episodes_parallel"] = args.episodes_parallel
    config = algo.config_cls(**options)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / (checkpoint_stem(args.algo, args.scenario, args.vehicles, args.seed) + ".log")
    tty = sys.stderr.isatty()
    with open(log_path, "w") as log_fh:

        def log(line: str) -> None:
            log_fh.write(time.strftime("%H:%M:%S ") + line + "\n")
            log_fh.flush()

        log(
            f"train {args.algo} on {args.scenario}, N = {args.vehicles}, seed {args.seed}, "
            f"{args.steps} steps, config {config}"
        )
        result = run_training(
            algo,
            config,
            args.scenario,
            args.vehicles,
            args.steps,
            args.seed,
            out,
            progress=_Bar(tty),
            log=log,
        )
    if tty:
        print(
            f"checkpoint {result.checkpoint}, curve {result.curve_csv}, log {log_path}; "
            f"{result.env_steps_per_s:.0f} env steps/s",
            file=sys.stderr,
        )
    return 0
