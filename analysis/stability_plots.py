"""Figures of the string-stability analysis (headless: matplotlib ``Figure`` objects, never shown).

Every function takes computed data and returns a :class:`matplotlib.figure.Figure`;
:func:`analysis.plots.save_figure` writes it as PNG and PDF. Nothing here touches pyplot's global
state.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

_COLORS = (
    "tab:blue",
    "tab:orange",
    "tab:green",
    "tab:red",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:gray",
    "tab:olive",
    "tab:cyan",
)


@dataclass(frozen=True)
class GainCurve:
    """One magnitude curve ``|Gamma(jw)|`` to draw.

    Attributes
    ----------
    label : str
        Legend text.
    omegas_rad_s, gains : (W,)
        Frequencies and magnitudes.
    style : {"analytic", "discrete", "empirical", "highlight"}
        Solid line, dashed line, markers only, thick black dashed line.
    group : int
        Curves of one group share a colour (e.g. one controller's analytic and empirical).
    """

    label: str
    omegas_rad_s: np.ndarray
    gains: np.ndarray
    style: str = "analytic"
    group: int = 0


def _draw(ax: Axes, curve: GainCurve) -> bool:
    """Draw one curve (its finite points); False if it has none."""
    w = np.asarray(curve.omegas_rad_s, dtype=np.float64)
    g = np.asarray(curve.gains, dtype=np.float64)
    ok = np.isfinite(w) & np.isfinite(g) & (w > 0)
    if not ok.any():
        return False
    curve = GainCurve(curve.label, w[ok], g[ok], curve.style, curve.group)
    color = _COLORS[curve.group % len(_COLORS)]
    if curve.style == "empirical":
        ax.plot(curve.omegas_rad_s, curve.gains, "o-", color=color, ms=5, lw=0.7, label=curve.label)
    elif curve.style == "discrete":
        ax.plot(curve.omegas_rad_s, curve.gains, "--", color=color, lw=1.2, label=curve.label)
    elif curve.style == "highlight":
        ax.plot(curve.omegas_rad_s, curve.gains, "--", color="black", lw=2.2, label=curve.label)
    else:
        ax.plot(curve.omegas_rad_s, curve.gains, "-", color=color, lw=1.5, label=curve.label)
    return True


def _gain_axes(ax: Axes, title: str) -> None:
    ax.axhline(1.0, color="red", lw=1.0, ls=":", label="bound |Γ| = 1")
    ax.set_xscale("log")
    ax.set_xlabel("frequency ω (rad/s)")
    ax.set_ylabel("|Γ(jω)| (acceleration ratio, –)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best")


def plot_gain_panels(panels: Sequence[tuple[str, Sequence[GainCurve]]]) -> Figure:
    """Magnitude curves, one panel per (title, curves), each with the bound 1 drawn."""
    n = max(1, len(panels))
    fig = Figure(figsize=(6.0 * n, 4.5), layout="constrained")
    axes = fig.subplots(1, n, squeeze=False)[0]
    for ax, (title, curves) in zip(axes, panels):
        drawn = [_draw(ax, curve) for curve in curves]
        if not any(drawn):  # nothing finite (e.g. every sweep collided): keep a sane log axis
            ax.set_xlim(1e-2, 1e1)
            ax.text(0.5, 0.5, "no finite data", transform=ax.transAxes, ha="center")
        _gain_axes(ax, title)
    return fig


def plot_h_min(
    delays_s: np.ndarray,
    h_min_by_lag: Mapping[float, np.ndarray],
    acc_h_min_s: float | None = None,
    title: str = "",
) -> Figure:
    """Smallest string-stable time gap against the V2V delay, one line per actuator lag."""
    fig = Figure(figsize=(6.0, 4.5), layout="constrained")
    ax = fig.subplots()
    for k, (lag, hs) in enumerate(sorted(h_min_by_lag.items())):
        ax.plot(delays_s, hs, "o-", color=_COLORS[k % len(_COLORS)], label=f"CACC, τ = {lag:g} s")
    if acc_h_min_s is not None:
        ax.axhline(
            acc_h_min_s,
            color="black",
            ls="--",
            lw=1.2,
            label=f"ACC (any τ, θ): √(2/kp) = {acc_h_min_s:.3f} s",
        )
    ax.set_xlabel("V2V delay θ (s)")
    ax.set_ylabel("smallest string-stable time gap h_min (s)")
    ax.set_title(title, fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    return fig


def plot_peak_grid(
    time_gaps_s: np.ndarray, delays_s: np.ndarray, peak_gain: np.ndarray, title: str = ""
) -> Figure:
    """``||Gamma||_inf`` against the time gap, one line per delay (``peak_gain`` is (n_h, n_theta))."""
    fig = Figure(figsize=(6.0, 4.5), layout="constrained")
    ax = fig.subplots()
    for j, th in enumerate(delays_s):
        ax.plot(
            time_gaps_s,
            peak_gain[:, j],
            "-",
            color=_COLORS[j % len(_COLORS)],
            label=f"θ = {th:g} s",
        )
    ax.axhline(1.0, color="red", lw=1.0, ls=":", label="bound 1")
    ax.set_xlabel("time gap h (s)")
    ax.set_ylabel("‖Γ‖∞ (–)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best", ncol=2)
    return fig
