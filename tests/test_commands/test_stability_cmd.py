"""``cacc-bench stability``: files, CSV columns, and exit status 2 on bad input."""

from __future__ import annotations

import csv

import pytest

from commands.cli import main

SUMMARY = [
    "controller",
    "kind",
    "time_gap_s",
    "delay_s",
    "lag_s",
    "peak_gain",
    "peak_omega_rad_s",
    "h_min_s",
    "string_stable",
]
CURVES = ["controller", "kind", "time_gap_s", "delay_s", "lag_s", "omega_rad_s", "gain"]
SMALL = ["--n-omega", "3", "--omega-min", "0.3", "--omega-max", "1.0", "--n-vehicles", "3"]


def read(path):
    with path.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], [dict(zip(rows[0], r)) for r in rows[1:]]


def test_analytic_and_empirical(tmp_path, capsys):
    rc = main(
        ["stability", "--out", str(tmp_path), "--controllers", "cacc,acc", "--empirical", *SMALL]
    )
    assert rc == 0
    header, summary = read(tmp_path / "stability_summary.csv")
    assert header == SUMMARY
    kinds = {(r["controller"], r["kind"]) for r in summary}
    assert kinds == {
        ("cacc", "analytic"),
        ("acc", "analytic"),
        ("cacc", "empirical"),
        ("acc", "empirical"),
    }
    by = {(r["controller"], r["kind"]): r for r in summary}
    assert float(by["cacc", "analytic"]["peak_gain"]) == pytest.approx(1.0486, abs=1e-3)
    assert float(by["cacc", "analytic"]["h_min_s"]) == pytest.approx(0.779, abs=1e-3)
    assert float(by["acc", "analytic"]["h_min_s"]) == pytest.approx(3.162, abs=1e-3)
    assert by["cacc", "empirical"]["h_min_s"] == ""
    assert by["acc", "analytic"]["string_stable"] == "False"
    header, curves = read(tmp_path / "stability.csv")
    assert header == CURVES
    assert sum(r["kind"] == "empirical" for r in curves) == 6
    assert {r["kind"] for r in curves} == {"analytic", "empirical"}
    for stem in ("gamma_time_gaps", "h_min_delay", "peak_gain_grid", "gamma_empirical"):
        for ext in ("png", "pdf"):
            assert (tmp_path / f"{stem}.{ext}").stat().st_size > 0
    out = capsys.readouterr().out
    assert "analytic sweep" in out and "empirical sweep of cacc" in out


def test_analytic_only_and_options(tmp_path):
    rc = main(
        [
            "stability",
            "--out",
            str(tmp_path),
            "--controllers",
            "cacc:kp=0.3",
            "--time-gap",
            "1.0",
            "--delay",
            "0.1",
            "--lag",
            "0",
        ]
    )
    assert rc == 0
    _, summary = read(tmp_path / "stability_summary.csv")
    assert len(summary) == 1
    row = summary[0]
    assert row["controller"] == "cacc[kp=0.3]" and row["kind"] == "analytic"
    assert float(row["time_gap_s"]) == 1.0 and float(row["delay_s"]) == 0.1
    assert row["string_stable"] == "True"
    assert not (tmp_path / "gamma_empirical.png").exists()


def test_nonlinear_controller_is_measured_only(tmp_path):
    rc = main(["stability", "--out", str(tmp_path), "--controllers", "ovm", "--empirical", *SMALL])
    assert rc == 0
    _, summary = read(tmp_path / "stability_summary.csv")
    assert [(r["controller"], r["kind"]) for r in summary] == [("ovm", "empirical")]
    assert summary[0]["time_gap_s"] == "" and summary[0]["h_min_s"] == ""


@pytest.mark.parametrize(
    "args",
    [
        ["--controllers", "nosuch"],
        ["--delay", "-0.1"],
        ["--time-gap", "-1"],
        ["--lag", "-0.1"],
        ["--lag", "5"],  # kd <= lag kp: unstable loop
        ["--controllers", "cacc:kp=abc"],
        ["--controllers", "cacc:kp=-1"],
        ["--delay", "abc"],
        ["--empirical", "--omega-max", "50"],
    ],
)
def test_bad_input_exit_2(tmp_path, args, capsys):
    assert main(["stability", "--out", str(tmp_path), *args]) == 2
    err = capsys.readouterr().err
    if args[:2] == ["--controllers", "nosuch"]:
        assert "cacc" in err and "acc" in err
