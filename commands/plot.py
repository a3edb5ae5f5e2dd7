"""``cacc-bench plot DIR``: figures from a results folder or a training folder (PNG and PDF,
headless)."""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmark.store import STORE_NAME, ResultStore
from commands.cli import plain


def main(argv: list[str]) -> int:
    """Write the figures of a results folder into ``DIR/figures`` (or ``--out``)."""
    from analysis.energy_plots import plot_energy_map
    from analysis.plots import plot_leaderboard, plot_radar, plot_time_series
    from benchmark.export import leaderboard_frame, runs_frame
    from envs.scenarios import make_scenario

    p = argparse.ArgumentParser(prog="cacc-bench plot", description=plain(__doc__))
    p.add_argument("results_dir", help="results folder written by `cacc-bench run`, or a training "
                                       "folder of `cacc-bench train --out` (learning curves)")
    p.add_argument("--out", default=None, help="figure folder (default: RESULTS_DIR/figures)")
    p.add_argument("--no-energy-map", action="store_true", help="skip the energy-map figure")
    args = p.parse_args(argv)
    folder = Path(args.results_dir)
    out = Path(args.out) if args.out else folder / "figures"
    from benchmark.paths import writable_dir

    writable_dir(args.out if args.out is not None else out)  # before any figure is drawn
    if folder.is_dir() and not (folder / STORE_NAME).exists() and any(
            folder.glob("*.curve.csv")):
        return plot_training_folder(folder, out)
    with ResultStore(folder, create=False) as store:
        records = store.records()
        with_traj = store.trajectory_ids()
        ok = [r for r in records if r["status"] == "ok"]
        # one run per controller x scenario x N x setting: the lowest seed with a trajectory
        chosen: dict[tuple, dict] = {}
        for r in sorted(ok, key=lambda r: r["seed"]):
            key = (r["controller"], r["scenario"], r["n_vehicles"], r["comm_delay_s"],
                   r["packet_loss"], r["lag_s"])
            if key not in chosen and r["id"] in with_traj:
                chosen[key] = r
        written: list[Path] = []
        # a stored label is built once (read back from the store, not given on the command line)
        built = {label: make_scenario(label) for label in {r["scenario"] for r in chosen.values()}}
        for r in chosen.values():
            arrays = store.trajectory(r["id"])
            assert arrays is not None
            sc = built[r["scenario"]]
            stem = "timeseries__" + r["id"].replace("|", "__").replace("/", "_")
            title = (f"{r['controller']} on {r['scenario']}, N={r['n_vehicles']}, seed {r['seed']}"
                     f" (V2V delay {r['comm_delay_s']:g} s, loss {r['packet_loss']:g})")
            if sc.note:
                title += "\n" + sc.note
            written += plot_time_series(arrays, title, out, stem, sc.target_gap_m,
                                        sc.target_speed_mps)
    if not records:
        print(f"{folder}: no runs stored; nothing to plot")
        return 0
    lb = leaderboard_frame(runs_frame(records))
    written += plot_leaderboard(lb, out)
    for (sc_id, n), _ in lb.groupby(["scenario", "n_vehicles"]):
        written += plot_radar(lb, sc_id, int(n), out, f"radar__{sc_id}__n{int(n)}")
    if not args.no_energy_map:
        written += plot_energy_map(out)
    print(f"wrote {len(written)} files into {out}")
    return 0


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
    print(f"wrote {len(written)} files into {out}")
    return 0
