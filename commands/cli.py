"""The ``cacc-bench`` command line.

Subcommands with their own option parsers live in their own modules and are imported only when
called, so ``cacc-bench --help`` and ``cacc-bench list`` start fast. Every user-fixable error
(:class:`infra.errors.CaccBenchError`) becomes a one-paragraph message and exit status 2.
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import os
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, TypeVar

from infra.errors import CaccBenchError

if TYPE_CHECKING:
    import argparse
    from pathlib import Path

    from envs.scenarios import Scenario

T = TypeVar("T")

#: subcommand -> (module with ``main(argv) -> int``, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "list": ("commands.list", "list scenarios and controllers"),
    "run": ("commands.run", "run a sweep of controllers x scenarios x sizes x seeds"),
    "leaderboard": ("commands.leaderboard", "rebuild runs.csv and leaderboard.csv"),
    "plot": ("commands.plot", "figures from a results folder"),
    "stability": ("commands.stability", "string stability, analytic and measured"),
    "train": ("commands.train", "train a MARL algorithm"),
    "tune": ("commands.tune", "tune every MARL algorithm with the same budget (Optuna)"),
    "reproduce": ("commands.reproduce", "the paper's tables, curves and claims in one report"),
    "pareto": ("commands.pareto", "energy against spacing error for every controller family"),
    "sensitivity": ("commands.sensitivity", "BDC-MARL's knobs one at a time and its V2V tolerance"),
    "compare-learned": ("commands.compare_learned",
                        "learned control against MPC: action set, learning, V2V, one report"),
    "generalise": ("commands.generalise",
                   "learned controllers off their training scenario: a matrix on the test seeds"),
    "penetration": ("commands.penetration",
                    "mixed traffic: which family damps waves at what share of automated vehicles"),
    "heterogeneous": ("commands.heterogeneous",
                      "a bus, a van and cars in three orders under every family, one report"),
    "string-stability": ("commands.string_stability",
                         "string stability against reward for every controller, one report"),
    "fit-power": ("commands.fit_power", "re-fit the energy polynomial and print its quality"),
    "perf": ("commands.perf", "environment, controller and training throughput"),
    "sumo-compare": ("commands.sumo_compare", "the built-in simulator and SUMO side by side"),
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


def command_parser(name: str, doc: str | None, raw: bool = False) -> argparse.ArgumentParser:
    """The option parser of ``cacc-bench NAME``, described by the first paragraph of ``doc`` (a
    docstring, as :func:`plain` help text; ``raw``: all of it, laid out as written)."""
    import argparse

    text = plain(doc) if raw else plain(doc).split("\n\n")[0]
    return argparse.ArgumentParser(
        prog=f"cacc-bench {name}", description=text,
        formatter_class=argparse.RawDescriptionHelpFormatter if raw else argparse.HelpFormatter)


def add_scenarios_option(parser: argparse.ArgumentParser, default: str) -> None:
    """``--scenarios``: the comma list of scenario ids a study runs on (read by
    :func:`scenarios_argument`)."""
    parser.add_argument("--scenarios", default=default,
                        help="comma list of scenario ids (default: %(default)s)")


def add_study_options(parser: argparse.ArgumentParser, out: str, what: str = "study",
                      executor: str = "process") -> None:
    """The options every study command ends with: ``--out`` (default ``out``), ``--resume``
    (complete the ``what`` in ``--out``) and the executor options
    (:func:`benchmark.executors.add_executor_options`, default ``executor``: a study's sweep of
    many runs takes the cores)."""
    from benchmark.executors import add_executor_options

    parser.add_argument("--out", default=out, help="output folder (default: %(default)s)")
    parser.add_argument("--resume", action="store_true", help=f"complete a {what} in --out")
    add_executor_options(parser, default=executor)


def report_command(prog: str, argv: Sequence[str]) -> str:
    """The command line a report prints: ``cacc-bench PROG`` and its options without ``--out``
    (the report names its own folder, never a machine's path) and ``--resume``."""
    import shlex

    shown = [a for i, a in enumerate(argv)
             if a not in ("--out", "--resume") and not a.startswith("--out=")
             and (i == 0 or argv[i - 1] != "--out")]
    return " ".join([f"cacc-bench {prog}", *(shlex.quote(a) for a in shown)])


def check_executor(workers: int, ray_address: str | None = None) -> None:
    """The executor options of every command that runs in parallel, checked before any work:
    ``--workers`` at least 1 and a ``--ray-address`` that answers."""
    from benchmark.executors import check_ray_address
    from infra.errors import ConfigError

    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    check_ray_address(ray_address)


@contextlib.contextmanager
def out_folder(text: str, check: Callable[[Path], None] | None = None) -> Iterator[Path]:
    """``--out`` as a folder files can be written in (:func:`benchmark.paths.writable_dir`),
    then ``check``ed (refusals before any work), then held by this command alone inside the
    block (:func:`benchmark.folder_lock.folder_lock`: a second writer is refused, naming the
    first)."""
    from benchmark.folder_lock import folder_lock
    from benchmark.paths import writable_dir

    out = writable_dir(text)
    if check is not None:
        check(out)
    with folder_lock(out):
        yield out


def check_study_folder(out: Path, resume: bool, study: str, files: Sequence[str],
                       remade: str) -> None:
    """Refuse, before any run, a folder holding a ``study`` study (the first two of its
    ``files``, report and table, or its store) unless ``resume`` (a finished file changes only
    when asked; ``remade``: what a resumed study makes again), and output paths that cannot be
    written (a folder where one of ``files`` goes, a file where ``runs/`` or ``figures/`` go).

    Raises
    ------
    ConfigError
        Naming the first file found and what to do.
    """
    from infra.errors import ConfigError

    held = [name for name in (*files[:2], "runs/store.sqlite") if (out / name).exists()]
    if held and not resume:
        raise ConfigError(f"--out {out} already holds a {study} study ({held[0]}); add "
                          f"--resume to complete it (stored runs are kept; {remade} are made "
                          "again), or choose another --out")
    wrong = ([out / name for name in files if (out / name).is_dir()]
             + [p for p in (out / "runs", out / "figures") if p.exists() and not p.is_dir()])
    if wrong:
        kind = "a folder" if wrong[0].is_dir() else "a file"
        raise ConfigError(f"--out {out}: {wrong[0].relative_to(out)} is {kind}, where the study "
                          "writes the other; move it away, or choose another --out")


def named_once(items: Sequence[T], labels: Sequence[str], option: str) -> list[T]:
    """``items`` once per label, in order (:func:`infra.naming.merge_repeats`); a repeat is
    said on standard error."""
    from infra.naming import merge_repeats

    once, note = merge_repeats(items, labels, option)
    if note:
        print(note, file=sys.stderr)
    return once


def controllers_argument(text: str) -> list[tuple[str, dict[str, str]]]:
    """The controllers a ``--controllers`` argument names, with their options, each setting
    once (by its leaderboard label, :func:`controllers.registry.controller_label`)."""
    from controllers.registry import controller_label, parse_controller_list

    given = parse_controller_list(text)
    return named_once(given, [controller_label(*c) for c in given], "--controllers")


def scenarios_argument(text: str, option: str = "--scenarios") -> list[Scenario]:
    """The scenarios a ``--scenarios`` (or ``--scenario``) argument names, each built and checked
    once, here (:func:`envs.scenarios.parse_scenarios`), one per canonical label, in order. The
    layers below take these objects and never parse the text again.

    Raises
    ------
    ConfigError
        For an empty list; as :func:`envs.scenarios.make_scenario` for a bad item.
    """
    from envs.scenarios import parse_scenarios
    from infra.errors import ConfigError

    if not text.strip(" ,"):
        raise ConfigError(f"{option}: no scenario named")
    built = parse_scenarios(text)
    return named_once(built, [sc.label for sc in built], option)


def fail(message: str) -> int:
    """Print a user error and return exit status 2."""
    print(f"cacc-bench: error: {message}", file=sys.stderr)
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cacc-bench`` console script.

    SIGINT and SIGTERM are handled from the first line (:mod:`infra.interrupt`): the command ends
    with 128 + the signal's number and one line on stderr, after its worker processes and Ray
    were stopped; repeated signals never interrupt that shutdown. A signal that came while the
    command held signals (:func:`infra.interrupt.held`: finishing a write) ends it the same way
    once it returns, never with the command's own status.
    """
    from infra.interrupt import Interrupted, install, received, set_exit_line

    on_main_thread = threading.current_thread() is threading.main_thread()
    previous = install() if on_main_thread else {}
    args = sys.argv[1:] if argv is None else list(argv)
    command = args[0] if args else ""
    if argv is None:  # its own process: a start-up that cannot be unwound may end it at once
        set_exit_line(lambda signum: interrupted_line(signum, command))
    try:
        try:
            status = _main(argv)
        finally:  # a reader that went away shows here (argparse's --help too), not at exit
            sys.stdout.flush()
        signum = received()  # held while the command finished (or swallowed by a library)
        return status if signum is None else _interrupted(Interrupted(signum), command)
    except BrokenPipeError:  # stdout's reader went away (`cacc-bench --help | head -1`)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing left to flush
        return 128 + int(signal.SIGPIPE)
    except KeyboardInterrupt as exc:
        return _interrupted(exc, command)
    except ImportError:  # a signal during a C extension's start-up (numpy's) ends that import
        signum = received()  # with an ImportError: the signal's
        if signum is None:
            raise
        return _interrupted(Interrupted(signum), command)
    finally:
        set_exit_line(None)
        _end(previous, restore_handlers=argv is not None)


def _main(argv: Sequence[str] | None) -> int:
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
    try:
        return int(entry(rest) or 0)
    except CaccBenchError as exc:
        _stop_workers()
        return fail(str(exc))
    except Exception as exc:
        reason = no_space(exc)
        if reason is None:
            raise
        _stop_workers()
        return fail(f"{cmd} stopped: {reason}; files already finished were left as they were "
                    "(each is replaced only when whole, the store in whole transactions): free "
                    "some space (or lift the file-size limit) and rerun (with --resume where the "
                    "command has it)")


#: ``errno`` values of a write refused for room: a full disk, a quota, a file-size limit.
_NO_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
#: SQLite's names for the same: a full disk, a write the system refused (a file-size limit).
_SQLITE_NO_SPACE = ("SQLITE_FULL", "SQLITE_IOERR_WRITE")


def no_space(exc: BaseException) -> str | None:
    """What a write refused for want of room reports (``OSError`` of :data:`_NO_SPACE`, or
    SQLite's :data:`_SQLITE_NO_SPACE`), or None for any other exception.

    Parameters
    ----------
    exc : BaseException
        The exception a command raised.

    Returns
    -------
    str or None
        The reason with the file where it is known, e.g. ``No space left on device
        (/data/out/runs.csv)``.
    """
    if isinstance(exc, OSError) and exc.errno in _NO_SPACE:
        where = f" ({exc.filename})" if exc.filename else ""
        return f"{exc.strerror or os.strerror(exc.errno)}{where}"
    if getattr(exc, "sqlite_errorname", None) in _SQLITE_NO_SPACE:
        return f"the results store could not grow ({exc})"
    return None


#: Commands that complete an interrupted invocation with ``--resume``.
RESUMABLE = ("run", "train", "tune", "reproduce", "pareto", "sensitivity", "compare-learned",
             "generalise", "penetration", "string-stability", "heterogeneous")


def _interrupted(exc: KeyboardInterrupt, command: str = "") -> int:
    """Stop what runs (signals only recorded from here on), print one line, 128 + signum."""
    from infra.interrupt import Interrupted, hold_forever, received

    hold_forever()
    # the first signal received names it (a library may re-raise it as a bare KeyboardInterrupt:
    # Ray's blocking calls do)
    signum = received() or (exc.signum if isinstance(exc, Interrupted) else signal.SIGINT)
    _stop_workers()
    print(interrupted_line(signum, command), file=sys.stderr)
    return 128 + int(signum)


def interrupted_line(signum: int, command: str) -> str:
    """The one line an interrupted ``command`` prints (what was kept, how to go on)."""
    advice = ("its study records the trial in flight as failed and keeps the finished ones "
              "(complete with --resume)" if command == "tune" else
              "finished runs are stored, the runs in flight keep their last snapshot "
              "(continue with --resume)" if command == "train" else
              "the run in flight was not stored, finished runs are (complete with --resume)"
              if command in RESUMABLE else
              "nothing in flight was written, finished files were left as they were (rerun it)")
    return f"cacc-bench: interrupted ({signal.Signals(signum).name}); {advice}"


def _stop_workers() -> None:
    """Kill the process executor's workers still running, then stop Ray (every exit path)."""
    executors = sys.modules.get("benchmark.executors")
    if executors is not None:
        executors.stop_all()
    _shutdown_ray()


def _end(previous: dict, restore_handlers: bool) -> None:
    """The end of every command: workers and Ray stopped; the signal handlers restored when
    called from Python, kept (recording only) when the process is about to exit."""
    from infra.interrupt import hold_forever, restore

    if not restore_handlers:
        hold_forever()  # a signal while the interpreter exits prints no traceback
    _stop_workers()
    if restore_handlers:
        restore(previous)
    elif previous:
        # ignored, not reset to the default at the interpreter's exit (which would let a late
        # signal kill the process with it instead of the status the command returned)
        for sig in previous:
            signal.signal(sig, signal.SIG_IGN)


def _shutdown_ray() -> None:
    """Stop the Ray instance a command started or attached to (every exit path)."""
    executors = sys.modules.get("benchmark.executors")
    if executors is not None:
        executors.shutdown_ray()


if __name__ == "__main__":
    sys.exit(main())
