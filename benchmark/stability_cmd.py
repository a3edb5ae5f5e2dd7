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
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmark.export import write_csv
from envs.errors import ConfigError
from envs.params import PlatoonParams

SUMMARY_COLUMNS = (
    "controller",
    "kind",
    "time_gap_s",
    "delay_s",
    "lag_s",
    "peak_gain",
    "peak_omega_rad_s",
    "h_min_s",
    "string_stable",
)
CURVE_COLUMNS = ("controller", "kind", "time_gap_s", "delay_s", "lag_s", "omega_rad_s", "gain")
#: Delays of the h_min and grid sweeps (s), and the lags of the h_min figure (s).
SWEEP_DELAYS_S = (0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3)
SWEEP_LAGS_S = (0.1, 0.5)


def build_parser() -> argparse.ArgumentParser:
    """Options of ``cacc-bench stability``."""
    p = argparse.ArgumentParser(
        prog="cacc-bench stability",
        description="String stability of platoon controllers: analytic |Gamma(jw)| for the linear "
        "laws (acc, cacc), measured frequency sweeps for any registered controller.",
    )
    p.add_argument(
        "--controllers",
        default="cacc,acc",
        help="comma list, with options as name:key=value (default cacc,acc)",
    )
    p.add_argument(
        "--time-gap", type=float, default=0.5, help="time gap h of the linear laws, s (default 0.5)"
    )
    p.add_argument("--delay", type=float, default=0.2, help="V2V delay theta, s (default 0.2)")
    p.add_argument("--lag", type=float, default=0.1, help="actuator lag tau, s (default 0.1)")
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


def _check_args(args: argparse.Namespace) -> None:
    for flag, value in (
        ("--time-gap", args.time_gap),
        ("--delay", args.delay),
        ("--lag", args.lag),
    ):
        if not math.isfinite(value) or value < 0:
            raise ConfigError(f"{flag} must be a finite number >= 0, got {value}")
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
    if args.n_omega < 1:
        raise ConfigError(f"--n-omega must be >= 1, got {args.n_omega}")
    from envs.scenarios import check_vehicles

    check_vehicles(args.n_vehicles)


def _fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool | np.bool_):
        return str(bool(value))
    if isinstance(value, float | np.floating):
        return "inf" if math.isinf(value) else ("" if math.isnan(value) else f"{float(value):.6g}")
    return str(value)


def _write_csv(path: Path, columns: tuple[str, ...], rows: list[dict[str, Any]]) -> None:
    import pandas as pd

    frame = pd.DataFrame([{c: row.get(c) for c in columns} for row in rows], columns=columns)
    write_csv(frame, path, float_format="%.6g")


def _print_table(rows: list[dict[str, Any]]) -> None:
    cols = SUMMARY_COLUMNS
    table = [[_fmt(r.get(c)) for c in cols] for r in rows]
    widths = [
        max(len(c), *(len(t[i]) for t in table)) if table else len(c) for i, c in enumerate(cols)
    ]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)))
    for t in table:
        print("  ".join(v.ljust(w) for v, w in zip(t, widths)))


@dataclass
class _Entry:
    """One requested controller: registered name, label, options, analytic loop (or None)."""

    name: str
    label: str
    options: dict[str, Any]
    loop: Any  # analysis.stability.PloegLoop or None


def _curve_rows(
    label: str,
    kind: str,
    time_gap_s: float | None,
    delay_s: float,
    lag_s: float,
    omegas: np.ndarray,
    gains: np.ndarray,
) -> list[dict[str, Any]]:
    return [
        {
            "controller": label,
            "kind": kind,
            "time_gap_s": time_gap_s,
            "delay_s": delay_s,
            "lag_s": lag_s,
            "omega_rad_s": w,
            "gain": g,
        }
        for w, g in zip(omegas, gains)
    ]


def _entries(args: argparse.Namespace) -> list[_Entry]:
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
        entries.append(_Entry(name, controller_label(name, options), opts, loop))
    return entries


def _analytic(
    entries: list[_Entry], omegas: np.ndarray
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[str]]:
    """Summary rows, curve rows and discrete-model notes of the linear controllers."""
    from analysis import stability as st

    summary, curves, notes = [], [], []
    for e in entries:
        loop = e.loop
        if loop is None:
            continue
        norm = st.hinf_norm(loop)
        summary.append(
            {
                "controller": e.label,
                "kind": "analytic",
                "time_gap_s": loop.time_gap_s,
                "delay_s": loop.delay_s,
                "lag_s": loop.lag_s,
                "peak_gain": norm.gain,
                "peak_omega_rad_s": norm.omega_rad_s,
                "h_min_s": st.h_min(loop.kp, loop.kd, loop.delay_s, loop.lag_s, loop.feedforward),
                "string_stable": norm.string_stable and st.internally_stable(loop),
            }
        )
        curves += _curve_rows(
            e.label,
            "analytic",
            loop.time_gap_s,
            loop.delay_s,
            loop.lag_s,
            omegas,
            np.abs(st.gamma_response(omegas, loop)),
        )
        dnorm = st.discrete_hinf_norm(loop)
        notes.append(
            f"  {e.label}: discrete-time model of the simulator (dt = {PlatoonParams().dt_s:g} s): "
            f"||Gamma||_inf = {dnorm.gain:.4f} at {dnorm.omega_rad_s:.3f} rad/s "
            f"(continuous {norm.gain:.4f} at {norm.omega_rad_s:.3f} rad/s)"
        )
    return summary, curves, notes


