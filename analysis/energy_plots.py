"""Figure of the energy model: map model, fitted polynomial and their difference."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from envs import energy


def plot_energy_map(
    out_dir: str | Path,
    *,
    polynomial: energy.PowerPolynomial | None = None,
    stem: str = "energy_map",
    speed_step_mps: float = 0.1,
    accel_step_mps2: float = 0.05,
) -> list[Path]:
    """Draw the BMW i3 map model P(v, u), the polynomial fit and their error; write PNG and PDF.

    Three panels over v in [0.5, 30] m/s and u in [-3, 2.5] m/s^2 (the fit grid): the map model's
    battery power, the polynomial's, and polynomial minus map. Points the motor cannot reach
    (motoring beyond its torque or power limit) are hatched and left out of the error panel;
    the dashed line marks the onset of the regeneration limit (friction brakes below it).

    Parameters
    ----------
    out_dir : str or Path
        Output folder (created if missing).
    polynomial : PowerPolynomial, optional
        The polynomial to show; the shipped one when omitted.
    stem : str
        File name without suffix.
    speed_step_mps, accel_step_mps2 : float
        Grid resolution of the contours.

    Returns
    -------
    list of Path
        The PNG and PDF files written.
    """
    from analysis.plots import _plt, save_figure

    plt = _plt()
    poly = energy.load_power_polynomial() if polynomial is None else polynomial

    speeds = np.linspace(0.5, 30.0, int(round(29.5 / speed_step_mps)) + 1)
    accels = np.linspace(-3.0, 2.5, int(round(5.5 / accel_step_mps2)) + 1)
    vg, ug = np.meshgrid(speeds, accels, indexing="xy")  # rows: accel, columns: speed
    op = energy.map_operating_point(vg, ug)
    p_map = op.battery_power_w / 1000.0
    p_poly = np.asarray(poly(vg, ug), dtype=np.float64)
    err = np.where(op.reachable, p_poly - p_map, np.nan)

    finite = np.concatenate([p_map[op.reachable], p_poly[op.reachable]])
    lo, hi = float(np.floor(finite.min() / 10) * 10), float(np.ceil(finite.max() / 10) * 10)
    levels = np.linspace(lo, hi, 2 * int(round((hi - lo) / 10)) + 1)
    emax = max(float(np.ceil(np.nanmax(np.abs(err)))), 1.0)
    elevels = np.linspace(-emax, emax, 2 * int(emax) * (2 if emax <= 5 else 1) + 1)

    fig, axes = plt.subplots(1, 3, figsize=(15.0, 4.6), sharey=True, layout="constrained")
    panels = (
        (p_map, levels, "viridis", "Map model (BMW i3, SUMO MMPEVEM)", "battery power P (kW)"),
        (p_poly, levels, "viridis", "fit: max(5x5 polynomial, floor)", "battery power P (kW)"),
        (err, elevels, "RdBu_r", "Error: fit - map", "error (kW)"),
    )
    unreachable = (~op.reachable).astype(float)
    for ax, (z, lev, cmap, title, clabel) in zip(axes, panels):
        cs = ax.contourf(vg, ug, np.ma.masked_invalid(z), levels=lev, cmap=cmap, extend="both")
        if z is not err:
            ax.contour(vg, ug, z, levels=[0.0], colors="white", linewidths=1.0)
        if unreachable.any():
            ax.contourf(vg, ug, unreachable, levels=[0.5, 1.5], colors="none", hatches=["////"])
        if op.regen_limited.any():
            ax.contour(
                vg,
                ug,
                op.regen_limited.astype(float),
                levels=[0.5],
                colors="k",
                linestyles="--",
                linewidths=0.8,
            )
        cb = fig.colorbar(cs, ax=ax)
        cb.set_label(clabel)
        ax.set_title(title)
        ax.set_xlabel("speed v (m/s)")
    axes[0].set_ylabel("acceleration u (m/s$^2$)")
    quality = poly.metadata.get("quality", {})
    if quality:
        axes[2].text(
            0.02,
            0.02,
            f"R$^2$ = {quality.get('r2', float('nan')):.4f}, "
            f"RMSE = {quality.get('rmse_kw', float('nan')):.2f} kW\n"
            f"v $\\leq$ 20 m/s: R$^2$ = {quality.get('r2_low_speed', float('nan')):.4f}, "
            f"RMSE = {quality.get('rmse_kw_low_speed', float('nan')):.2f} kW",
            transform=axes[2].transAxes,
            fontsize=8,
            va="bottom",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )
    try:
        return save_figure(fig, out_dir, stem)
    finally:
        plt.close(fig)
