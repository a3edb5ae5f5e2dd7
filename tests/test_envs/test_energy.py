"""Tests of the energy models (the envs.energy package), the fit script and the energy figure."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from envs import energy

# spec/energy.md, reference values of the map model: (v m/s, u m/s^2, P_batt kW)
REFERENCES = [
    (5.0, 0.0, 1.15),
    (11.1, 0.0, 2.89),
    (20.0, 0.0, 8.03),
    (11.0, 1.0, 21.8),
    (11.0, -1.0, -12.4),
    (11.0, -3.0, -20.2),  # regeneration torque limit
]


@pytest.fixture(scope="module")
def refit() -> energy.PowerFit:
    return energy.fit_power_polynomial()


# --- data files --------------------------------------------------------------------------------


def test_vehicle_params_from_file_match_spec() -> None:
    p = energy.load_vehicle_params()
    assert p == energy.VehicleParams()
    assert (p.mass_kg, p.theta_kgm2, p.wheel_radius_m) == (1417.0, 12.5, 0.3498)
    assert (p.rolling_coeff, p.drag_coeff, p.frontal_area_m2) == (0.007, 0.29, 2.38)
    assert (p.gear_ratio, p.gear_efficiency) == (9.665, 0.96)
    assert (p.motor_torque_max_nm, p.motor_power_max_w) == (250.0, 125000.0)
    assert (p.regen_torque_max_nm, p.regen_power_max_w, p.aux_power_w) == (77.0, 50000.0, 360.0)
    assert (p.air_density_kgm3, p.gravity_mps2) == (1.204, 9.81)


def test_loss_map_shape() -> None:
    lm = energy.load_loss_map()
    assert lm.speed_rpm.shape == (30,) and lm.torque_nm.shape == (33,)
    assert lm.loss_w.shape == (33, 30)
    assert lm.speed_rpm[0] == 0.0 and lm.speed_rpm[-1] == 11000.0
    # grid points interpolate to themselves
    assert energy.LossMap.interpolate(lm, lm.speed_rpm[3], lm.torque_nm[20]) == pytest.approx(
        lm.loss_w[20, 3]
    )


def test_loss_map_nan_filled_from_same_speed_column() -> None:
    lm = energy.load_loss_map()
    loss = lm.loss_w.copy()
    loss[-3:, 5] = np.nan
    filled = energy.LossMap(lm.speed_rpm, lm.torque_nm, loss).filled()
    assert np.all(filled[-3:, 5] == lm.loss_w[-4, 5])
    assert np.array_equal(np.delete(filled, 5, axis=1), np.delete(lm.loss_w, 5, axis=1))


def _broken_copy(tmp_path: Path, old: str, new: str) -> Path:
    text = energy.DEFAULT_VEHICLE_FILE.read_text(encoding="utf-8")
    assert old in text
    path = tmp_path / "broken_i3.dat"
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("old", "new", "problem"),
    [
        (",1070.56,", ",", "values, expected"),  # one value missing
        (",1070.56,", ",abc,", "non-number"),
        ("2,1|0,379.3103", "2,1|0;379.3103", "axes"),
        ("powerLossMapString", "lossMap", "missing"),
    ],
)
def test_malformed_loss_map_names_file(tmp_path: Path, old: str, new: str, problem: str) -> None:
    path = _broken_copy(tmp_path, old, new)
    with pytest.raises(ValueError, match=problem) as info:
        energy.load_loss_map(path)
    assert str(path) in str(info.value)


def test_malformed_params_name_file(tmp_path: Path) -> None:
    path = _broken_copy(tmp_path, "m = 1417.0", "m = heavy")
    with pytest.raises(ValueError, match="'m'") as info:
        energy.load_vehicle_params(path)
    assert str(path) in str(info.value)
    missing = tmp_path / "nope.dat"
    with pytest.raises(ValueError, match="not found") as info:
        energy.load_loss_map(missing)
    assert str(missing) in str(info.value)


# --- map model ---------------------------------------------------------------------------------


@pytest.mark.parametrize(("v", "u", "ref_kw"), REFERENCES)
def test_map_model_reference_values(v: float, u: float, ref_kw: float) -> None:
    p = float(energy.battery_power_kw(v, u, model="map"))
    assert p == pytest.approx(ref_kw, rel=0.03)
    # SUMO's variant with the battery's internal resistance matches the table more closely
    p_sumo = float(energy.map_battery_power_kw(v, u, include_battery_loss=True))
    assert p_sumo == pytest.approx(ref_kw, rel=0.005)


def test_map_model_limits() -> None:
    op = energy.map_operating_point(11.0, -3.0)
    assert float(op.motor_torque_nm) == pytest.approx(-77.0)
    assert bool(op.regen_limited) and bool(op.reachable)
    op = energy.map_operating_point(29.0, -3.0)  # regeneration power limit: 50 kW mechanical
    assert float(op.motor_power_w) == pytest.approx(-50000.0)
    op = energy.map_operating_point(30.0, 2.5)  # beyond 125 kW: held at the limit, unreachable
    assert float(op.motor_power_w) == pytest.approx(125000.0)
    assert not bool(op.reachable)
    op = energy.map_operating_point(3.0, 2.5)
    assert bool(op.reachable) and float(op.motor_torque_nm) < 250.0


def test_map_model_broadcasting() -> None:
    v = np.linspace(1.0, 25.0, 7)[:, None]
    u = np.linspace(-2.0, 2.0, 5)[None, :]
    p = energy.map_battery_power_kw(v, u)
    assert p.shape == (7, 5)
    assert p[3, 2] == pytest.approx(float(energy.map_battery_power_kw(v[3, 0], u[0, 2])))
    assert np.all(np.diff(p, axis=1) > 0)  # more acceleration, more power


# --- polynomial --------------------------------------------------------------------------------


def test_shipped_quality_equals_refit(refit: energy.PowerFit) -> None:
    poly = energy.load_power_polynomial()
    stored = poly.metadata["quality"]
    for key, value in refit.quality().items():
        assert stored[key] == pytest.approx(value, rel=1e-9, abs=1e-12), key
    scale = np.abs(refit.coefficients_kw).max()
    np.testing.assert_allclose(
        poly.coefficients_kw, refit.coefficients_kw, rtol=1e-8, atol=1e-12 * scale
    )
    assert poly.metadata["grid"] == refit.grid
    assert poly.metadata["provenance"]["cacc_bench_version"] == "0.1.0"
    assert poly.coefficients_kw.shape == (5, 5)


def test_fit_quality_as_spec(refit: energy.PowerFit) -> None:
    assert refit.r2_low_speed > 0.999 and refit.rmse_kw_low_speed < 1.0
    assert refit.r2 > 0.998 and refit.rmse_kw < 1.5


@pytest.mark.parametrize(("v", "u", "ref_kw"), REFERENCES)
def test_polynomial_close_to_map(v: float, u: float, ref_kw: float) -> None:
    """Issue 16: the shipped model within 5 % of the map model at every reference point."""
    p_poly = float(energy.battery_power_kw(v, u))
    p_map = float(energy.battery_power_kw(v, u, model="map"))
    assert abs(p_poly - p_map) <= 0.05 * abs(p_map)


def test_a_plain_polynomial_misses_the_regeneration_limit_and_the_floor_meets_it() -> None:
    """Why the floor: the unweighted 5x5 polynomial (the fit shipped before) errs by 9.5 % at
    (11 m/s, -3 m/s^2), where the regeneration limit holds the battery power flat; the floor is
    that flat power (the map model's value at u = -3 m/s^2) within 2 kW over the speeds (a cubic
    rounds the corner where the torque limit meets the power limit)."""
    from envs.energy.fit import reference_errors

    plain = energy.fit_power_polynomial(regeneration_floor=False, weight_offset_kw=None)
    assert plain.floor_kw is None
    errors = [e[4] for e in reference_errors(plain.polynomial())]
    assert errors[-1] == pytest.approx(0.095, abs=0.001)
    shipped = energy.load_power_polynomial()
    assert max(abs(e[4]) for e in reference_errors(shipped)) < 0.05
    v = np.linspace(2.0, 30.0, 57)
    limited = energy.map_battery_power_kw(v, np.full_like(v, -3.0))
    assert np.abs(shipped.floor_at(v) - limited).max() < 2.0
    assert np.all(energy.map_battery_power_kw(v, np.full_like(v, -2.0)) == limited)  # flat


def _naive(coef: np.ndarray, floor: np.ndarray | None, v: float, u: float) -> float:
    total = 0.0
    for k in range(coef.shape[0]):
        for j in range(coef.shape[1]):
            total += coef[k, j] * v**k * u**j
    if floor is not None:
        total = max(total, sum(c * v**i for i, c in enumerate(floor)))
    return total


def test_power_polynomial_equals_naive_double_loop() -> None:
    poly = energy.load_power_polynomial()
    coef, floor = poly.coefficients_kw, poly.floor_kw
    assert floor is not None and floor.shape == (4,)
    rng = np.random.default_rng(0)
    v = rng.uniform(0.0, 30.0, 50)
    u = rng.uniform(-3.0, 2.5, 50)
    got = poly(v, u)
    want = np.array([_naive(coef, floor, a, b) for a, b in zip(v, u)])
    assert np.any(poly.floor_at(v) == got)  # the sample reaches the floor
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-10)
    assert poly.expression(float(v[0]), float(u[0])) == pytest.approx(want[0], rel=1e-12)
    # derivatives against central differences
    h = 1e-5
    np.testing.assert_allclose(
        poly.dP_dv(v, u), (poly(v + h, u) - poly(v - h, u)) / (2 * h), rtol=1e-6, atol=1e-6
    )
    np.testing.assert_allclose(
        poly.dP_du(v, u), (poly(v, u + h) - poly(v, u - h)) / (2 * h), rtol=1e-6, atol=1e-6
    )


def test_power_polynomial_shapes_dtypes_and_out() -> None:
    poly = energy.load_power_polynomial()
    v = np.linspace(0.0, 30.0, 6).reshape(6, 1)
    u = np.linspace(-2.5, 2.5, 4)
    assert poly(v, u).shape == (6, 4)
    assert poly(5.0, 0.0).shape == ()
    assert poly(v, 0.0).shape == (6, 1)
    assert poly(v.astype(np.float32), u.astype(np.float32)).dtype == np.float32
    assert poly(v.astype(np.float32), u).dtype == np.float64
    np.testing.assert_allclose(
        poly(v.astype(np.float32), u.astype(np.float32)), poly(v, u), rtol=1e-4, atol=1e-3
    )
    out = np.empty((6, 4))
    res = poly(v, u, out=out)
    assert res is out
    np.testing.assert_array_equal(out, poly(v, u))
    # out may alias an input
    vv = np.broadcast_to(v, (6, 4)).copy()
    expected = poly(vv, u)
    poly(vv, u, out=vv)
    np.testing.assert_array_equal(vv, expected)
    with pytest.raises(ValueError, match="shape"):
        poly(v, u, out=np.empty((6, 3)))
    # several blocks with a remainder, broadcast inputs, a non-contiguous out
    vb = np.linspace(0.0, 30.0, 20_001)[:, None]
    ub = np.array([-2.0, 0.5])
    vv, uu = np.broadcast_arrays(vb, ub)
    want = np.maximum(np.polynomial.polynomial.polyval2d(vv, uu, poly.coefficients_kw),
                      np.polynomial.polynomial.polyval(vv, poly.floor_kw))
    np.testing.assert_allclose(poly(vb, ub), want, rtol=1e-12, atol=1e-10)
    strided = np.empty((20_001, 4))[:, ::2]
    poly(vb, ub, out=strided)
    np.testing.assert_allclose(strided, want, rtol=1e-12, atol=1e-10)
    assert poly.coefficients_kw.shape == (5, 5)
    assert not poly.coefficients_kw.flags.writeable
    assert energy.battery_power_kw(v, u, model="poly").shape == (6, 4)
    assert energy.battery_power_kw(v, u, model="vtcpem").shape == (6, 4)


def test_invalid_model_name() -> None:
    with pytest.raises(ValueError, match="poly, map, vtcpem"):
        energy.battery_power_kw(10.0, 0.0, model="fastsim")


def test_malformed_polynomial_file(tmp_path: Path) -> None:
    path = tmp_path / "poly.json"
    path.write_text('{"coefficients_kw": [[1, 2], [3]]}', encoding="utf-8")
    with pytest.raises(ValueError) as info:
        energy.load_power_polynomial(path)
    assert str(path) in str(info.value)
    for bad, message in [('"floor_kw": [1, "x"]', "floor_kw"), ('"floor_kw": []', "floor_kw"),
                         ('"format": "cacc-bench power polynomial 9"', "format")]:
        path.write_text('{"coefficients_kw": [[1, 2], [3, 4]], ' + bad + "}", encoding="utf-8")
        with pytest.raises(ValueError, match=message):
            energy.load_power_polynomial(path)


def test_a_format_1_file_loads_as_a_plain_polynomial(tmp_path: Path) -> None:
    path = tmp_path / "poly.json"
    path.write_text('{"format": "cacc-bench power polynomial 1", '
                    '"coefficients_kw": [[1, 2], [3, 4]]}', encoding="utf-8")
    poly = energy.load_power_polynomial(path)
    assert poly.floor_kw is None
    assert float(poly(2.0, -1.0)) == 1 - 2 + 3 * 2 - 4 * 2
    assert poly.fingerprint != energy.load_power_polynomial().fingerprint


# --- VT-CPEM and energy ------------------------------------------------------------------------


def test_vtcpem() -> None:
    v, u = 11.0, 1.0
    p = energy.VTCPEMParams()
    force = p.mass_kg * u + p.mass_kg * 9.81 * 1.75e-3 * (0.0328 * 39.6 + 4.575)
    force += 0.5 * 1.2256 * 2.3316 * 0.28 * v * v
    want = force * v / (0.92 * 0.91) / 1000.0
    assert float(energy.battery_power_kw(v, u, model="vtcpem")) == pytest.approx(want, rel=1e-12)
    braking = float(energy.vtcpem_battery_power_kw(25.0, -3.0))
    assert braking < -50.0
    assert float(energy.vtcpem_battery_power_kw(25.0, -3.0, regen_limit_kw=50.0)) == -50.0
    eta_rb = math.exp(-0.0411 / 1.0)
    force = (
        -p.mass_kg
        + p.mass_kg * 9.81 * 1.75e-3 * (0.0328 * 36.0 + 4.575)
        + 0.5 * 1.2256 * 2.3316 * 0.28 * 100
    )
    assert float(energy.vtcpem_battery_power_kw(10.0, -1.0)) == pytest.approx(
        force * 10.0 * 0.92 * 0.91 * eta_rb / 1000.0, rel=1e-12
    )


def test_energy_kwh() -> None:
    assert energy.energy_kwh(np.full(3600, 10.0), 0.1) == pytest.approx(1.0)
    trace = np.stack([np.full(100, 36.0), np.full(100, -36.0)], axis=1)
    np.testing.assert_allclose(energy.energy_kwh(trace, 1.0), [1.0, -1.0])
    assert energy.kwh_per_100km(15.0, 100_000.0) == pytest.approx(15.0)


# --- script and figure -------------------------------------------------------------------------


def test_fit_power_main(capsys: pytest.CaptureFixture[str]) -> None:
    from commands import fit_power

    assert fit_power.main([]) == 0
    out = capsys.readouterr().out
    assert "R^2" in out and "RMSE" in out and "DIFFERENT" not in out
    # the reference points, by an independent evaluation of both models
    poly = energy.load_power_polynomial()
    for v, u, _ in REFERENCES:
        want = float(energy.map_battery_power_kw(np.array(v), np.array(u)))
        got = float(poly(np.array([v]), np.array([u]))[0])
        line = f"v = {v:4.1f} m/s, u = {u:+.0f} m/s^2: {want:7.2f} kW  {got:7.2f} kW  "
        assert f"{line}{100 * (got - want) / abs(want):+5.1f} %" in out
    # within 5 % everywhere, and at the regeneration limit (issue 16: docs/energy-fit.md)
    assert "u = -3 m/s^2:  -20.41 kW   -20.41 kW   +0.0 %" in out
    with pytest.raises(SystemExit) as info:
        fit_power.main(["--no-such-option"])
    assert info.value.code == 2


def test_plot_energy_map(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from analysis.energy_plots import plot_energy_map

    paths = plot_energy_map(tmp_path, speed_step_mps=0.5, accel_step_mps2=0.25)
    assert {p.suffix for p in paths} == {".png", ".pdf"}
    for p in paths:
        assert p.exists() and p.stat().st_size > 1000
