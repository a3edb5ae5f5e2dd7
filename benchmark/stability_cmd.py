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
import csv
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from envs.errors import ConfigError

SUMMARY_COLUMNS = (
    "controller", "kind", "time_gap_s", "delay_s", "lag_s", "peak_gain", "peak_omega_rad_s",
    "h_min_s", "string_stable",
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
    p.add_argument("--controllers", default="cacc,acc",
                   help="comma list, with options as name:key=value (default cacc,acc)")
    p.add_argument("--time-gap", type=float, default=0.5,
                   help="time gap h of the linear laws, s (default 0.5)")
    p.add_argument("--delay", type=float, default=0.2, help="V2V delay theta, s (default 0.2)")
    p.add_argument("--lag", type=float, default=0.1, help="actuator lag tau, s (default 0.1)")
    p.add_argument("--empirical", action="store_true",
                   help="also measure |Gamma(jw)| by sine-v1 frequency sweeps")
    p.add_argument("--n-vehicles", type=int, default=4, help="followers of the sweeps (default 4)")
    p.add_argument("--amplitude", type=float, default=0.1,
                   help="leader speed amplitude of the sweeps, m/s (default 0.1)")
    p.add_argument("--omega-min", type=float, default=0.05, help="lowest frequency, rad/s")
    p.add_argument("--omega-max", type=float, default=3.0, help="highest frequency, rad/s")
    p.add_argument("--n-omega", type=int, default=12, help="frequencies of the sweep (default 12)")
    p.add_argument("--out", default="results/stability", help="output folder")
    return p


def _check_args(args: argparse.Namespace) -> None:
    for flag, value in (("--time-gap", args.time_gap), ("--delay", args.delay), ("--lag", args.lag)):
        if not math.isfinite(value) or value < 0:
            raise ConfigError(f"{flag} must be a finite number >= 0, got {value}")
    for flag, value in (("--amplitude", args.amplitude), ("--omega-min", args.omega_min),
                        ("--omega-max", args.omega_max)):
        if not math.isfinite(value) or value <= 0:
            raise ConfigError(f"{flag} must be > 0, got {value}")
    if args.omega_max < args.omega_min:
        raise ConfigError("--omega-max must be >= --omega-min")
    if args.omega_max >= math.pi / 0.1:
        raise ConfigError(f"--omega-max must lie below the Nyquist frequency {math.pi / 0.1:.4g} rad/s")
    if args.n_omega < 1:
        raise ConfigError(f"--n-omega must be >= 1, got {args.n_omega}")


def _fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool | np.bool_):
        return str(bool(value))
    if isinstance(value, float | np.floating):
        return "inf" if math.isinf(value) else ("" if math.isnan(value) else f"{float(value):.6g}")
    return str(value)


def _write_csv(path: Path, columns: tuple[str, ...], rows: list[dict[str, Any]]) -> None:
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for row in rows:
            writer.writerow([_fmt(row.get(c)) for c in columns])


def _print_table(rows: list[dict[str, Any]]) -> None:
    cols = ("controller", "kind", "time_gap_s", "delay_s", "lag_s", "peak_gain",
            "peak_omega_rad_s", "h_min_s", "string_stable")
    table = [[_fmt(r.get(c)) for c in cols] for r in rows]
    widths = [max(len(c), *(len(t[i]) for t in table)) if table else len(c) for i, c in enumerate(cols)]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)))
    for t in table:
        print("  ".join(v.ljust(w) for v, w in zip(t, widths)))


