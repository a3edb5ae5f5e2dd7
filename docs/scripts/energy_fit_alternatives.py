"""Fits of the power model, the shipped one (polynomial with a regeneration floor) and plain 5x5
polynomials, scored at the reference points of docs/spec/energy.md (the evidence of
docs/energy-fit.md). Run: python docs/scripts/energy_fit_alternatives.py
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from envs.energy import fit_power_polynomial, map_operating_point
from envs.energy.fit import REFERENCE_POINTS, _axis, _monomial_to_si
from envs.energy.power import PowerPolynomial

Weight = Callable[[np.ndarray], np.ndarray]


def fit(v_range: tuple[float, float] = (0.5, 30.0), u_range: tuple[float, float] = (-3.0, 2.5),
        weight: Weight | None = None, pin_references: bool = False) -> PowerPolynomial:
    """Weighted least squares (weight of a point from its power, kW) over a grid, optionally with
    the reference points as equality constraints."""
    speeds, accels = _axis(*v_range, 0.1), _axis(*u_range, 0.05)
    vg, ug = np.meshgrid(speeds, accels, indexing="ij")
    op = map_operating_point(vg, ug)
    v, u, y = vg[op.reachable], ug[op.reachable], op.battery_power_w[op.reachable] / 1000
    cv, sv = speeds.mean(), 0.5 * (speeds[-1] - speeds[0])
    cu, su = 0.5 * (accels[0] + accels[-1]), 0.5 * (accels[-1] - accels[0])

    def design(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        x, z = np.vander((a - cv) / sv, 5, True), np.vander((b - cu) / su, 5, True)
        return (x[:, :, None] * z[:, None, :]).reshape(a.size, -1)

    w = np.sqrt(np.ones_like(y) if weight is None else weight(y))
    a, rhs = design(v, u) * w[:, None], y * w
    if pin_references:
        rv = np.array([p[0] for p in REFERENCE_POINTS])
        ru = np.array([p[1] for p in REFERENCE_POINTS])
        c = design(rv, ru)
        d = map_operating_point(rv, ru).battery_power_w / 1000
        kkt = np.block([[a.T @ a, c.T], [c, np.zeros((len(d), len(d)))]])
        q = np.linalg.solve(kkt, np.concatenate([a.T @ rhs, d]))[:25]
    else:
        q = np.linalg.lstsq(a, rhs, rcond=None)[0]
    return PowerPolynomial(_monomial_to_si(5, cv, sv).T @ q.reshape(5, 5) @ _monomial_to_si(5, cu, su))


def report(name: str, poly: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> None:
    speeds, accels = _axis(0.5, 30.0, 0.1), _axis(-3.0, 2.5, 0.05)
    vg, ug = np.meshgrid(speeds, accels, indexing="ij")
    op = map_operating_point(vg, ug)
    v, u = vg[op.reachable], ug[op.reachable]
    err = poly(v, u) - op.battery_power_w[op.reachable] / 1000
    low = v <= 20
    worst = float(np.abs(err).max())
    ring = [100 * r[4] for r in reference_errors_at(poly, [(s, -2.5) for s in (5, 11, 17)])]
    refs = " ".join(f"{100 * r[4]:+.1f}" for r in reference_errors_at(poly, REFERENCE_POINTS))
    print(f"{name:34s} RMSE {np.sqrt(np.mean(err**2)):.2f} kW (v<=20: "
          f"{np.sqrt(np.mean(err[low] ** 2)):.2f}, max {worst:.2f})  refs % {refs}  "
          f"at u=-2.5, v=5/11/17: {' '.join(f'{r:+.0f}' for r in ring)} %")


def reference_errors_at(poly: Callable[[np.ndarray, np.ndarray], np.ndarray],
                        points: list[tuple[float, float]] | tuple) -> list:
    v = np.array([p[0] for p in points])
    u = np.array([p[1] for p in points])
    want = map_operating_point(v, u).battery_power_w / 1000
    return [(a, b, m, g, (g - m) / abs(m)) for a, b, m, g in zip(v, u, want, poly(v, u), strict=True)]


def regeneration_limit() -> None:
    """The map model's battery power in braking (kW), where the regeneration limit flattens it."""
    accels = np.arange(-3.5, -0.9, 0.25)
    print("map model battery power (kW) at u = " + " ".join(f"{u:+.2f}" for u in accels))
    for v in (5.0, 11.0, 17.0, 25.0):
        p = map_operating_point(np.full_like(accels, v), accels).battery_power_w / 1000
        print(f"  v = {v:4.1f} m/s: " + " ".join(f"{x:6.1f}" for x in p))


if __name__ == "__main__":
    regeneration_limit()
    relative: Weight = lambda y: 100.0 / (np.abs(y) + 10.0) ** 2  # noqa: E731
    report("plain, unweighted (shipped before)", fit())
    report("v <= 20 m/s only", fit(v_range=(0.5, 20.0)))
    report("u in [-2.5, 2.5] (the env's bounds)", fit(u_range=(-2.5, 2.5)))
    report("relative weights 1/(|P|+10 kW)^2", fit(weight=relative))
    report("reference points pinned", fit(pin_references=True))
    report("shipped: floor, weights 1/(|P|+2 kW)^2", fit_power_polynomial().polynomial())
