"""``cacc-bench stability``: string stability, analytic (linear laws) and measured (any controller).

Writes to ``--out`` (default ``results/stability``):

- ``stability_summary.csv``: ``controller, kind, time_gap_s, delay_s, lag_s, peak_gain,
  peak_omega_rad_s, h_min_s, string_stable`` (kind ``analytic``: continuous ``||Gamma||_inf``
  with the exact delay; ``empirical``: the measured sweep's maximum);
- ``stability.csv``: ``controller, kind, time_gap_s, delay_s, lag_s, omega_rad_s, gain``;
- ``stability_grid.csv`` (``||Gamma||_inf`` over 50 time gaps x 7 delays) and
  ``stability_h_min.csv`` (h_min against the delay for tau = 0.1, 0.5 s and the run's lag);
- figures (PNG + PDF): ``gamma_time_gaps``, ``h_min_delay``, ``peak_gain_grid`` and, with
  ``--empirical``, ``gamma_empirical``.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np

from analysis.stability_report import SUMMARY_COLUMNS, Entry, StabilityTables
from benchmark.export import write_csv
from commands.cli import command_parser
from envs.params import PlatoonParams
from infra.errors import CaccBenchError, ConfigError, ControllerContractError
from infra.interrupt import raise_if_interrupted
from infra.naming import is_reference
from infra.plugins import first_line

#: The V2V delay and actuator lag the analysis assumes unless told (s): string stability is
#: decided by them, and the ideal loop of ``run``'s defaults (no delay, no lag) hides what a
#: real one shows; the command says on standard output which it uses.
DEFAULT_DELAY_S = 0.2
DEFAULT_LAG_S = 0.1


def setting_line(args: argparse.Namespace, given: set[str]) -> str:
    """The line saying which delay and lag the analysis uses, and which are this command's
    defaults (``given``: the flags the user set)."""
    unset = [f for f in ("--delay", "--lag") if f not in given]
    why = (f" ({' and '.join(unset)} at this command's default{'s' * (len(unset) > 1)}; "
           "`cacc-bench run` defaults to no delay and no lag)") if unset else ""
    return f"V2V delay {args.delay:g} s, actuator lag {args.lag:g} s{why}"


def build_parser() -> argparse.ArgumentParser:
    """Options of ``cacc-bench stability``."""
    p = command_parser("stability", "String stability of platoon controllers: analytic "
                       "|Gamma(jw)| for the linear laws (acc, cacc), measured frequency sweeps "
                       "for any registered controller.")
    p.add_argument(
        "--controllers",
        default="cacc,acc",
        help="comma list, with options as name:key=value (default cacc,acc)",
    )
    p.add_argument(
        "--time-gap", type=float, default=0.5, help="time gap h of the linear laws, s (default 0.5)"
    )
    p.add_argument("--delay", type=float, default=None,
                   help=f"V2V delay theta, s (default {DEFAULT_DELAY_S:g}; `run`'s default is 0)")
    p.add_argument("--lag", type=float, default=None,
                   help=f"actuator lag tau, s (default {DEFAULT_LAG_S:g}; `run`'s default is 0)")
    p.add_argument(
        "--empirical",
        action="store_true",
        help="also measure |Gamma(jw)| by sine-v1 frequency sweeps",
    )
    p.add_argument("--n-vehicles", type=int, default=4, help="followers of the sweeps (default 4)")
    p.add_argument(
        "--amplitude",
        type=float,
        default=0.1,
        help="leader speed amplitude of the sweeps, m/s (default 0.1)",
    )
    p.add_argument("--omega-min", type=float, default=0.05, help="lowest frequency, rad/s")
    p.add_argument("--omega-max", type=float, default=3.0, help="highest frequency, rad/s")
    p.add_argument("--n-omega", type=int, default=12, help="frequencies of the sweep (default 12)")
    p.add_argument("--out", default="results/stability", help="output folder")
    return p


#: Most frequencies of one sweep.
MAX_N_OMEGA = 1000
#: Largest array an empirical sweep may allocate (its accelerations, steps x frequencies x
#: vehicles, float64).
MAX_SWEEP_BYTES = 2**30


def _check_args(args: argparse.Namespace) -> None:
    from infra.limits import MAX_TIME_GAP_S, check_delay, check_range, check_whole_steps

    check_delay(args.delay, "--delay")
    if args.empirical:  # the analytic loop takes any delay; the simulated sweeps whole steps
        check_whole_steps(args.delay, "--delay (with --empirical)", PlatoonParams().dt_s)
    for flag, value in (
        ("--time-gap", args.time_gap),
        ("--lag", args.lag),
    ):
        if not math.isfinite(value) or value < 0:
            raise ConfigError(f"{flag} must be a finite number >= 0, got {value}")
    if args.time_gap > MAX_TIME_GAP_S:  # the linear laws' own bound (controllers.linear)
        raise ConfigError(f"--time-gap must be at most {MAX_TIME_GAP_S:g} s, got {args.time_gap:g}")
    for flag, value in (
        ("--amplitude", args.amplitude),
        ("--omega-min", args.omega_min),
        ("--omega-max", args.omega_max),
    ):
        if not math.isfinite(value) or value <= 0:
            raise ConfigError(f"{flag} must be > 0, got {value}")
    if args.omega_max < args.omega_min:
        raise ConfigError("--omega-max must be >= --omega-min")
    nyquist = math.pi / PlatoonParams().dt_s
    if args.omega_max >= nyquist:
        raise ConfigError(
            f"--omega-max must lie below the Nyquist frequency {nyquist:.4g} rad/s"
        )
    check_range(args.n_omega, "--n-omega", 1, MAX_N_OMEGA)
    from envs.scenarios import check_vehicles

    check_vehicles(args.n_vehicles)
    if args.empirical:
        _check_sweep_size(args)


def _check_sweep_size(args: argparse.Namespace) -> None:
    """Refuse an empirical sweep whose arrays would not fit :data:`MAX_SWEEP_BYTES` (its
    episodes last at least ``periods`` periods of the lowest frequency)."""
    import inspect

    from analysis.stability import empirical_gain

    defaults = {k: v.default for k, v in inspect.signature(empirical_gain).parameters.items()}
    window_s = max(defaults["periods"] * 2 * math.pi / args.omega_min, defaults["min_window_s"])
    n_steps = (defaults["transient_s"] + window_s) / PlatoonParams().dt_s
    size = n_steps * args.n_omega * (args.n_vehicles + 1) * 8
    if size > MAX_SWEEP_BYTES:
        raise ConfigError(
            f"--n-omega {args.n_omega} from --omega-min {args.omega_min:g} rad/s with "
            f"--n-vehicles {args.n_vehicles} needs {size / 2**30:.3g} GiB for the sweep (at most "
            f"{MAX_SWEEP_BYTES / 2**30:g}); lower --n-omega or raise --omega-min")


def _fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool | np.bool_):
        return str(bool(value))
    if isinstance(value, float | np.floating):
        return "inf" if math.isinf(value) else ("" if math.isnan(value) else f"{float(value):.6g}")
    return str(value)


def _print_table(rows: list[dict[str, Any]]) -> None:
    cols = SUMMARY_COLUMNS
    table = [[_fmt(r.get(c)) for c in cols] for r in rows]
    widths = [
        max(len(c), *(len(t[i]) for t in table)) if table else len(c) for i, c in enumerate(cols)
    ]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)))
    for t in table:
        print("  ".join(v.ljust(w) for v, w in zip(t, widths)))


def _entries(args: argparse.Namespace) -> list[Entry]:
    """Resolve and build the requested controllers (all names checked before any work)."""
    from analysis.stability import PloegLoop
    from controllers.registry import (
        controller_label,
        make_controller,
        parse_controller_list,
        resolve,
    )

    requested = parse_controller_list(args.controllers)
    for name, _ in requested:
        resolve(name)  # unknown name -> UnknownNameError listing the valid ones
    entries = []
    for name, options in requested:
        opts: dict[str, Any] = dict(options)
        ctrl = make_controller(name, **opts)
        runs_in = getattr(ctrl, "runs_in", None)  # a SUMO or Plexe model (envs.simulators)
        if runs_in is not None:
            raise ConfigError(
                f"{name} is a model of {runs_in} and runs in {runs_in} only, and this command "
                "analyses and sweeps controllers in the built-in simulator; measure its string "
                f"gain in {runs_in}: `cacc-bench run --simulator {runs_in} --controllers {name}` "
                "(the leaderboard's string_gain)")
        linear = resolve(name).family == "linear" and hasattr(
            getattr(ctrl, "config", None), "time_gap_s"
        )
        loop = None
        if linear:
            if "time_gap_s" not in opts:
                opts["time_gap_s"] = args.time_gap
                ctrl = make_controller(name, **opts)
            ctrl.config.check_lag(args.lag)
            loop = PloegLoop.from_controller(ctrl, args.delay, args.lag)
        elif not args.empirical:
            raise ConfigError(f"{name} has no transfer function to analyse (only the linear "
                              "controllers acc and cacc have one); add --empirical to measure its "
                              "string gain in closed loop")
        else:  # measured on sine-v1: a missing policy fails now, before any sweep
            _preflight_empirical(name, opts, ctrl, args)
        entries.append(Entry(name, controller_label(name, options), opts, loop))
    return entries


def _preflight_empirical(name: str, opts: dict[str, Any], ctrl: Any,
                         args: argparse.Namespace) -> None:
    """Load what ``ctrl`` needs for the ``sine-v1`` sweeps with N = ``--n-vehicles``; a policy
    without a sine-v1 checkpoint is refused naming the option that works (a policy trained on
    another scenario, ``NAME:scenario=ID``)."""
    from benchmark.rollout import check_contract
    from controllers.registry import make_controller
    from envs.channel import ChannelConfig
    from envs.params import PlatoonParams as Params
    from envs.scenarios import make_scenario

    sine = make_scenario("sine-v1", amplitude_mps=args.amplitude)
    try:
        ctrl.preflight(sine, args.n_vehicles, Params(lag_s=args.lag))
    except ConfigError as exc:
        if resolve_family(name) != "marl" or "scenario" in opts:
            raise
        from controllers.policy import checkpoint_path

        have = [sc for sc in ("catchup-v1", "slowdown-v1")
                if checkpoint_path(name, sc, args.n_vehicles, int(opts.get("seed", 0))).exists()]
        if not have:
            raise
        raise ConfigError(
            f"{name} has no policy trained on sine-v1 with N = {args.n_vehicles}; measure the "
            f"one trained on {have[0]}: --controllers {name}:scenario={have[0]} (or train one: "
            f"`cacc-bench train --algo {name} --scenario sine-v1 --vehicles {args.n_vehicles}`)"
        ) from exc
    # a controller that breaks the loop's contract (a NaN command, an error in act) is refused
    # now, in one line, not as a traceback in the middle of the sweeps
    check_contract(make_controller(name, **opts), sine, args.n_vehicles, Params(lag_s=args.lag),
                   ChannelConfig(args.delay, 0.0))


def resolve_family(name: str) -> str:
    """The registered family of controller ``name``."""
    from controllers.registry import resolve

    return resolve(name).family


def main(argv: list[str]) -> int:
    """Run the stability analysis; see the module docstring for the outputs."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or an argparse error (2)
        return int(exc.code or 0)
    given = {f for f, v in (("--delay", args.delay), ("--lag", args.lag)) if v is not None}
    args.delay = DEFAULT_DELAY_S if args.delay is None else args.delay
    args.lag = DEFAULT_LAG_S if args.lag is None else args.lag
    _check_args(args)
    entries = _entries(args)
    from benchmark.paths import writable_dir

    out = writable_dir(args.out, create=True)
    omegas_plot = np.geomspace(0.01, 10.0, 300)
    print(setting_line(args, given))

    from analysis import stability_report as report
    from benchmark.folder_lock import folder_lock

    with folder_lock(out):  # one writer per folder, as `run`
        tables = StabilityTables()
        tables.extend(report.analytic(entries, omegas_plot))
        tables.extend(report.design(entries, args.time_gap, args.delay, args.lag, omegas_plot,
                                    out))
        if args.empirical:
            omegas = np.geomspace(args.omega_min, args.omega_max, args.n_omega)
            try:
                tables.extend(report.empirical(
                    entries, omegas, omegas_plot, n_vehicles=args.n_vehicles,
                    amplitude_mps=args.amplitude, delay_s=args.delay, lag_s=args.lag,
                    figures_dir=out))
            except ControllerContractError as exc:  # past the first steps _entries checked
                raise ConfigError(f"{exc} in its frequency sweep; fix the controller (its "
                                  "contract: controllers.base.Controller); no table was "
                                  "written") from None
            except CaccBenchError:
                raise
            except Exception as exc:  # noqa: BLE001 - a user's law failing past its first steps
                raise_if_interrupted()
                own = [e.name for e in entries if is_reference(e.name.removeprefix("safe:"))]
                if not own:
                    raise  # the package's own controllers: a bug to report, with its trace
                raise ConfigError(f"a controller of your own ({', '.join(own)}) failed in its "
                                  f"frequency sweep ({first_line(exc)}); fix it (`cacc-bench "
                                  "run` with it stores each failure's traceback); no table "
                                  "was written") from None
        for name, frame in (("stability_grid.csv", tables.grid),
                            ("stability_h_min.csv", tables.h_min),
                            ("stability_summary.csv", tables.summary_frame()),
                            ("stability.csv", tables.curve_frame())):
            if frame is not None:
                write_csv(frame, out / name, float_format="%.6g")
    _print_table(tables.summary)
    for line in tables.notes:
        print(line)
    print(
        f"wrote {out / 'stability_summary.csv'}, {out / 'stability.csv'} and "
        f"{len(tables.figures)} figure files in {out}"
    )
    return 0