def _design(
    entries: list[_Entry], args: argparse.Namespace, out: Path, omegas: np.ndarray
) -> tuple[list[dict[str, Any]], list[Path], str]:
    """Sweeps over time gaps and delays (grid, h_min) and their figures.

    Returns the extra analytic curve rows (other time gaps), the figure files, a timing line.
    """
    from analysis import stability as st
    from analysis import stability_plots as sp

    delay, lag = args.delay, args.lag
    loops = [e.loop for e in entries if e.loop is not None]
    cacc = next((lp for lp in loops if lp.feedforward), None)
    acc = next((lp for lp in loops if not lp.feedforward), None)
    base = cacc or (acc.replace(feedforward=True) if acc else None)
    base = base or st.PloegLoop(time_gap_s=args.time_gap, delay_s=delay, lag_s=lag)
    if not st.internally_stable(base):
        return [], [], "analytic sweeps skipped: kd <= lag kp, the linear loop is unstable"
    delays = np.array(SWEEP_DELAYS_S)
    t0 = time.perf_counter()
    grid_h = np.linspace(0.1, 3.0, 50)
    grid_gain, grid_omega = st.peak_gain_grid(grid_h, delays, base.kp, base.kd, lag, True)
    h_min_by_lag = {
        tau: np.array([st.h_min(base.kp, base.kd, th, tau, True) for th in delays])
        for tau in sorted({*SWEEP_LAGS_S, lag})
        if base.kd > tau * base.kp
    }
    acc_hmin = st.h_min(base.kp, base.kd, 0.0, lag, False)
    timing = (
        f"analytic sweep ({len(grid_h)} time gaps x {len(delays)} delays, and h_min for "
        f"{len(h_min_by_lag)} lags x {len(delays)} delays): {time.perf_counter() - t0:.2f} s"
    )
    _write_csv(
        out / "stability_grid.csv",
        ("kp", "kd", "time_gap_s", "delay_s", "lag_s", "peak_gain", "peak_omega_rad_s"),
        [
            {
                "kp": base.kp,
                "kd": base.kd,
                "time_gap_s": h,
                "delay_s": th,
                "lag_s": lag,
                "peak_gain": grid_gain[i, j],
                "peak_omega_rad_s": grid_omega[i, j],
            }
            for i, h in enumerate(grid_h)
            for j, th in enumerate(delays)
        ],
    )
    _write_csv(
        out / "stability_h_min.csv",
        ("kp", "kd", "lag_s", "delay_s", "h_min_s"),
        [
            {"kp": base.kp, "kd": base.kd, "lag_s": tau, "delay_s": th, "h_min_s": hs[j]}
            for tau, hs in h_min_by_lag.items()
            for j, th in enumerate(delays)
        ],
    )

    # |Gamma| for several time gaps: a CACC panel and, if acc is requested, an ACC panel
    curves: list[dict[str, Any]] = []
    panels: list[tuple[str, list[sp.GainCurve]]] = []
    label_of = {id(e.loop): e.label for e in entries if e.loop is not None}
    for lp in ([base] if cacc is not None or acc is None else []) + ([acc] if acc else []):
        label = label_of.get(id(lp), "cacc" if lp.feedforward else "acc")
        gaps = (0.2, 0.3, 0.5, 1.0, 1.5) if lp.feedforward else (0.5, 1.0, 2.0, 4.0)
        drawn = []
        for k, h in enumerate(sorted({*gaps, lp.time_gap_s})):
            g = np.abs(st.gamma_response(omegas, lp.replace(time_gap_s=h)))
            drawn.append(sp.GainCurve(f"h = {h:g} s", omegas, g, "analytic", k))
            if id(lp) in label_of and h != lp.time_gap_s:
                curves += _curve_rows(label, "analytic", h, delay, lag, omegas, g)
        hmin = st.h_min(lp.kp, lp.kd, lp.delay_s, lp.lag_s, lp.feedforward)
        if math.isfinite(hmin):
            g = np.abs(st.gamma_response(omegas, lp.replace(time_gap_s=hmin)))
            drawn.append(sp.GainCurve(f"h = h_min = {hmin:.3f} s", omegas, g, "highlight"))
        v2v = f", θ = {delay:g} s" if lp.feedforward else " (no V2V)"
        panels.append((f"{label}: kp = {lp.kp:g}, kd = {lp.kd:g}, τ = {lag:g} s{v2v}", drawn))
    gains = f"kp = {base.kp:g}, kd = {base.kd:g}"
    written = sp.save_figure(sp.plot_gain_panels(panels), out, "gamma_time_gaps")
    written += sp.save_figure(
        sp.plot_h_min(delays, h_min_by_lag, acc_hmin, gains), out, "h_min_delay"
    )
    written += sp.save_figure(
        sp.plot_peak_grid(grid_h, delays, grid_gain, f"CACC, {gains}, τ = {lag:g} s"),
        out,
        "peak_gain_grid",
    )
    return curves, written, timing


