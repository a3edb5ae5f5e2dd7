"""The tables and figures of ``cacc-bench stability``, as data frames: analytic ``|Gamma(jw)|``
of the linear laws, design sweeps over time gaps and delays, and measured frequency sweeps of
any registered controller. The command only parses, calls these and writes what they return.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from benchmark.string_gain import is_string_stable
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
GRID_COLUMNS = ("kp", "kd", "time_gap_s", "delay_s", "lag_s", "peak_gain", "peak_omega_rad_s")
H_MIN_COLUMNS = ("kp", "kd", "lag_s", "delay_s", "h_min_s")
#: Delays of the h_min and grid sweeps (s), and the lags of the h_min figure (s).
SWEEP_DELAYS_S = (0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3)
SWEEP_LAGS_S = (0.1, 0.5)
#: Time gaps of the design grid (s).
GRID_TIME_GAPS_S = tuple(np.linspace(0.1, 3.0, 50))


@dataclass
class Entry:
    """One requested controller: registered name, label, options, analytic loop (or None)."""

    name: str
    label: str
    options: dict[str, Any]
    loop: Any  # analysis.stability.PloegLoop or None


@dataclass
class StabilityTables:
    """What one part of the analysis produced: summary and curve rows, figure files, notes."""

    summary: list[dict[str, Any]] = field(default_factory=list)
    curves: list[dict[str, Any]] = field(default_factory=list)
    figures: list[Path] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    grid: pd.DataFrame | None = None
    h_min: pd.DataFrame | None = None

    def extend(self, other: StabilityTables) -> None:
        """Append another part's rows, figures and notes (its grid and h_min win if set)."""
        self.summary += other.summary
        self.curves += other.curves
        self.figures += other.figures
        self.notes += other.notes
        self.grid = other.grid if other.grid is not None else self.grid
        self.h_min = other.h_min if other.h_min is not None else self.h_min

    def summary_frame(self) -> pd.DataFrame:
        """The summary rows in :data:`SUMMARY_COLUMNS` order."""
        return _frame(self.summary, SUMMARY_COLUMNS)

    def curve_frame(self) -> pd.DataFrame:
        """The curve rows in :data:`CURVE_COLUMNS` order."""
        return _frame(self.curves, CURVE_COLUMNS)


def _frame(rows: list[dict[str, Any]], columns: tuple[str, ...]) -> pd.DataFrame:
    return pd.DataFrame([{c: row.get(c) for c in columns} for row in rows], columns=columns)


def _curve_rows(label: str, kind: str, time_gap_s: float | None, delay_s: float, lag_s: float,
                omegas: np.ndarray, gains: np.ndarray) -> list[dict[str, Any]]:
    return [{"controller": label, "kind": kind, "time_gap_s": time_gap_s, "delay_s": delay_s,
             "lag_s": lag_s, "omega_rad_s": w, "gain": g} for w, g in zip(omegas, gains)]


def analytic(entries: list[Entry], omegas: np.ndarray) -> StabilityTables:
    """``||Gamma||_inf``, ``h_min`` and ``|Gamma(jw)|`` of the entries with a linear loop, and a
    note comparing the continuous norm with the simulator's discrete-time model."""
    from analysis import stability as st

    out = StabilityTables()
    dt_s = PlatoonParams().dt_s
    for e in entries:
        loop = e.loop
        if loop is None:
            continue
        norm = st.hinf_norm(loop)
        out.summary.append({
            "controller": e.label, "kind": "analytic", "time_gap_s": loop.time_gap_s,
            "delay_s": loop.delay_s, "lag_s": loop.lag_s, "peak_gain": norm.gain,
            "peak_omega_rad_s": norm.omega_rad_s,
            "h_min_s": st.h_min(loop.kp, loop.kd, loop.delay_s, loop.lag_s, loop.feedforward),
            "string_stable": norm.string_stable and st.internally_stable(loop),
        })
        out.curves += _curve_rows(e.label, "analytic", loop.time_gap_s, loop.delay_s,
                                  loop.lag_s, omegas, np.abs(st.gamma_response(omegas, loop)))
        dnorm = st.discrete_hinf_norm(loop)
        out.notes.append(
            f"  {e.label}: discrete-time model of the simulator (dt = {dt_s:g} s): "
            f"||Gamma||_inf = {dnorm.gain:.4f} at {dnorm.omega_rad_s:.3f} rad/s "
            f"(continuous {norm.gain:.4f} at {norm.omega_rad_s:.3f} rad/s)"
        )
    return out


