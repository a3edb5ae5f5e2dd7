"""The ``cacc-bench`` command line.

Subcommands with their own option parsers live in their own modules and are imported only when
called, so ``cacc-bench --help`` and ``cacc-bench list`` start fast. Every user-fixable error
(:class:`envs.errors.CaccBenchError`) becomes a one-paragraph message and exit status 2.
"""

from __future__ import annotations

import importlib
import re
import signal
import sys
import threading
from collections.abc import Callable, Sequence

from envs.errors import CaccBenchError

#: subcommand -> (module with ``main(argv) -> int``, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "list": ("benchmark.list_cmd", "list scenarios and controllers"),
    "run": ("benchmark.run_cmd", "run a sweep of controllers x scenarios x sizes x seeds"),
    "leaderboard": ("benchmark.leaderboard_cmd", "rebuild runs.csv and leaderboard.csv"),
    "plot": ("benchmark.plot_cmd", "figures from a results folder"),
    "stability": ("benchmark.stability_cmd", "string stability, analytic and measured"),
    "train": ("benchmark.train_cmd", "train a MARL algorithm"),
    "tune": ("benchmark.tune_cmd", "tune every MARL algorithm with the same budget (Optuna)"),
    "reproduce": ("benchmark.reproduce_cmd", "the paper's tables, curves and claims in one report"),
    "pareto": ("benchmark.pareto_cmd", "energy against spacing error for every controller family"),
    "sensitivity": ("benchmark.sensitivity_cmd", "BDC-MARL's knobs one at a time and its V2V tolerance"),
    "fit-power": ("benchmark.fit_power", "re-fit the energy polynomial and print its quality"),
    "perf": ("benchmark.perf", "environment, controller and training throughput"),
}

USAGE = """usage: cacc-bench <command> [options]

cacc-bench: learned and optimisation-based platoon controllers on one simulated platoon.

commands:
{commands}

Run `cacc-bench <command> --help` for the options of a command.
Main job: `cacc-bench run --controllers ovm,cacc` (writes results/run/leaderboard.csv).
"""


def _usage() -> str:
    width = max(len(k) for k in SUBCOMMANDS)
    lines = [f"  {k.ljust(width)}  {h}" for k, (_, h) in SUBCOMMANDS.items()]
    return USAGE.format(commands="\n".join(lines))


def plain(text: str | None) -> str:
    """A docstring as help text: reStructuredText roles and double backticks removed."""
    text = re.sub(r":(?:func|class|mod|meth|attr|data):`~?([^`]+)`", r"\1", text or "")
    return text.replace("``", "")


def fail(message: str) -> int:
    """Print a user error and return exit status 2."""
    print(f"cacc-bench: error: {message}", file=sys.stderr)
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cacc-bench`` console script."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:  # a command is required: usage on stderr, status 2 (argparse's convention)
        print(_usage(), file=sys.stderr)
        return 2
    if args[0] == "help" and len(args) > 1:  # `cacc-bench help run` is `cacc-bench run --help`
        args = [args[1], "--help"]
    if args[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    if args[0] == "--version":
        from benchmark.provenance import version

        print(f"cacc-bench {version()}")
        return 0
    cmd, rest = args[0], args[1:]
    if cmd not in SUBCOMMANDS:
        return fail(
            f"unknown command {cmd!r}; valid commands are: {', '.join(SUBCOMMANDS)}. "
            "Run `cacc-bench --help`."
        )
    module_name = SUBCOMMANDS[cmd][0]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            return fail(f"command {cmd!r} is not available in this version")
        raise
    entry: Callable[[list[str]], int] = module.main
    from envs.interrupt import Interrupted, install, restore

    previous = install() if threading.current_thread() is threading.main_thread() else {}
    try:
        return int(entry(rest) or 0)
    except CaccBenchError as exc:
        return fail(str(exc))
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else signal.SIGINT
        print(f"cacc-bench: interrupted ({signal.Signals(signum).name}); the run in flight was "
              "not stored, finished runs are (complete with --resume)", file=sys.stderr)
        return 128 + int(signum)
    finally:
        _shutdown_ray()
        restore(previous)


def _shutdown_ray() -> None:
    """Stop the Ray instance a command started or attached to (every exit path)."""
    ray = sys.modules.get("ray")
    if ray is not None and getattr(ray, "is_initialized", lambda: False)():
        ray.shutdown()


if __name__ == "__main__":
    sys.exit(main())
