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


def _save(fig: Any, out_dir: Path, stem: str) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for ext in ("png", "pdf"):
        p = out_dir / f"{stem}.{ext}"
        fig.savefig(p, dpi=130, bbox_inches="tight")
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


def plot_leaderboard(lb: Any, out_dir: Path, stem: str = "leaderboard") -> list[Path]:
    """Bars of the main metrics per controller and scenario, with 95 % bootstrap intervals."""
    plt = _plt()
    lb = lb.copy()
    lb["setting"] = lb["scenario"] + " N=" + lb["n_vehicles"].astype(str)
    settings = list(dict.fromkeys(lb["setting"]))
    controllers = list(dict.fromkeys(lb["controller"]))
    metrics = [(m, lab) for m, lab in BAR_METRICS if f"{m}_mean" in lb.columns]
    fig, axes = plt.subplots(len(metrics), 1, figsize=(max(6, 1.6 * len(settings) * max(1, len(controllers)) / 2), 2.4 * len(metrics)))
    axes = np.atleast_1d(axes)
    width = 0.8 / max(len(controllers), 1)
    cmap = plt.get_cmap("tab10")
    x = np.arange(len(settings))
    for ax, (metric, label) in zip(axes, metrics, strict=True):
        for j, ctrl in enumerate(controllers):
            sub = lb[lb["controller"] == ctrl].set_index("setting")
            mean = np.array([sub[f"{metric}_mean"].get(s, np.nan) for s in settings], dtype=float)
            lo = np.array([sub[f"{metric}_ci_low"].get(s, np.nan) for s in settings], dtype=float)
            hi = np.array([sub[f"{metric}_ci_high"].get(s, np.nan) for s in settings], dtype=float)
            err = np.vstack([mean - lo, hi - mean])
            ax.bar(x + (j - (len(controllers) - 1) / 2) * width, mean, width, yerr=err,
                   capsize=2, color=cmap(j % 10), label=ctrl)
        ax.set_ylabel(label, fontsize=8)
        ax.set_xticks(x)
        ax.set_xticklabels(settings, fontsize=8)
        ax.grid(axis="y", alpha=0.3)
        if metric == "string_gain":
            ax.axhline(1.0, color="red", ls="--", lw=0.8)
    axes[0].legend(fontsize=8, ncol=min(4, len(controllers)), loc="best")
    axes[0].set_title("leaderboard: means with 95 % bootstrap intervals over episodes")
    fig.tight_layout()
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
    cmap = plt.get_cmap("tab10")
    for j, (_, r) in enumerate(sub.iterrows()):
        v = np.abs(vals[j]) / scale
        ax.plot(np.append(angles, angles[0]), np.append(v, v[0]), color=cmap(j % 10),
                label=str(r["controller"]))
        ax.fill(np.append(angles, angles[0]), np.append(v, v[0]), color=cmap(j % 10), alpha=0.1)
    ax.set_xticks(angles)
    ax.set_xticklabels([f"{lab}\nmax {s:.3g}" for lab, s in zip(labels, scale, strict=True)],
                       fontsize=8)
    ax.set_yticklabels([])
    ax.tick_params(axis="x", pad=14)
    ax.set_title(f"{scenario}, N={n_vehicles} (each axis / its max; centre is best)", fontsize=10)
    ax.legend(loc="upper right", bbox_to_anchor=(1.35, 1.1), fontsize=8)
    return _save(fig, out_dir, stem)
