"""Figures of a results folder (headless; functions return paths, never call ``show()``).

- per-vehicle time series of gap, speed, acceleration and power of a run (paper Figs. 3 and 5),
  with the published and the controller's own gap target, the start-up transient and a
  collision marked;
- leaderboard comparison: bars with 95 % bootstrap intervals;
- radar chart of inter-vehicle spacing, speed, acceleration and power (paper Fig. 6).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from controllers.base import SpacingPolicy


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


def save_figure(fig: Any, out_dir: str | Path, stem: str, **kwargs: Any) -> list[Path]:
    """Write ``out_dir/stem.png`` and ``out_dir/stem.pdf`` (``savefig`` options ``kwargs``; the
    PNG at 150 dpi unless they give one); return their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{stem}.png", out / f"{stem}.pdf"]
    savefig_atomic(fig, paths[0], **{"dpi": 150, **kwargs})
    savefig_atomic(fig, paths[1], **kwargs)
    return paths


def save_png(fig: Any, path: Path) -> Path:
    """Lay ``fig`` out tight, write it to ``path`` (PNG, 90 dpi) and close it."""
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    savefig_atomic(fig, path, dpi=90)
    _plt().close(fig)
    return path


def _save(fig: Any, out_dir: Path, stem: str) -> list[Path]:
    paths = save_figure(fig, out_dir, stem, dpi=130, bbox_inches="tight")
    _plt().close(fig)
    return paths


#: Label of the scenario's constant target gap (the published reward's ``d*``) in figures.
PUBLISHED_TARGET_LABEL = "published reward target"


def spacing_label(spacing: SpacingPolicy | None, controller: str = "") -> str:
    """How a figure names a controller's own spacing policy (``r + h v``, with its numbers)."""
    if spacing is None:
        return ""
    who = f" ({controller})" if controller else ""
    return f"own policy{who}: {spacing.describe()}"


def transient_rows(arrays: dict[str, np.ndarray]) -> int:
    """Rows ``0 .. k`` of a trajectory that hold the start-up transient
    (:data:`benchmark.metrics.START_TRANSIENT_STEPS` steps after row 0), capped at its length."""
    from benchmark.metrics import START_TRANSIENT_STEPS

    return min(START_TRANSIENT_STEPS, int(np.shape(arrays["gap_m"])[0]) - 1)


def _limits_after(values: np.ndarray, first_row: int) -> tuple[float, float] | None:
    """Axis limits that show rows ``first_row..`` with a margin, or None when those rows already
    hold the whole range (the transient sets no axis)."""
    rest = values[first_row:]
    if not rest.size or not np.isfinite(rest).any():
        return None
    lo, hi = float(np.nanmin(rest)), float(np.nanmax(rest))
    if np.nanmin(values) >= lo and np.nanmax(values) <= hi:
        return None
    pad = max(0.1 * (hi - lo), 0.05)
    return lo - pad, hi + pad


