"""``cacc-bench fit-power``: refit the energy model (polynomial and regeneration floor) from the
shipped BMW i3 map data.

Prints the fit quality (R^2, RMSE, max error over the full grid and over v in [0.5, 20] m/s,
and the error at the spec's reference points),
compares the refit with the shipped coefficients (``envs/data/energy/power_poly.json``),
optionally overwrites them (``--write``) and draws the figure (``--figure DIR``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from commands.cli import command_parser
from envs import energy
from envs.energy import power
from infra import atomic


def _parser() -> argparse.ArgumentParser:
    parser = command_parser("fit-power", "Refit the battery-power model P(v, u) = max(5x5 "
                            "polynomial, regeneration floor) (kW) to the BMW i3 efficiency-map "
                            "model, print its quality and compare it with the shipped "
                            "coefficients.")
    parser.add_argument(
        "--write",
        action="store_true",
        help=f"overwrite the shipped coefficients ({energy.DEFAULT_POLYNOMIAL_FILE.name}) with the refit",
    )
    parser.add_argument(
        "--figure",
        metavar="DIR",
        help="write the map / polynomial / error figure (PNG and PDF) into DIR",
    )
    return parser


def _quality_lines(fit: energy.PowerFit) -> list[str]:
    g = fit.grid
    v0, v1 = g["speed_range_mps"]
    u0, u1 = g["accel_range_mps2"]
    lv0, lv1 = g["low_speed_range_mps"]
    return [
        "Battery power P(v, u) = max(sum_k sum_j p[k, j] v^k u^j, floor(v))  (kW; BMW i3 map "
        "model; floor: regeneration-limited power, cubic in v)",
        f"grid: v in [{v0:g}, {v1:g}] m/s step {g['speed_step_mps']:g}, u in [{u0:g}, {u1:g}] m/s^2 "
        f"step {g['accel_step_mps2']:g}; {fit.n_points} of {g['n_grid']} points reachable",
        f"  v in [{v0:g}, {v1:g}] m/s: R^2 = {fit.r2:.5f}  RMSE = {fit.rmse_kw:.3f} kW  "
        f"max |error| = {fit.max_abs_error_kw:.3f} kW  ({fit.n_points} points)",
        f"  v in [{lv0:g}, {lv1:g}] m/s: R^2 = {fit.r2_low_speed:.5f}  RMSE = {fit.rmse_kw_low_speed:.3f} kW  "
        f"max |error| = {fit.max_abs_error_kw_low_speed:.3f} kW  ({fit.n_points_low_speed} points)",
    ]


def _reference_lines(fit: energy.PowerFit) -> list[str]:
    """The refit against the map model at the reference points of docs/spec/energy.md."""
    from envs.energy.fit import reference_errors

    lines = ["at the reference points of docs/spec/energy.md (map model, fitted model, error):"]
    for v, u, want, got, rel in reference_errors(fit.polynomial()):
        lines.append(f"  v = {v:4.1f} m/s, u = {u:+.0f} m/s^2: {want:7.2f} kW  {got:7.2f} kW  "
                     f"{100 * rel:+5.1f} %")
    return lines


def _compare(fit: energy.PowerFit, path: Path) -> tuple[bool, list[str]]:
    """Compare the refit with a stored polynomial file: (readable, report lines)."""
    try:
        shipped = energy.load_power_polynomial(path)
    except ValueError as exc:
        return False, [f"shipped coefficients: {exc}"]
    ref = fit.coefficients_kw
    if shipped.coefficients_kw.shape != ref.shape:
        return True, [
            f"shipped coefficients ({path}): shape {shipped.coefficients_kw.shape} differs from the "
            f"refit's {ref.shape}"
        ]
    old_floor = np.array([]) if shipped.floor_kw is None else shipped.floor_kw
    new_floor = np.array([]) if fit.floor_kw is None else fit.floor_kw
    if old_floor.shape != new_floor.shape:
        return True, [f"shipped coefficients ({path}): the regeneration floor differs in form "
                      "from the refit's (remake with `cacc-bench fit-power --write`)"]
    coef_diff = float(np.max(np.abs(np.concatenate(
        [(shipped.coefficients_kw - ref).ravel(), old_floor - new_floor]))))
    v0, v1 = fit.grid["speed_range_mps"]
    u0, u1 = fit.grid["accel_range_mps2"]
    nv = int(round((v1 - v0) / fit.grid["speed_step_mps"])) + 1
    nu = int(round((u1 - u0) / fit.grid["accel_step_mps2"])) + 1
    vg, ug = np.meshgrid(np.linspace(v0, v1, nv), np.linspace(u0, u1, nu), indexing="ij")
    pred_diff = float(np.max(np.abs(shipped(vg, ug) - fit.polynomial()(vg, ug))))
    fitted_on = shipped.metadata.get("provenance", {}).get("fitted_on", "?")
    verdict = (
        "identical"
        if coef_diff == 0.0
        else ("equal to rounding" if pred_diff < 1e-6 else "DIFFERENT")
    )
    return True, [
        f"shipped coefficients ({path}, fitted on {fitted_on}): {verdict}",
        f"  max |coefficient difference| = {coef_diff:.3e}",
        f"  max |prediction difference| over the grid = {pred_diff:.3e} kW",
    ]


def main(argv: list[str] | None = None) -> int:
    """Run ``cacc-bench fit-power``; returns the exit status (2 for bad arguments, via argparse).

    Returns 1 when the shipped coefficient file is missing or unreadable and ``--write`` is not
    given, else 0.
    """
    args = _parser().parse_args(argv)
    if args.figure is not None:
        from benchmark.paths import writable_dir

        writable_dir(args.figure, "--figure", create=True)
    fit = energy.fit_power_polynomial()
    for line in _quality_lines(fit):
        print(line)
    for line in _reference_lines(fit):
        print(line)
    path = energy.DEFAULT_POLYNOMIAL_FILE
    readable, lines = _compare(fit, path)
    for line in lines:
        print(line)
    status = 0
    if args.write:
        data = fit.to_json_dict()
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic.write_text(path, json.dumps(data, indent=2) + "\n")
        power._default_polynomial.cache_clear()
        print(f"wrote {path}")
    elif not readable:
        print("run `cacc-bench fit-power --write` to (re)create it", file=sys.stderr)
        status = 1
    if args.figure is not None:
        from analysis.energy_plots import plot_energy_map

        for out in plot_energy_map(Path(args.figure)):
            print(f"wrote {out}")
    return status


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