def main(argv: list[str]) -> int:
    """Run the stability analysis; see the module docstring for the outputs."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or an argparse error (2)
        return int(exc.code or 0)
    _check_args(args)

    from analysis import stability as st
    from analysis import stability_plots as sp
    from controllers.registry import (
        controller_label,
        make_controller,
        parse_controller_list,
        resolve,
    )

    requested = parse_controller_list(args.controllers)
    for name, _ in requested:
        resolve(name)  # unknown name -> UnknownNameError listing the valid ones
    delay, lag = float(args.delay), float(args.lag)

    entries: list[dict[str, Any]] = []
    for name, options in requested:
        spec = resolve(name)
        opts: dict[str, Any] = dict(options)
        ctrl = make_controller(name, **opts)
        linear = spec.family == "linear" and hasattr(getattr(ctrl, "config", None), "time_gap_s")
        if linear and "time_gap_s" not in opts:
            opts["time_gap_s"] = args.time_gap
            ctrl = make_controller(name, **opts)
        loop = None
        if linear:
            ctrl.config.check_lag(lag)
            loop = st.PloegLoop.from_controller(ctrl, delay, lag)
        entries.append({"name": name, "label": controller_label(name, options), "options": opts,
                        "loop": loop})

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary: list[dict[str, Any]] = []
    curves: list[dict[str, Any]] = []
    omega_plot = np.geomspace(0.01, 10.0, 300)

    # ---------------------------------------------------------------- analytic, per controller
    discrete_rows: list[str] = []
    for e in entries:
        loop = e["loop"]
        if loop is None:
            continue
        norm = st.hinf_norm(loop)
        hmin = st.h_min(loop.kp, loop.kd, loop.delay_s, loop.lag_s, loop.feedforward)
        summary.append({
            "controller": e["label"], "kind": "analytic", "time_gap_s": loop.time_gap_s,
            "delay_s": delay, "lag_s": lag, "peak_gain": norm.gain,
            "peak_omega_rad_s": norm.omega_rad_s, "h_min_s": hmin,
            "string_stable": norm.string_stable and st.internally_stable(loop),
        })
        dnorm = st.discrete_hinf_norm(loop)
        discrete_rows.append(
            f"  {e['label']}: discrete-time model of the simulator (dt = 0.1 s): "
            f"||Gamma||_inf = {dnorm.gain:.4f} at {dnorm.omega_rad_s:.3f} rad/s "
            f"(continuous {norm.gain:.4f} at {norm.omega_rad_s:.3f} rad/s)"
        )
        for w, g in zip(omega_plot, np.abs(st.gamma_response(omega_plot, loop))):
            curves.append({"controller": e["label"], "kind": "analytic",
                           "time_gap_s": loop.time_gap_s, "delay_s": delay, "lag_s": lag,
                           "omega_rad_s": w, "gain": g})

    # ---------------------------------------------- analytic sweeps (design figures) and timing
    linear_loops = [e["loop"] for e in entries if e["loop"] is not None]
    cacc_loop = next((lp for lp in linear_loops if lp.feedforward), None)
    acc_loop = next((lp for lp in linear_loops if not lp.feedforward), None)
    base = cacc_loop or (acc_loop.replace(feedforward=True) if acc_loop else None)
    base = base or st.PloegLoop(time_gap_s=args.time_gap, delay_s=delay, lag_s=lag)
    t0 = time.perf_counter()
    grid_h = np.linspace(0.1, 3.0, 50)
    grid_gain, grid_omega = st.peak_gain_grid(grid_h, SWEEP_DELAYS_S, base.kp, base.kd, lag, True)
    lags = sorted({*SWEEP_LAGS_S, lag})
    h_min_by_lag = {
        tau: np.array([st.h_min(base.kp, base.kd, th, tau, True) for th in SWEEP_DELAYS_S])
        for tau in lags if base.kd > tau * base.kp
    }
    acc_hmin = st.h_min(base.kp, base.kd, 0.0, lag, False) if base.kd > lag * base.kp else None
    t_analytic = time.perf_counter() - t0
    _write_csv(
        out / "stability_grid.csv",
        ("kp", "kd", "time_gap_s", "delay_s", "lag_s", "peak_gain", "peak_omega_rad_s"),
        [{"kp": base.kp, "kd": base.kd, "time_gap_s": h, "delay_s": th, "lag_s": lag,
          "peak_gain": grid_gain[i, j], "peak_omega_rad_s": grid_omega[i, j]}
         for i, h in enumerate(grid_h) for j, th in enumerate(SWEEP_DELAYS_S)],
    )
    _write_csv(
        out / "stability_h_min.csv", ("kp", "kd", "lag_s", "delay_s", "h_min_s"),
        [{"kp": base.kp, "kd": base.kd, "lag_s": tau, "delay_s": th, "h_min_s": hs[j]}
         for tau, hs in h_min_by_lag.items() for j, th in enumerate(SWEEP_DELAYS_S)],
    )

    # time-gap figure (CACC panel and, if requested, ACC panel), curves also go to stability.csv
    panels: list[tuple[str, list[sp.GainCurve]]] = []
    panel_loops = ([base] if cacc_loop is not None or acc_loop is None else [])
    panel_loops += [acc_loop] if acc_loop is not None else []
    label_of = {id(e["loop"]): e["label"] for e in entries if e["loop"] is not None}
    for loop_ in panel_loops:
        label = label_of.get(id(loop_), "cacc" if loop_.feedforward else "acc")
        hmin = st.h_min(loop_.kp, loop_.kd, loop_.delay_s, loop_.lag_s, loop_.feedforward)
        gaps = (0.2, 0.3, 0.5, 1.0, 1.5) if loop_.feedforward else (0.5, 1.0, 2.0, 4.0)
        pcurves = []
        for k, h in enumerate(sorted({*gaps, loop_.time_gap_s})):
            g = np.abs(st.gamma_response(omega_plot, loop_.replace(time_gap_s=h)))
            pcurves.append(sp.GainCurve(f"h = {h:g} s", omega_plot, g, "analytic", k))
            if id(loop_) in label_of and h != loop_.time_gap_s:
                curves.extend({"controller": label, "kind": "analytic", "time_gap_s": h,
                               "delay_s": delay, "lag_s": lag, "omega_rad_s": w, "gain": gv}
                              for w, gv in zip(omega_plot, g))
        if math.isfinite(hmin):
            g = np.abs(st.gamma_response(omega_plot, loop_.replace(time_gap_s=hmin)))
            pcurves.append(sp.GainCurve(f"h = h_min = {hmin:.3f} s", omega_plot, g, "highlight"))
        title = (f"{label}: kp = {loop_.kp:g}, kd = {loop_.kd:g}, τ = {lag:g} s"
                 + (f", θ = {delay:g} s" if loop_.feedforward else " (no V2V)"))
        panels.append((title, pcurves))
    written = sp.save_figure(sp.plot_gain_panels(panels), out, "gamma_time_gaps")
    written += sp.save_figure(
        sp.plot_h_min(np.array(SWEEP_DELAYS_S), h_min_by_lag, acc_hmin,
                      f"kp = {base.kp:g}, kd = {base.kd:g}"), out, "h_min_delay")
    written += sp.save_figure(
        sp.plot_peak_grid(grid_h, np.array(SWEEP_DELAYS_S), grid_gain,
                          f"CACC, kp = {base.kp:g}, kd = {base.kd:g}, τ = {lag:g} s"),
        out, "peak_gain_grid")

    # ---------------------------------------------------------------------------- empirical
    timings: list[str] = []
    if args.empirical:
        omegas = np.geomspace(args.omega_min, args.omega_max, args.n_omega)
        emp_curves: list[sp.GainCurve] = []
        for k, e in enumerate(entries):
            t0 = time.perf_counter()
            res = st.empirical_gain(
                e["name"], omegas, e["options"], n_vehicles=args.n_vehicles,
                amplitude_mps=args.amplitude, delay_s=delay, lag_s=lag,
            )
            timings.append(f"empirical sweep of {e['label']} ({len(omegas)} frequencies, "
                           f"{res.duration_s:.0f} s simulated): {time.perf_counter() - t0:.2f} s")
            if res.collided.any() or res.saturated.any():
                print(f"warning: {e['label']}: the sweep left the linear regime at "
                      f"{int((res.collided | res.saturated).sum())} frequencies (collision or "
                      "saturation); lower --amplitude")
            finite = np.isfinite(res.gain)
            i = int(np.nanargmax(res.gain)) if finite.any() else 0
            peak = float(res.gain[i]) if finite.any() else math.nan
            loop = e["loop"]
            summary.append({
                "controller": e["label"], "kind": "empirical",
                "time_gap_s": loop.time_gap_s if loop is not None else None,
                "delay_s": delay, "lag_s": lag, "peak_gain": peak,
                "peak_omega_rad_s": float(omegas[i]) if finite.any() else math.nan,
                "h_min_s": None,
                "string_stable": bool(peak <= 1.0 + st.STRING_GAIN_TOL) if finite.any() else False,
            })
            for w, g in zip(omegas, res.gain):
                curves.append({"controller": e["label"], "kind": "empirical",
                               "time_gap_s": loop.time_gap_s if loop is not None else None,
                               "delay_s": delay, "lag_s": lag, "omega_rad_s": w, "gain": g})
            if loop is not None:
                emp_curves.append(sp.GainCurve(
                    f"{e['label']} analytic (continuous)", omega_plot,
                    np.abs(st.gamma_response(omega_plot, loop)), "analytic", k))
                w_d = omega_plot[omega_plot < math.pi / 0.1]
                emp_curves.append(sp.GainCurve(
                    f"{e['label']} analytic (discrete, dt = 0.1 s)", w_d,
                    np.abs(st.discrete_gamma_response(w_d, loop)), "discrete", k))
            emp_curves.append(sp.GainCurve(f"{e['label']} measured (sine-v1, N = "
                                           f"{res.n_vehicles})", omegas, res.gain, "empirical", k))
        written += sp.save_figure(
            sp.plot_gain_panels([(f"measured vs analytic, θ = {delay:g} s, τ = {lag:g} s, "
                                  f"A = {args.amplitude:g} m/s", emp_curves)]),
            out, "gamma_empirical")

    _write_csv(out / "stability_summary.csv", SUMMARY_COLUMNS, summary)
    _write_csv(out / "stability.csv", CURVE_COLUMNS, curves)
    _print_table(summary)
    for line in discrete_rows:
        print(line)
    print(f"analytic sweep ({len(grid_h)} time gaps x {len(SWEEP_DELAYS_S)} delays, and h_min for "
          f"{len(h_min_by_lag)} lags x {len(SWEEP_DELAYS_S)} delays): {t_analytic:.2f} s")
    for line in timings:
        print(line)
    print(f"wrote {out / 'stability_summary.csv'}, {out / 'stability.csv'} and "
          f"{len(written)} figure files in {out}")
    return 0
