"""The figures a platoon paper shows first (headless; functions return paths, never ``show()``).

- :func:`plot_time_space`: the time-space (x-t) diagram of one run, every vehicle's position
  against time, coloured by its speed, and each follower's distance behind the leader;
- :func:`plot_per_vehicle`: peak spacing error and acceleration norm against the vehicle's index
  (the per-vehicle string-stability figure), one line per controller and seed;
- :func:`plot_gain_frequency`: a string gain against the leader's frequency, from sweep data.

Positions come from the stored gaps and leader speed (:func:`benchmark.export.positions_m`,
the ``position_m`` column of a trajectory CSV).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from analysis import plots

if TYPE_CHECKING:
    from controllers.base import SpacingPolicy


#: Most rows a vehicle's line of the time-space diagram draws (evenly spaced, the last kept).
MAX_POINTS = 1000
#: Most followers named one by one in a time-space diagram's legend.
LEGEND_MAX_FOLLOWERS = 10


def _ring_breaks(x: np.ndarray, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``x`` folded onto ``[0, length_m)``, and the indices where it wraps (a line is broken
    there, not drawn across the diagram)."""
    folded = np.mod(x, length_m)
    return folded, np.flatnonzero(np.abs(np.diff(folded)) > length_m / 2) + 1


def plot_time_space(
    arrays: dict[str, np.ndarray], title: str, out_dir: Path, stem: str, *,
    ring_length_m: float | None = None, collided: bool = False,
) -> list[Path]:
    """Time-space diagram of one run.

    Top: position along the road against time, each follower's line coloured by its speed
    (the leader black; on a ring, positions folded onto the ring, with no leader). Bottom: each
    follower's distance behind the leader (the sum of the gaps ahead of it), where spacing
    waves show. A collision is marked with a red cross at the follower whose gap closed.

    Parameters
    ----------
    arrays : dict
        As :func:`benchmark.export.trajectory_arrays` (``ring`` read for a ring road).
    ring_length_m : float or None
        The ring's length (m) for a ring-road run; None for an open road.
    collided : bool
        Whether the run ended in a collision (at its last row).
    """
    from matplotlib.collections import LineCollection

    from benchmark.export import positions_m

    plt = plots._plt()
    ring = ring_length_m is not None
    x = positions_m(arrays, ring=ring)
    speed = np.asarray(arrays["speed_mps"])
    t1, n = speed.shape
    t = np.arange(t1) * float(arrays["dt_s"])
    fig, (ax, ax_rel) = plt.subplots(2, 1, figsize=(8, 8), sharex=True, layout="constrained",
                                     gridspec_kw={"height_ratios": (2, 1)})
    lo = float(min(speed.min(), np.min(arrays["leader_speed_mps"][:t1])))
    hi = float(max(speed.max(), np.max(arrays["leader_speed_mps"][:t1])))
    norm = plt.Normalize(lo, hi if hi > lo else lo + 1.0)
    cmap = plt.get_cmap("turbo_r")
    order = plt.get_cmap("viridis")  # the followers' colours of the time-series figure
    # at most MAX_POINTS rows per line (the last one kept): a 300 s ring of 22 vehicles draws
    # as it looks, in a file a tenth of the size
    rows = np.unique(np.append(np.arange(0, t1, -(-t1 // MAX_POINTS)), t1 - 1))
    if not ring:
        ax.plot(t, x[:, 0], color="black", lw=1.4, label="leader")
    for i in range(n):
        ti, xi, vi = t[rows], x[rows, i + 1], speed[rows, i]
        if ring_length_m is not None:
            xi, wraps = _ring_breaks(xi, ring_length_m)
            ti, xi, vi = (np.insert(arr, wraps, np.nan) for arr in (ti, xi, vi))
        pts = np.column_stack([ti, xi])
        segs = np.stack([pts[:-1], pts[1:]], axis=1)
        keep = np.isfinite(segs).all(axis=(1, 2))
        # not antialiased: a ring's dense stripes compress to half the file, as sharp
        lc = LineCollection(segs[keep], cmap=cmap, norm=norm, linewidths=1.2,
                            antialiaseds=False, label=f"follower {i + 1}")
        lc.set_array(((vi[:-1] + vi[1:]) / 2)[keep])
        ax.add_collection(lc)
        ax_rel.plot(t, x[:, 0] - x[:, i + 1], color=order(i / max(n - 1, 1)), lw=0.9,
                    label=f"follower {i + 1}")
    ax.autoscale_view()
    if ring_length_m is not None:
        ax.set_ylim(0.0, ring_length_m)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=[ax, ax_rel], shrink=0.6,
                 anchor=(0.0, 1.0), label="speed (m/s)")
    ax.set_ylabel("position on the ring (m)" if ring else "position (m)")
    ax_rel.set_ylabel("distance behind\nfollower N (m)" if ring else
                      "distance behind\nthe leader (m)")
    ax_rel.invert_yaxis()  # the leader at the top, as in the diagram above
    ax_rel.set_xlabel("time (s)")
    if collided:
        hit = int(np.argmin(np.asarray(arrays["gap_m"])[-1]))
        xh = float(x[-1, hit + 1] if ring_length_m is None else np.mod(x[-1, hit + 1], ring_length_m))
        ax.plot([t[-1]], [xh], marker="X", color="red", ms=10, ls="none",
                label=f"collision: follower {hit + 1} at {t[-1]:.1f} s")
        ax_rel.axvline(t[-1], color="red", lw=1.0)
    for a in (ax, ax_rel):
        a.grid(alpha=0.3)
    if n <= LEGEND_MAX_FOLLOWERS:
        ax_rel.legend(fontsize=7, loc="upper left", ncol=2)
    else:
        ax_rel.text(0.01, 0.02, f"followers 1 (dark) .. {n} (yellow)", fontsize=7,
                    transform=ax_rel.transAxes)
    handles, labels = ax.get_legend_handles_labels()
    keep_h = [(h, lab) for h, lab in zip(handles, labels, strict=True)
              if not lab.startswith("follower")]
    if keep_h:
        ax.legend(*zip(*keep_h, strict=True), loc="upper left", fontsize=8)
    ax.set_title(title, fontsize=10)
    return plots._save(fig, out_dir, stem)


@dataclass(frozen=True)
class VehicleProfile:
    """Per-vehicle numbers of one run (the per-vehicle string-stability figure's points).

    Attributes
    ----------
    peak_spacing_error_m : (N,)
        ``max_t |gap_i - target_i|`` of followers 1..N after the start-up transient, against
        the controller's own spacing policy where it has one, else the scenario's target.
    accel_rms_mps2 : (N+1,)
        RMS acceleration of the leader (index 0) and followers after the start-up transient:
        the ratio of consecutive entries is the time-domain string gain's
        (:func:`benchmark.string_gain.time_domain_string_gain`, same rows, same norm up to
        the common ``sqrt(T)``).
    """

    peak_spacing_error_m: np.ndarray
    accel_rms_mps2: np.ndarray


def vehicle_profile(arrays: Mapping[str, np.ndarray], target_gap_m: float,
                    spacing: SpacingPolicy | None = None) -> VehicleProfile:
    """The :class:`VehicleProfile` of one run (rows after the start-up transient,
    :func:`analysis.plots.transient_rows`)."""
    first = plots.transient_rows(dict(arrays)) + 1
    gap = np.asarray(arrays["gap_m"])[first:]
    speed = np.asarray(arrays["speed_mps"])[first:]
    target = target_gap_m if spacing is None else spacing.target_gap_m(speed)
    accel = np.concatenate([np.asarray(arrays["leader_accel_mps2"])[first: first + len(gap), None],
                            np.asarray(arrays["accel_mps2"])[first:]], axis=1)
    if not len(gap):
        nan_n = np.full(gap.shape[1], np.nan)
        return VehicleProfile(nan_n, np.full(gap.shape[1] + 1, np.nan))
    return VehicleProfile(np.max(np.abs(gap - target), axis=0),
                          np.sqrt(np.mean(np.square(accel), axis=0)))


#: Markers of the seeds in :func:`plot_per_vehicle` (in seed order, repeating).
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def plot_per_vehicle(
    runs: Mapping[str, Sequence[tuple[int, VehicleProfile]]], title: str, out_dir: Path,
    stem: str, target_names: Mapping[str, str] | None = None,
) -> list[Path]:
    """Peak spacing error and RMS acceleration against the vehicle's index, one colour per
    controller and one line (with markers) per seed: a string-stable controller's lines do not
    rise along the string.

    Parameters
    ----------
    runs : mapping
        Controller label -> ``(seed, profile)`` of each drawn run.
    target_names : mapping, optional
        Controller label -> what its spacing error is measured against (shown in the legend).
    """
    plt = plots._plt()
    fig, (ax_e, ax_a) = plt.subplots(2, 1, figsize=(7.5, 7), sharex=True)
    cmap = plt.get_cmap("tab10" if len(runs) <= 10 else "tab20")
    all_seeds = sorted({seed for seeds in runs.values() for seed, _ in seeds})
    marker_of = {seed: MARKERS[k % len(MARKERS)] for k, seed in enumerate(all_seeds)}
    for j, (label, seeds) in enumerate(runs.items()):
        colour = cmap(j % cmap.N)
        target = (target_names or {}).get(label, "")
        for k, (seed, prof) in enumerate(seeds):
            n = len(prof.peak_spacing_error_m)
            name = f"{label}{f' [{target}]' if target else ''}" if k == 0 else "_seed"
            style = dict(color=colour, marker=marker_of[seed], ms=5, lw=1.2,
                         alpha=1.0 if k == 0 else 0.6)
            ax_e.plot(np.arange(1, n + 1), prof.peak_spacing_error_m, label=name, **style)
            ax_a.plot(np.arange(0, n + 1), prof.accel_rms_mps2,
                      label=f"{label} seed {seed}", **style)
    ax_e.set_ylabel("peak |spacing error| (m)")
    ax_a.set_ylabel("RMS acceleration (m/s$^2$)")
    ax_a.set_xlabel("vehicle index (0: leader)")
    n_seeds = sorted({len(v) for v in runs.values()})
    ax_e.set_title(f"{title}\n(after the start-up transient; {'/'.join(map(str, n_seeds))} "
                   "seed(s) per controller, markers by seed)", fontsize=10)
    for ax in (ax_e, ax_a):
        ax.grid(alpha=0.3)
        ax.xaxis.get_major_locator().set_params(integer=True)
    ax_e.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    from matplotlib.lines import Line2D

    ax_a.legend([Line2D([], [], color="0.4", marker=marker_of[s], ls="none") for s in all_seeds],
                [f"seed {s}" for s in all_seeds], fontsize=7, loc="upper left",
                bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    return plots._save(fig, out_dir, stem)


def plot_gain_frequency(
    curves: Mapping[str, tuple[np.ndarray, np.ndarray]], title: str, out_dir: Path, stem: str,
    tolerance: float = 0.0,
) -> list[Path]:
    """String gain against the leader's angular frequency, one line with markers per controller
    (each point a measured or computed frequency), and the line ``1 + tolerance``.

    Parameters
    ----------
    curves : mapping
        Controller label -> ``(omega_rad_s, gain)`` arrays of the same length.
    tolerance : float
        String stable where every gain is at most ``1 + tolerance``.
    """
    plt = plots._plt()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    cmap = plt.get_cmap("tab10" if len(curves) <= 10 else "tab20")
    for j, (label, (omega, gain)) in enumerate(curves.items()):
        order = np.argsort(omega)
        ax.plot(np.asarray(omega)[order], np.asarray(gain)[order], marker="o", ms=4,
                color=cmap(j % cmap.N), label=label)
    ax.axhline(1.0 + tolerance, color="red", ls="--", lw=0.8,
               label=f"string stable below {1.0 + tolerance:g}")
    ax.set_xscale("log")
    grid = np.unique(np.concatenate([np.asarray(o, dtype=float) for o, _ in curves.values()]))
    if 0 < len(grid) <= 12:  # the swept frequencies themselves, as plain numbers
        from matplotlib.ticker import NullFormatter

        ax.set_xticks(grid, [f"{w:.2g}" for w in grid], fontsize=8)
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("leader frequency $\\omega$ (rad/s)")
    ax.set_ylabel("string gain")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    return plots._save(fig, out_dir, stem)