def design(entries: list[Entry], time_gap_s: float, delay_s: float, lag_s: float,
           omegas: np.ndarray, figures_dir: Path) -> StabilityTables:
    """Sweeps over time gaps and delays: the peak-gain grid, ``h_min`` against the delay, the
    requested laws' ``|Gamma|`` at other time gaps, and their figures (into ``figures_dir``)."""
    from analysis import stability as st
    from analysis import stability_plots as sp
    from analysis.plots import save_figure

    out = StabilityTables()
    loops = [e.loop for e in entries if e.loop is not None]
    cacc = next((lp for lp in loops if lp.feedforward), None)
    acc = next((lp for lp in loops if not lp.feedforward), None)
    base = cacc or (acc.replace(feedforward=True) if acc else None)
    base = base or st.PloegLoop(time_gap_s=time_gap_s, delay_s=delay_s, lag_s=lag_s)
    if not st.internally_stable(base):
        out.notes.append("analytic sweeps skipped: kd <= lag kp, the linear loop is unstable")
        return out
    delays = np.array(SWEEP_DELAYS_S)
    t0 = time.perf_counter()
    grid_h = np.array(GRID_TIME_GAPS_S)
    grid_gain, grid_omega = st.peak_gain_grid(grid_h, delays, base.kp, base.kd, lag_s, True)
    h_min_by_lag = {
        tau: np.array([st.h_min(base.kp, base.kd, th, tau, True) for th in delays])
        for tau in sorted({*SWEEP_LAGS_S, lag_s})
        if base.kd > tau * base.kp
    }
    acc_hmin = st.h_min(base.kp, base.kd, 0.0, lag_s, False)
    out.notes.append(
        f"analytic sweep ({len(grid_h)} time gaps x {len(delays)} delays, and h_min for "
        f"{len(h_min_by_lag)} lags x {len(delays)} delays): {time.perf_counter() - t0:.2f} s"
    )
    out.grid = _frame([
        {"kp": base.kp, "kd": base.kd, "time_gap_s": h, "delay_s": th, "lag_s": lag_s,
         "peak_gain": grid_gain[i, j], "peak_omega_rad_s": grid_omega[i, j]}
        for i, h in enumerate(grid_h) for j, th in enumerate(delays)
    ], GRID_COLUMNS)
    out.h_min = _frame([
        {"kp": base.kp, "kd": base.kd, "lag_s": tau, "delay_s": th, "h_min_s": hs[j]}
        for tau, hs in h_min_by_lag.items() for j, th in enumerate(delays)
    ], H_MIN_COLUMNS)

    # |Gamma| for several time gaps: a CACC panel and, if acc is requested, an ACC panel
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
                out.curves += _curve_rows(label, "analytic", h, delay_s, lag_s, omegas, g)
        hmin = st.h_min(lp.kp, lp.kd, lp.delay_s, lp.lag_s, lp.feedforward)
        if math.isfinite(hmin):
            g = np.abs(st.gamma_response(omegas, lp.replace(time_gap_s=hmin)))
            drawn.append(sp.GainCurve(f"h = h_min = {hmin:.3f} s", omegas, g, "highlight"))
        v2v = f", θ = {delay_s:g} s" if lp.feedforward else " (no V2V)"
        panels.append((f"{label}: kp = {lp.kp:g}, kd = {lp.kd:g}, τ = {lag_s:g} s{v2v}", drawn))
    gains = f"kp = {base.kp:g}, kd = {base.kd:g}"
    out.figures += save_figure(sp.plot_gain_panels(panels), figures_dir, "gamma_time_gaps")
    out.figures += save_figure(
        sp.plot_h_min(delays, h_min_by_lag, acc_hmin, gains), figures_dir, "h_min_delay")
    out.figures += save_figure(
        sp.plot_peak_grid(grid_h, delays, grid_gain, f"CACC, {gains}, τ = {lag_s:g} s"),
        figures_dir, "peak_gain_grid")
    return out


def empirical(entries: list[Entry], omegas: np.ndarray, omegas_plot: np.ndarray, *,
              n_vehicles: int, amplitude_mps: float, delay_s: float, lag_s: float,
              figures_dir: Path) -> StabilityTables:
    """Measured sweeps (``sine-v1`` episodes through the harness's loop) of every entry, with
    the analytic curves of the linear ones beside them in one figure. A note warns of any
    frequency where the sweep left the linear regime (collision or saturation)."""
    from analysis import stability as st
    from analysis import stability_plots as sp
    from analysis.plots import save_figure

    out = StabilityTables()
    dt_s = PlatoonParams().dt_s
    drawn: list[sp.GainCurve] = []
    for k, e in enumerate(entries):
        t0 = time.perf_counter()
        res = st.empirical_gain(e.name, omegas, e.options, n_vehicles=n_vehicles,
                                amplitude_mps=amplitude_mps, delay_s=delay_s, lag_s=lag_s)
        out.notes.append(
            f"empirical sweep of {e.label} ({len(omegas)} frequencies, "
            f"{res.duration_s:.0f} s simulated): {time.perf_counter() - t0:.2f} s"
        )
        bad = res.collided | res.saturated
        if bad.any():
            out.notes.append(
                f"warning: {e.label}: the sweep left the linear regime at {int(bad.sum())} "
                "frequencies (collision or saturation); lower --amplitude"
            )
        ok = np.isfinite(res.gain)
        i = int(np.nanargmax(res.gain)) if ok.any() else 0
        peak = float(res.gain[i]) if ok.any() else math.nan
        h = e.loop.time_gap_s if e.loop is not None else None
        out.summary.append({
            "controller": e.label, "kind": "empirical", "time_gap_s": h, "delay_s": delay_s,
            "lag_s": lag_s, "peak_gain": peak,
            "peak_omega_rad_s": float(omegas[i]) if ok.any() else math.nan, "h_min_s": None,
            "string_stable": is_string_stable(peak),
        })
        out.curves += _curve_rows(e.label, "empirical", h, delay_s, lag_s, omegas, res.gain)
        if e.loop is not None:
            drawn.append(sp.GainCurve(f"{e.label} analytic (continuous)", omegas_plot,
                                      np.abs(st.gamma_response(omegas_plot, e.loop)),
                                      "analytic", k))
            w_d = omegas_plot[omegas_plot < math.pi / dt_s]
            drawn.append(sp.GainCurve(f"{e.label} analytic (discrete, dt = {dt_s:g} s)", w_d,
                                      np.abs(st.discrete_gamma_response(w_d, e.loop)),
                                      "discrete", k))
        drawn.append(sp.GainCurve(f"{e.label} measured (sine-v1, N = {res.n_vehicles})", omegas,
                                  res.gain, "empirical", k))
    title = f"measured vs analytic, θ = {delay_s:g} s, τ = {lag_s:g} s, A = {amplitude_mps:g} m/s"
    out.figures += save_figure(sp.plot_gain_panels([(title, drawn)]), figures_dir,
                                  "gamma_empirical")
    return out
