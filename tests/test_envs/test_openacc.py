"""Tests of the OpenACC replay data (envs/openacc.py and the shipped window files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from envs.openacc import (
    DT_S,
    WINDOWS,
    OpenACCDataError,
    OpenACCWindow,
    data_path,
    load_window,
    read_openacc_csv,
    read_openacc_header,
    real_followers_record,
)

HEADER = "Date,8,10,2019\r\nVehicle_order,LEAD,CAR_A,CAR_B,\r\nNumber_of_vehicles,3\r\nACC,1\r\nDistance_setting,M\r\n"
COLUMNS = "Time,Speed1,E1,Speed2,E2,Speed3,E3,IVS1,IVS2\r\n"


def _write_csv(path: Path, rows: list[str], header: str = HEADER, columns: str = COLUMNS) -> Path:
    path.write_text(header + columns + "".join(r + "\r\n" for r in rows), newline="")
    return path


def _good_rows(n: int = 10) -> list[str]:
    rows = []
    for i in range(n):
        t = 100.0 + 0.1 * i
        rows.append(f"{t:.1f},{10 + i},0,{9 + i},0,{8 + i},0,{20 + i},{15 + 2 * i}")
    return rows


# ---------------------------------------------------------------------------------------------
# Shipped windows
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["S", "M", "L"])
def test_window_time_base(name: str) -> None:
    w = load_window(name)
    spec = WINDOWS[name]
    assert isinstance(w, OpenACCWindow)
    assert w.name == name
    assert w.n_samples == 601
    assert w.time_s.shape == (601,)
    assert w.time_s[0] == pytest.approx(spec.t_start_s, abs=1e-9)
    assert w.time_s[-1] == pytest.approx(spec.t_end_s, abs=1e-9)
    np.testing.assert_allclose(np.diff(w.time_s), DT_S, atol=1e-6)
    assert w.leader_speed_mps.shape == (601,)
    k = w.n_followers
    for arr in (w.follower_speed_mps, w.follower_gap_m, w.follower_accel_mps2):
        assert arr.shape == (601, k)
        assert not np.isnan(arr).any()
    assert not np.isnan(w.leader_speed_mps).any()
    assert (w.follower_gap_m > 0).all()
    assert (w.follower_speed_mps >= 0).all()
    assert w.distance_setting == name
    assert w.vehicle_names[0] == "SMART_TARGET"
    assert len(w.follower_names) == k
    assert w.target_gap_m == {"S": 12.0, "M": 16.0, "L": 20.0}[name]
    assert w.target_speed_mps == 11.0


@pytest.mark.parametrize(
    ("name", "v_start", "v_min", "t_min", "n_followers"),
    [
        ("S", 11.2, 5.83, 329.4, 5),
        ("L", 11.2, 4.38, 460.6, 5),
        ("M", 8.3, 4.41, 1261.7, 4),
    ],
)
def test_leader_facts(
    name: str, v_start: float, v_min: float, t_min: float, n_followers: int
) -> None:
    w = load_window(name)
    v = w.leader_speed_mps
    assert w.n_followers_available == n_followers
    assert w.n_followers == n_followers
    assert v[:50].max() == pytest.approx(v_start, abs=0.1)
    assert v.min() == pytest.approx(v_min, abs=0.01)
    assert w.time_s[np.argmin(v)] == pytest.approx(t_min, abs=0.051)


def test_m_window_note_and_fewer_followers() -> None:
    w = load_window("M", n_followers=2)
    assert "dynamic_part8" in w.note and "dynamic_part9" in w.note
    assert "8 m/s" in w.note
    assert w.follower_speed_mps.shape == (601, 2)
    assert w.follower_names == ("MERCEDES_GLE450", "TESLA_MODELX")
    assert load_window("S").note == ""


def test_gap_and_accel_columns_match_file() -> None:
    w = load_window("S", n_followers=4)
    df = read_openacc_csv(data_path("S"))
    sel = df[(df["Time"] >= 316.0 - 1e-6) & (df["Time"] <= 376.0 + 1e-6)]
    np.testing.assert_array_equal(w.follower_gap_m[:, 2], sel["IVS3"].to_numpy())
    np.testing.assert_array_equal(w.follower_speed_mps[:, 0], sel["Speed2"].to_numpy())
    full_v = df["Speed3"].to_numpy()
    i0 = int(np.flatnonzero(np.isclose(df["Time"].to_numpy(), 316.0))[0])
    expected = np.gradient(full_v, 0.1)[i0 : i0 + 601]
    np.testing.assert_allclose(w.follower_accel_mps2[:, 1], expected)


def test_window_arrays_are_read_only() -> None:
    w = load_window("L")
    with pytest.raises(ValueError):
        w.leader_speed_mps[0] = 0.0


def test_unknown_window_lists_valid_names() -> None:
    with pytest.raises(KeyError) as info:
        load_window("X")
    msg = str(info.value)
    assert "'X'" in msg
    for name in ("L", "M", "S"):
        assert name in msg


def test_lowercase_name_accepted() -> None:
    assert load_window("s").name == "S"


@pytest.mark.parametrize("n", [0, 6])
def test_too_many_or_too_few_followers(n: int) -> None:
    with pytest.raises(ValueError, match="has 5 followers"):
        load_window("S", n_followers=n)


def test_real_followers_record() -> None:
    w = load_window("L")
    rec = real_followers_record(w, 4)
    assert rec.window == "L"
    assert rec.speed_mps.shape == rec.gap_m.shape == rec.accel_mps2.shape == (601, 4)
    np.testing.assert_array_equal(rec.gap_m, w.follower_gap_m[:, :4])
    d = rec.as_dict()
    assert {"speed_mps", "gap_m", "accel_mps2"} <= set(d)
    if rec.energy_kwh is not None:
        assert rec.energy_kwh.shape == (4,)
        assert np.isfinite(rec.energy_kwh).all()
    with pytest.raises(ValueError):
        real_followers_record(w, 6)
    assert real_followers_record("M").n_followers == 4


# ---------------------------------------------------------------------------------------------
# Reading and validation on hand-made files
# ---------------------------------------------------------------------------------------------


def test_header(tmp_path: Path) -> None:
    h = read_openacc_header(_write_csv(tmp_path / "a.csv", _good_rows()))
    assert h.vehicle_names == ("LEAD", "CAR_A", "CAR_B")
    assert h.n_vehicles == 3
    assert h.distance_setting == "M"
    assert h.date == "2019-10-08"
    assert h.acc_mode == "1"


def test_read_selects_columns_by_name(tmp_path: Path) -> None:
    df = read_openacc_csv(_write_csv(tmp_path / "a.csv", _good_rows()))
    assert list(df.columns) == ["Time", "Speed1", "Speed2", "Speed3", "IVS1", "IVS2"]
    assert len(df) == 10
    assert df.attrs["n_nan_filled_total"] == 0
    assert df["IVS2"].iloc[3] == 21.0


def test_short_nan_run_is_interpolated(tmp_path: Path) -> None:
    rows = _good_rows()
    # IVS2 at rows 4 and 5 (t = 100.4, 100.5) missing; neighbours 15 + 2*3 = 21 and 15 + 2*6 = 27.
    # Change the neighbours to make the line non-trivial: row 3 -> 20.0, row 6 -> 29.0.
    for i, val in ((3, "20.0"), (4, ""), (5, ""), (6, "29.0")):
        parts = rows[i].split(",")
        parts[-1] = val
        rows[i] = ",".join(parts)
    df = read_openacc_csv(_write_csv(tmp_path / "nan.csv", rows))
    # Linear between (100.3, 20) and (100.6, 29): 23 at 100.4 and 26 at 100.5.
    assert df["IVS2"].iloc[4] == pytest.approx(23.0)
    assert df["IVS2"].iloc[5] == pytest.approx(26.0)
    assert df.attrs["n_nan_filled"]["IVS2"] == 2
    assert df.attrs["n_nan_filled_total"] == 2
    assert not df.isna().any().any()


def test_nan_at_edge_takes_nearest_value(tmp_path: Path) -> None:
    rows = _good_rows()
    rows[0] = rows[0].replace("100.0,10,0,9,0,", "100.0,10,0,,0,")
    df = read_openacc_csv(_write_csv(tmp_path / "edge.csv", rows))
    assert df["Speed2"].iloc[0] == pytest.approx(10.0)
    assert df.attrs["n_nan_filled"]["Speed2"] == 1


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.csv"
    with pytest.raises(OpenACCDataError, match="nope.csv"):
        read_openacc_csv(path)


def test_missing_column(tmp_path: Path) -> None:
    rows = [r.rsplit(",", 1)[0] for r in _good_rows()]
    path = _write_csv(
        tmp_path / "nocol.csv", rows, columns="Time,Speed1,E1,Speed2,E2,Speed3,E3,IVS1\r\n"
    )
    with pytest.raises(OpenACCDataError, match=r"nocol\.csv.*IVS2"):
        read_openacc_csv(path)


def test_text_in_number_column(tmp_path: Path) -> None:
    rows = _good_rows()
    parts = rows[2].split(",")
    parts[3] = "abc"
    rows[2] = ",".join(parts)
    path = _write_csv(tmp_path / "text.csv", rows)
    with pytest.raises(OpenACCDataError, match=r"text\.csv.*'abc'.*Speed2.*line 9"):
        read_openacc_csv(path)


def test_nan_run_too_long(tmp_path: Path) -> None:
    rows = _good_rows(40)
    for i in range(5, 5 + 21):
        parts = rows[i].split(",")
        parts[1] = ""
        rows[i] = ",".join(parts)
    path = _write_csv(tmp_path / "long.csv", rows)
    with pytest.raises(OpenACCDataError, match=r"long\.csv.*Speed1.*21 missing"):
        read_openacc_csv(path)
    # A run of exactly the limit is filled.
    df = read_openacc_csv(path, max_nan_run_rows=21)
    assert df.attrs["n_nan_filled"]["Speed1"] == 21
    np.testing.assert_allclose(df["Speed1"].to_numpy(), 10.0 + np.arange(40))


def test_non_monotonic_time(tmp_path: Path) -> None:
    rows = _good_rows()
    rows[4], rows[5] = rows[5], rows[4]
    with pytest.raises(OpenACCDataError, match=r"swap\.csv.*not strictly increasing"):
        read_openacc_csv(_write_csv(tmp_path / "swap.csv", rows))


def test_bad_time_step(tmp_path: Path) -> None:
    rows = _good_rows()
    del rows[5]
    with pytest.raises(OpenACCDataError, match=r"gap\.csv.*time step"):
        read_openacc_csv(_write_csv(tmp_path / "gap.csv", rows))


def test_bad_metadata(tmp_path: Path) -> None:
    path = _write_csv(tmp_path / "meta.csv", _good_rows(), header=HEADER.replace("ACC,1", "XYZ,1"))
    with pytest.raises(OpenACCDataError, match=r"meta\.csv.*line 4"):
        read_openacc_csv(path)


def test_error_is_value_error() -> None:
    assert issubclass(OpenACCDataError, ValueError)


# --------------------------------------------------------------------------- training family
def test_dynamic_platform_profile_has_the_drawn_shape() -> None:
    from envs.scenarios import dynamic_platform_profile_mps

    u = np.array([0.5, 0.25, 0.5, 0.5, 0.5, 0.5])  # v0 9.75, brake at 6 s, 2.5 m/s^2, 5 m/s
    v = dynamic_platform_profile_mps(u, 600)
    assert v[0] == pytest.approx(9.75) and v[-1] == pytest.approx(9.75)
    assert v.min() == pytest.approx(5.0)
    a = np.diff(v) / 0.1
    assert a.min() == pytest.approx(-2.5) and a.max() == pytest.approx(1.8)
    assert np.all(v[:61] == pytest.approx(9.75))  # cruise until 6 s
    # 5 m/s held for 2 s after reaching it at 6 + 4.75 / 2.5 = 7.9 s
    assert np.all(v[80:99] == pytest.approx(5.0))


def test_real_test_windows_lie_inside_the_training_family() -> None:
    """The ranges the family draws from cover what the three real windows do."""
    from envs.scenarios import make_scenario

    for name in ("openacc-s-v1", "openacc-m-v1", "openacc-l-v1"):
        v = make_scenario(name).episodes([0], 4).leader_speed_mps[0]
        a = np.diff(v) / 0.1
        assert 7.5 <= v[0] <= 12.0
        assert 3.0 <= v.min() <= 7.0
        assert 1.5 <= -a.min() <= 3.5
        assert 0.8 <= a.max() <= 2.8
        assert 3.0 <= np.argmin(v) * 0.1 <= 15.0 + (v[0] - v.min()) / 1.5 + 4.0


@pytest.mark.parametrize(("size", "gap"), [("s", 12.0), ("m", 16.0), ("l", 20.0)])
def test_training_family_is_seeded_randomised_and_not_the_windows(size: str, gap: float) -> None:
    from envs.scenarios import make_scenario

    sc = make_scenario(f"openacc-train-{size}-v1")
    assert (sc.target_gap_m, sc.target_speed_mps, sc.default_vehicles) == (gap, 11.0, 4)
    a, b = sc.episodes([1, 2, 3], 4), sc.episodes([1, 2, 3], 4)
    np.testing.assert_array_equal(a.leader_speed_mps, b.leader_speed_mps)
    np.testing.assert_array_equal(a.gap_m, b.gap_m)
    assert len({tuple(row) for row in a.leader_speed_mps.round(6)}) == 3
    assert np.all((a.gap_m >= 0.8 * gap) & (a.gap_m <= 1.4 * gap))
    window = make_scenario(f"openacc-{size}-v1").episodes([0], 4).leader_speed_mps[0]
    many = sc.episodes(list(range(200)), 4).leader_speed_mps
    assert np.abs(many - window).max(axis=1).min() > 0.5  # no episode replays the window