def plot_time_series(
    arrays: dict[str, np.ndarray], title: str, out_dir: Path, stem: str,
    target_gap_m: float | None = None, target_speed_mps: float | None = None,
    spacing: SpacingPolicy | None = None, controller: str = "", collided: bool = False,
) -> list[Path]:
    """Gap, speed, acceleration and power of every vehicle of one run, against time.

    The gap panel draws the scenario's constant target (the published reward's, named so) and,
    for a controller with a spacing policy of its own (``spacing``, e.g. ``cacc``'s ``r + h
    v``), each follower's own target from its speed, dotted in its colour. The start-up
    transient (:func:`transient_rows`) is shaded; where its accelerations or powers lie outside
    the rest of the run (``slowdown-v1``'s speed clip) they are left off the axis and their
    extreme is written on the panel. A collision (``collided``: the run ended at its last row)
    is marked by a red line and a label in every panel, and a cross on the gap that closed.

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
    k = transient_rows(arrays)
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
        values = arrays[key][:t1]
        if key == "speed_mps":
            ax.plot(t, arrays["leader_speed_mps"][:t1], color="black", lw=1.2, label="leader")
        if key == "accel_mps2":
            lead = arrays["leader_accel_mps2"][:t1]
            ax.plot(t, lead, color="black", lw=1.2, label="leader")
            values = np.concatenate([values, lead[:, None]], axis=1)
        for i in range(n):
            ax.plot(t, arrays[key][:, i], color=colors[i], lw=0.9, label=f"follower {i + 1}")
        if key == "gap_m" and spacing is not None:
            own = spacing.target_gap_m(arrays["speed_mps"][:t1])
            for i in range(n):
                ax.plot(t, own[:, i], color=colors[i], lw=0.8, ls=":",
                        label=spacing_label(spacing, controller) if i == 0 else "_own")
        if target is not None:
            name = (f"{PUBLISHED_TARGET_LABEL} {target:g} m" if key == "gap_m"
                    else f"target speed {target:g} m/s")
            ax.axhline(target, color="red", ls="--", lw=0.8, label=name)
        if k > 0:
            ax.axvspan(0.0, k * dt, color="0.85", zorder=0,
                       label="start-up transient (out of jerk_rms_after_start)")
        if key in ("accel_mps2", "power_kw"):
            limits = _limits_after(values, k + 1)
            if limits is not None:
                ax.set_ylim(*limits)
                extreme = values[: k + 1].flat[np.nanargmax(np.abs(values[: k + 1]))]
                unit = "m/s$^2$" if key == "accel_mps2" else "kW"
                ax.text(0.01, 0.04, f"start-up transient off axis: {extreme:.3g} {unit}",
                        transform=ax.transAxes, fontsize=7, color="0.3")
        if collided:
            ax.axvline(t[-1], color="red", lw=1.0, label="collision")
            ax.text(t[-1], 0.5, f" collision at {t[-1]:.1f} s", transform=ax.get_xaxis_transform(),
                    color="red", fontsize=7, ha="right", rotation=90, va="center")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if collided:
        hit = int(np.argmin(arrays["gap_m"][-1]))
        axes[0].plot([t[-1]], [arrays["gap_m"][-1, hit]], marker="X", color="red", ms=9, ls="none",
                     label=f"collision: follower {hit + 1}")
    axes[-1].set_xlabel("time (s)")
    handles: list[Any] = []
    labels: list[str] = []
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels and not lab.startswith("_"):
                handles.append(h)
                labels.append(lab)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    # below the figure: never over a panel or the title, whatever the number of entries
    fig.legend(handles, labels, loc="upper center", ncol=min(4, len(labels)), fontsize=8,
               bbox_to_anchor=(0.5, 0.0))
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
    fig.tight_layout()
    # above the figure (anchored at its top edge from outside, the saved figure grows to hold
    # it): it never covers a panel's title, with one setting as with many
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8,
               bbox_to_anchor=(0.5, 1.0), title="family (bars: means, 95 % bootstrap intervals)",
               title_fontsize=8)
    return _save(fig, out_dir, stem)


#: Fewest controllers a radar is drawn for: each axis is scaled by the largest value among the
#: controllers, so one controller alone is always a full diamond.
RADAR_MIN_CONTROLLERS = 2

RADAR_AXES = (
    ("gap_std_m", "IVS std (m)"),
    ("speed_std_mps", "speed std (m/s)"),
    ("accel_std_mps2", "accel. std (m/s$^2$)"),
    ("power_mean_kw", "mean power (kW)"),
)


def plot_radar(lb: Any, scenario: str, n_vehicles: int, out_dir: Path, stem: str) -> list[Path]:
    """Radar chart of IVS, speed, acceleration (standard deviations) and mean power (Fig. 6).

    Each axis is scaled by the largest value among the controllers (smaller is better: a
    controller close to the centre is smooth and frugal). With fewer than
    :data:`RADAR_MIN_CONTROLLERS` controllers nothing is drawn (an empty list is returned):
    scaled by its own values, one controller is always the full diamond and says nothing.
    """
    plt = _plt()
    sub = lb[(lb["scenario"] == scenario) & (lb["n_vehicles"] == n_vehicles)]
    if sub["controller"].nunique() < RADAR_MIN_CONTROLLERS:
        return []
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
