"""``cacc-bench plot DIR``: figures from a results folder or a training folder (PNG and PDF,
headless)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from benchmark.store import STORE_NAME, ResultStore
from commands.cli import command_parser

if TYPE_CHECKING:
    from controllers.base import SpacingPolicy


def main(argv: list[str]) -> int:
    """Write the figures of a results folder into ``DIR/figures`` (or ``--out``)."""
    from analysis.energy_plots import plot_energy_map
    from analysis.plots import plot_leaderboard, plot_radar
    from benchmark.export import leaderboard_frame, runs_frame
    from infra.errors import ConfigError

    p = command_parser("plot", __doc__)
    p.add_argument("results_dir", help="results folder written by `cacc-bench run`, or a training "
                                       "folder of `cacc-bench train --out` (learning curves)")
    p.add_argument("--out", default=None, help="figure folder (default: RESULTS_DIR/figures)")
    p.add_argument("--no-energy-map", action="store_true", help="skip the energy-map figure")
    p.add_argument("--seeds", type=int, default=1,
                   help="draw the first K seeds of each setting that have a trajectory: the "
                        "store keeps the first seed's, `run --trajectories` writes every run's "
                        "into RESULTS_DIR/trajectories (default: %(default)s)")
    args = p.parse_args(argv)
    if args.seeds < 1:
        raise ConfigError(f"--seeds must be >= 1, got {args.seeds}")
    folder = Path(args.results_dir)
    out = Path(args.out) if args.out else folder / "figures"
    from benchmark.paths import writable_dir

    writable_dir(args.out if args.out is not None else out)  # before any figure is drawn
    if folder.is_dir() and not (folder / STORE_NAME).exists() and any(
            folder.glob("*.curve.csv")):
        return plot_training_folder(folder, out)
    with ResultStore(folder, create=False) as store:
        records = store.records()
        written = run_figures(store, records, folder, out, args.seeds)
    if not records:
        print(f"{folder}: no runs stored; nothing to plot")
        return 0
    lb = leaderboard_frame(runs_frame(records))
    written += plot_leaderboard(lb, out)
    for (sc_id, n), sub in lb.groupby(["scenario", "n_vehicles"]):
        radar = plot_radar(lb, sc_id, int(n), out, f"radar__{sc_id}__n{int(n)}")
        if not radar:
            print(f"radar of {sc_id}, N={int(n)} skipped: {sub['controller'].nunique()} "
                  "controller (each axis is scaled by the largest value among the controllers, "
                  "so one alone is always the full diamond)")
        written += radar
    written += sweep_figures(folder, out)
    if not args.no_energy_map:
        written += plot_energy_map(out)
    say_written(written, out)
    return 0


#: A run's setting: the records of one setting differ only in their seed.
_SETTING = ("controller", "scenario", "n_vehicles", "comm_delay_s", "packet_loss", "lag_s")


def _setting_suffix(r: dict) -> str:
    """``__d<delay>_l<loss>_tau<lag>`` for a setting off the defaults (as run file names)."""
    if not (r["comm_delay_s"] or r["packet_loss"] or r["lag_s"]):
        return ""
    return f"__d{r['comm_delay_s']:g}_l{r['packet_loss']:g}_tau{r['lag_s']:g}"


def _spacing(r: dict) -> SpacingPolicy | None:
    """The controller's own spacing policy recorded with the run (None: it has none, or the
    run was stored before it was recorded)."""
    from controllers.base import SpacingPolicy

    if r.get("spacing_time_gap_s") is None or r.get("spacing_standstill_m") is None:
        return None
    return SpacingPolicy(float(r["spacing_standstill_m"]), float(r["spacing_time_gap_s"]))


def run_figures(store: ResultStore, records: list[dict], folder: Path, out: Path,
                seeds: int) -> list[Path]:
    """The per-run figures (time series, time-space diagram) of the first ``seeds`` seeds of
    every setting that have a trajectory (stored, or a CSV of ``run --trajectories``), and the
    per-vehicle figure of every scenario, N and V2V/lag setting (every controller, every seed
    drawn)."""
    from analysis.platoon_plots import (
        VehicleProfile,
        plot_per_vehicle,
        plot_time_space,
        vehicle_profile,
    )
    from analysis.plots import plot_time_series, spacing_label
    from benchmark.export import read_trajectory_csv
    from benchmark.suite import KEY_COLUMNS, RunKey
    from envs.scenarios import make_scenario

    with_traj = store.trajectory_ids()
    csv_dir = folder / "trajectories"

    def arrays_of(r: dict) -> dict | None:
        if r["id"] in with_traj:
            return store.trajectory(r["id"])
        path = csv_dir / f"{RunKey(**{f: r[f] for f in KEY_COLUMNS}).file_stem}.csv"
        return read_trajectory_csv(path) if path.is_file() else None

    ok = sorted((r for r in records if r["status"] == "ok"), key=lambda r: r["seed"])
    by_setting: dict[tuple, list[dict]] = {}
    for r in ok:
        by_setting.setdefault(tuple(r[c] for c in _SETTING), []).append(r)
    # a stored label is built once (read back from the store, not given on the command line)
    built = {label: make_scenario(label) for label in {r["scenario"] for r in ok}}
    written: list[Path] = []
    profiles: dict[tuple, dict[str, list[tuple[int, VehicleProfile]]]] = {}
    targets: dict[tuple, dict[str, str]] = {}
    short: list[str] = []
    for key, runs in by_setting.items():
        drawn = 0
        for r in runs:
            if drawn == seeds:
                break
            arrays = arrays_of(r)
            if arrays is None:
                continue
            drawn += 1
            sc = built[r["scenario"]]
            spacing = _spacing(r)
            stem = r["id"].replace("|", "__").replace("/", "_")
            title = (f"{r['controller']} on {r['scenario']}, N={r['n_vehicles']}, seed {r['seed']}"
                     f" (V2V delay {r['comm_delay_s']:g} s, loss {r['packet_loss']:g})")
            if sc.note:
                title += "\n" + sc.note
            collided = bool(r.get("collision"))
            written += plot_time_series(arrays, title, out, "timeseries__" + stem,
                                        sc.target_gap_m, sc.target_speed_mps, spacing=spacing,
                                        controller=str(r["controller"]), collided=collided)
            ring_m = float(sc.options["length_m"]) if sc.ring else None
            written += plot_time_space(arrays, title, out, "timespace__" + stem,
                                       ring_length_m=ring_m, collided=collided)
            group = key[1:]
            profiles.setdefault(group, {}).setdefault(str(r["controller"]), []).append(
                (int(r["seed"]), vehicle_profile(arrays, sc.target_gap_m, spacing)))
            targets.setdefault(group, {})[str(r["controller"])] = (
                spacing_label(spacing) or f"published target {sc.target_gap_m:g} m")
        if drawn < seeds and len(runs) > drawn:
            short.append(f"{key[0]} on {key[1]} (N={key[2]}): {drawn}")
    if short:
        print(f"--seeds {seeds}: fewer seeds have a trajectory for "
              f"{'; '.join(short[:5])}{' ...' if len(short) > 5 else ''} (the store keeps the "
              "first seed's; `cacc-bench run --trajectories` writes every run's)")
    for group, runs_of in profiles.items():
        r0 = dict(zip(_SETTING[1:], group, strict=True))
        stem = f"per_vehicle__{r0['scenario']}__n{r0['n_vehicles']}{_setting_suffix(r0)}"
        written += plot_per_vehicle(
            runs_of, f"{r0['scenario']}, N={r0['n_vehicles']}: spacing error and acceleration "
            "along the string", out, stem.replace("/", "_"), targets[group])
    return written


def sweep_figures(folder: Path, out: Path) -> list[Path]:
    """Gain against frequency of every controller configuration in the folder's string-sweep
    cache (:class:`benchmark.sweep.SweepCache`, written by ``run``/``leaderboard``), one figure
    per N and V2V/lag setting; none, with a line, when the folder has no sweep data."""
    from analysis.platoon_plots import plot_gain_frequency
    from benchmark.sweep import CACHE_NAME, SWEEP_TOL, SweepCache

    if not (folder / CACHE_NAME).is_file():
        print(f"gain-against-frequency figure skipped: {folder} has no {CACHE_NAME} (the "
              "string-stability sweeps `cacc-bench leaderboard` measures)")
        return []
    groups: dict[tuple, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for res in SweepCache(folder).values():
        key = (str(res.scenario or ""), res.n_vehicles, res.comm_delay_s, res.packet_loss,
               res.lag_s)
        groups.setdefault(key, {})[res.controller] = (np.asarray(res.omegas_rad_s),
                                                      np.asarray(res.gains_per_omega))
    written: list[Path] = []
    for (scenario, n, delay, loss, lag), curves in sorted(groups.items()):
        r = {"comm_delay_s": delay, "packet_loss": loss, "lag_s": lag}
        acting = f" acting as on {scenario}" if scenario else ""
        stem = f"gain_frequency__{scenario + '__' if scenario else ''}n{n}{_setting_suffix(r)}"
        written += plot_gain_frequency(
            curves, f"measured string gain |Gamma(jw)| (sinusoidal leader{acting}), N={n},\n"
            f"V2V delay {delay:g} s, loss {loss:g}, lag {lag:g} s", out,
            stem.replace("/", "_"), tolerance=SWEEP_TOL)
    return written


def plot_training_folder(folder: Path, out: Path) -> int:
    """Learning curves of every ``<algo>__<scenario>__n<N>__s<seed>.curve.csv`` in ``folder``:
    one figure per scenario and N, one line (mean over seeds, min-max band) per algorithm."""
    import re

    from studies.reproduction import learning_curve_figure, read_curve

    pattern = re.compile(r"^(?P<algo>[^_]+(?:-[^_]+)*)__(?P<scenario>.+)__n(?P<n>\d+)__s(?P<seed>\d+)$")
    groups: dict[tuple[str, int], dict[tuple[str, str, int], object]] = {}
    for path in sorted(folder.glob("*.curve.csv")):
        m = pattern.match(path.name[: -len(".curve.csv")])
        if m is None:
            continue
        curve = read_curve(path)
        key = (m["algo"], m["scenario"], int(m["seed"]))
        groups.setdefault((m["scenario"], int(m["n"])), {})[key] = curve
    written = []
    for (scenario, n), curves in sorted(groups.items()):
        algos = sorted({k[0] for k in curves})
        written += learning_curve_figure(curves, algos, scenario, out, f"curves__{scenario}__n{n}",
                                         f"learning curves on {scenario}, N = {n} ({folder})")
    say_written(written, out)
    return 0


def say_written(written: list, out: Path) -> None:
    """Name the files written, one figure a line (``leaderboard.{png,pdf}``), under the folder
    as the user can open it (relative to where they ran the command)."""
    from benchmark.work_folder import shown_path

    by_stem: dict[str, list[str]] = {}
    for path in map(Path, written):
        try:
            stem = path.relative_to(out).with_suffix("").as_posix()
        except ValueError:
            stem = shown_path(path.with_suffix(""))
        by_stem.setdefault(stem, []).append(path.suffix.lstrip("."))
    print(f"wrote {len(written)} files into {shown_path(out)}{':' if written else ''}")
    for stem, exts in by_stem.items():
        print(f"  {stem}.{exts[0]}" if len(exts) == 1 else f"  {stem}.{{{','.join(exts)}}}")
