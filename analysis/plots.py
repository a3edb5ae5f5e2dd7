"""Figures of a results folder (headless; functions return paths, never call ``show()``).

- per-vehicle time series of gap, speed, acceleration and power for one run per controller
  (paper Figs. 3 and 5);
- leaderboard comparison: bars with 95 % bootstrap intervals;
- radar chart of inter-vehicle spacing, speed, acceleration and power (paper Fig. 6).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def savefig_atomic(fig: Any, path: Path, **kwargs: Any) -> Path:
    """``fig.savefig(path)`` through a temporary file renamed over ``path``: an interrupted
    write leaves the earlier figure as it was (:func:`infra.atomic.write_with`)."""
    from infra.atomic import write_with

    return write_with(path, lambda tmp: fig.savefig(tmp, format=path.suffix[1:], **kwargs))


def _save(fig: Any, out_dir: Path, stem: str) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for ext in ("png", "pdf"):
        p = out_dir / f"{stem}.{ext}"
        savefig_atomic(fig, p, dpi=130, bbox_inches="tight")
        paths.append(p)
    _plt().close(fig)
    return paths


def plot_time_series(
    arrays: dict[str, np.ndarray], title: str, out_dir: Path, stem: str,
    target_gap_m: float | None = None, target_speed_mps: float | None = None,
) -> list[Path]:
    """Gap, speed, acceleration and power of every vehicle of one run, against time.

    Parameters
    ----------
    arrays : dict
        ``gap_m, speed_mps, accel_mps2, power_kw`` (T+1, N), ``leader_speed_mps``,
        ``leader_accel_mps2`` (T+1,), ``dt_s``.
    """
    plt = _plt()
    dt = float(arrays["dt_s"])
    t1, n = arrays["gap_m"].shape
    t = np.arange(t1) * dt
    fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    cmap = plt.get_cmap("viridis")
    colors = [cmap(i / max(n - 1, 1)) for i in range(n)]
    panels = [
        ("gap_m", "gap (m)", target_gap_m),
        ("speed_mps", "speed (m/s)", target_speed_mps),
        ("accel_mps2", "acceleration (m/s$^2$)", None),
        ("power_kw", "battery power (kW)", None),
    ]
    for ax, (key, label, target) in zip(axes, panels, strict=True):
        if key == "speed_mps":
            ax.plot(t, arrays["leader_speed_mps"][:t1], color="black", lw=1.2, label="leader")
        if key == "accel_mps2":
            ax.plot(t, arrays["leader_accel_mps2"][:t1], color="black", lw=1.2, label="leader")
        for i in range(n):
            ax.plot(t, arrays[key][:, i], color=colors[i], lw=0.9, label=f"follower {i + 1}")
        if target is not None:
            ax.axhline(target, color="red", ls="--", lw=0.8, label="target")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time (s)")
    handles, labels = axes[1].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=min(6, len(labels)), fontsize=8,
               bbox_to_anchor=(0.5, 1.0))
    fig.suptitle(title, y=1.03, fontsize=11)
    return _save(fig, out_dir, stem)


BAR_METRICS = (
    ("reward", "reward (mean over steps,\nsum over agents)"),
    ("energy_kwh", "platoon energy (kWh)"),
    ("gap_rmse_m", "gap RMSE (m)"),
    ("speed_rmse_mps", "speed RMSE (m/s)"),
    ("jerk_rms_mps3", "jerk RMS (m/s$^3$)"),
    ("string_gain", "time-domain string gain"),
)


#: Bar colour of each controller family (a legend shows only the families drawn).
FAMILY_COLOURS: dict[str, str] = {"human": "tab:grey", "linear": "tab:blue", "mpc": "tab:green",
                                  "marl": "tab:orange", "data": "tab:purple"}
#: Panels per row of the leaderboard figure before it wraps.
FACET_COLUMNS = 3


def _setting_names(lb: Any) -> Any:
    names = lb["scenario"] + " N=" + lb["n_vehicles"].astype(str)
    for col, unit in (("comm_delay_s", "s delay"), ("packet_loss", " loss"), ("lag_s", "s lag")):
        if col in lb.columns and (lb[col] != 0).any():
            names = names + np.where(lb[col] != 0, ", " + lb[col].astype(str) + unit, "")
    return names


def plot_leaderboard(lb: Any, out_dir: Path, stem: str = "leaderboard") -> list[Path]:
    """Horizontal bars of the main metrics, one panel per metric and setting (wrapped into rows
    of :data:`FACET_COLUMNS`), controllers named on each panel's axis in rank order, coloured by
    family, with 95 % bootstrap intervals: readable with 20 controllers or more."""
    import math

    plt = _plt()
    lb = lb.copy()
    lb["setting"] = _setting_names(lb)
    settings = list(dict.fromkeys(lb["setting"]))
    metrics = [(m, lab) for m, lab in BAR_METRICS if f"{m}_mean" in lb.columns]
    panels = [(m, lab, st) for m, lab in metrics for st in settings]
    ncols = min(len(settings), FACET_COLUMNS)
    nrows = math.ceil(len(panels) / ncols)
    most = max(int((lb["setting"] == st).sum()) for st in settings)
    fig, axes = plt.subplots(nrows, ncols, squeeze=False,
                             figsize=(4.6 * ncols, (0.7 + 0.2 * most) * nrows))
    families: set[str] = set()
    for ax, (metric, label, setting) in zip(axes.ravel(), panels, strict=False):
        sub = lb[lb["setting"] == setting]
        if "rank" in sub.columns:
            sub = sub.sort_values("rank", kind="mergesort")
        mean = sub[f"{metric}_mean"].to_numpy(dtype=float)
        err = np.abs(np.vstack([mean - sub[f"{metric}_ci_low"].to_numpy(dtype=float),
                                sub[f"{metric}_ci_high"].to_numpy(dtype=float) - mean]))
        fams = sub["family"].tolist() if "family" in sub.columns else ["other"] * len(sub)
        families.update(fams)
        y = np.arange(len(sub))[::-1]
        ax.barh(y, mean, xerr=err, capsize=2, height=0.7,
                color=[FAMILY_COLOURS.get(f, "tab:brown") for f in fams])
        ax.set_yticks(y, [str(c) for c in sub["controller"]], fontsize=7)
        ax.set_title(f"{label}, {setting}", fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
        ax.grid(axis="x", alpha=0.3)
        if metric == "string_gain":
            ax.axvline(1.0, color="red", ls="--", lw=0.8)
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    from matplotlib.patches import Patch

    handles = [Patch(color=FAMILY_COLOURS.get(f, "tab:brown"), label=f) for f in sorted(families)]
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=8,
               bbox_to_anchor=(0.5, 1.0), title="family (bars: means, 95 % bootstrap intervals)",
               title_fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    return _save(fig, out_dir, stem)


RADAR_AXES = (
    ("gap_std_m", "IVS std (m)"),
    ("speed_std_mps", "speed std (m/s)"),
    ("accel_std_mps2", "accel. std (m/s$^2$)"),
    ("power_mean_kw", "mean power (kW)"),
)


def plot_radar(lb: Any, scenario: str, n_vehicles: int, out_dir: Path, stem: str) -> list[Path]:
    """Radar chart of IVS, speed, acceleration (standard deviations) and mean power (Fig. 6).

    Each axis is scaled by the largest value among the controllers (smaller is better: a
    controller close to the centre is smooth and frugal).
    """
    plt = _plt()
    sub = lb[(lb["scenario"] == scenario) & (lb["n_vehicles"] == n_vehicles)]
    labels = [lab for _, lab in RADAR_AXES]
    vals = np.array([[float(r[f"{m}_mean"]) for m, _ in RADAR_AXES] for _, r in sub.iterrows()])
    scale = np.nanmax(np.abs(vals), axis=0)
    scale[~np.isfinite(scale) | (scale == 0)] = 1.0
    angles = np.linspace(0, 2 * np.pi, len(labels), endpoint=False)
    fig = plt.figure(figsize=(5.5, 5.5))
    ax = fig.add_subplot(111, polar=True)
    cmap = plt.get_cmap("tab10" if len(sub) <= 10 else "tab20")
    for j, (_, r) in enumerate(sub.iterrows()):
        v = np.abs(vals[j]) / scale
        colour = cmap(j % cmap.N)
        ax.plot(np.append(angles, angles[0]), np.append(v, v[0]), color=colour,
                label=str(r["controller"]), ls="-" if j < cmap.N else "--")
        ax.fill(np.append(angles, angles[0]), np.append(v, v[0]), color=colour, alpha=0.1)
    ax.set_xticks(angles)
    ax.set_xticklabels([f"{lab}\nmax {s:.3g}" for lab, s in zip(labels, scale, strict=True)],
                       fontsize=8)
    ax.set_yticklabels([])
    ax.tick_params(axis="x", pad=14)
    ax.set_title(f"{scenario}, N={n_vehicles} (each axis / its max; centre is best)", fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.15, 1.1), fontsize=7,
              ncol=1 if len(sub) <= 12 else 2)
    return _save(fig, out_dir, stem)