def _empirical(
    entries: list[_Entry], args: argparse.Namespace, out: Path, omegas_plot: np.ndarray
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[Path], list[str]]:
    """Measured sweeps of every requested controller; summary rows, curve rows, figure, timings."""
    from analysis import stability as st
    from analysis import stability_plots as sp

    omegas = np.geomspace(args.omega_min, args.omega_max, args.n_omega)
    summary, curves, timings = [], [], []
    drawn: list[sp.GainCurve] = []
    for k, e in enumerate(entries):
        t0 = time.perf_counter()
        res = st.empirical_gain(
            e.name,
            omegas,
            e.options,
            n_vehicles=args.n_vehicles,
            amplitude_mps=args.amplitude,
            delay_s=args.delay,
            lag_s=args.lag,
        )
        timings.append(
            f"empirical sweep of {e.label} ({len(omegas)} frequencies, "
            f"{res.duration_s:.0f} s simulated): {time.perf_counter() - t0:.2f} s"
        )
        bad = res.collided | res.saturated
        if bad.any():
            print(
                f"warning: {e.label}: the sweep left the linear regime at {int(bad.sum())} "
                "frequencies (collision or saturation); lower --amplitude"
            )
        ok = np.isfinite(res.gain)
        i = int(np.nanargmax(res.gain)) if ok.any() else 0
        peak = float(res.gain[i]) if ok.any() else math.nan
        h = e.loop.time_gap_s if e.loop is not None else None
        summary.append(
            {
                "controller": e.label,
                "kind": "empirical",
                "time_gap_s": h,
                "delay_s": args.delay,
                "lag_s": args.lag,
                "peak_gain": peak,
                "peak_omega_rad_s": float(omegas[i]) if ok.any() else math.nan,
                "h_min_s": None,
                "string_stable": bool(ok.any() and peak <= 1.0 + st.STRING_GAIN_TOL),
            }
        )
        curves += _curve_rows(e.label, "empirical", h, args.delay, args.lag, omegas, res.gain)
        if e.loop is not None:
            drawn.append(
                sp.GainCurve(
                    f"{e.label} analytic (continuous)",
                    omegas_plot,
                    np.abs(st.gamma_response(omegas_plot, e.loop)),
                    "analytic",
                    k,
                )
            )
            w_d = omegas_plot[omegas_plot < math.pi / PlatoonParams().dt_s]
            drawn.append(
                sp.GainCurve(
                    f"{e.label} analytic (discrete, dt = {PlatoonParams().dt_s:g} s)",
                    w_d,
                    np.abs(st.discrete_gamma_response(w_d, e.loop)),
                    "discrete",
                    k,
                )
            )
        drawn.append(
            sp.GainCurve(
                f"{e.label} measured (sine-v1, N = {res.n_vehicles})",
                omegas,
                res.gain,
                "empirical",
                k,
            )
        )
    title = (
        f"measured vs analytic, θ = {args.delay:g} s, τ = {args.lag:g} s, "
        f"A = {args.amplitude:g} m/s"
    )
    written = sp.save_figure(sp.plot_gain_panels([(title, drawn)]), out, "gamma_empirical")
    return summary, curves, written, timings


def main(argv: list[str]) -> int:
    """Run the stability analysis; see the module docstring for the outputs."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or an argparse error (2)
        return int(exc.code or 0)
    _check_args(args)
    entries = _entries(args)
    from benchmark.paths import writable_dir

    out = writable_dir(args.out, create=True)
    omegas_plot = np.geomspace(0.01, 10.0, 300)

    summary, curves, notes = _analytic(entries, omegas_plot)
    more_curves, written, timing = _design(entries, args, out, omegas_plot)
    curves += more_curves
    timings = [timing]
    if args.empirical:
        emp_summary, emp_curves, emp_written, emp_timings = _empirical(
            entries, args, out, omegas_plot
        )
        summary += emp_summary
        curves += emp_curves
        written += emp_written
        timings += emp_timings

    _write_csv(out / "stability_summary.csv", SUMMARY_COLUMNS, summary)
    _write_csv(out / "stability.csv", CURVE_COLUMNS, curves)
    _print_table(summary)
    for line in notes + timings:
        print(line)
    print(
        f"wrote {out / 'stability_summary.csv'}, {out / 'stability.csv'} and "
        f"{len(written)} figure files in {out}"
    )
    return 0
