"""``cacc-bench plot`` on a results folder: the time-space diagram and the per-vehicle figure of
every setting, several seeds, the sweep figure when sweep data exist, the radar left out for one
controller; each figure read back through what it drew."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import analysis.plots as plots
from commands.cli import main

SWEEP = ["run", "--controllers", "cacc,ovm", "--scenarios", "slowdown-v1", "--vehicles", "3",
         "--seeds", "2000,2001,2002", "--quiet"]


@pytest.fixture
def captured(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """The figures ``plot`` draws, by file stem (nothing is written)."""
    figs: dict[str, Any] = {}

    def keep(fig: Any, out_dir: Path, stem: str) -> list[Path]:
        figs[stem] = fig
        return [out_dir / f"{stem}.png"]

    monkeypatch.setattr(plots, "_save", keep)
    yield figs
    for fig in figs.values():
        plots._plt().close(fig)


def test_plot_draws_the_platoon_figures_for_several_seeds(
        tmp_path: Path, captured: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "r"
    assert main([*SWEEP, "--trajectories", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["plot", str(out), "--seeds", "2", "--no-energy-map",
                 "--out", str(tmp_path / "f")]) == 0
    said = capsys.readouterr().out
    stems = sorted(captured)
    for c in ("cacc", "ovm"):
        for seed in (2000, 2001):  # the store keeps 2000's; 2001 from the trajectory CSV
            stem = f"{c}__slowdown-v1__n3__d0.0__l0.0__tau0.0__s{seed}"
            assert f"timeseries__{stem}" in stems and f"timespace__{stem}" in stems
        assert f"timespace__{c}__slowdown-v1__n3__d0.0__l0.0__tau0.0__s2002" not in stems
    # the time-space diagram: the leader's position is the integral of its speed
    import pandas as pd

    csv = pd.read_csv(out / "trajectories" / "cacc__slowdown-v1__n3__s2001.csv")
    xt = captured["timespace__cacc__slowdown-v1__n3__d0.0__l0.0__tau0.0__s2001"]
    lead = [ln for ln in xt.axes[0].get_lines() if ln.get_label() == "leader"][0]
    np.testing.assert_allclose(lead.get_ydata(), csv[csv.vehicle == 0]["position_m"], atol=1e-5)
    # the per-vehicle figure: both controllers, two seeds each, cacc against its own policy
    pv = captured["per_vehicle__slowdown-v1__n3"]
    assert len(pv.axes[0].get_lines()) == 4
    names = [t.get_text() for t in pv.axes[0].get_legend().get_texts()]
    assert names == ["cacc [own policy: 12.5 m + 0.5 s x v]", "ovm [published target 20 m]"]
    # the time series of cacc draws its own target, the published one named as such
    ts = captured["timeseries__cacc__slowdown-v1__n3__d0.0__l0.0__tau0.0__s2000"]
    labels = [ln.get_label() for ln in ts.axes[0].get_lines()]
    assert "published reward target 20 m" in labels
    assert "own policy (cacc): 12.5 m + 0.5 s x v" in labels
    assert "radar__slowdown-v1__n3" in stems
    from benchmark.sweep import CACHE_NAME

    assert ("gain-against-frequency figure skipped" in said) != (out / CACHE_NAME).exists()


def test_plot_asks_for_more_seeds_than_stored_and_says_so(
        tmp_path: Path, captured: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "r"
    one = [a if a != "cacc,ovm" else "cacc" for a in SWEEP]
    assert main([*one, "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["plot", str(out), "--seeds", "3", "--no-energy-map",
                 "--out", str(tmp_path / "f")]) == 0
    said = capsys.readouterr().out
    assert "--seeds 3: fewer seeds have a trajectory for cacc on slowdown-v1 (N=3): 1" in said
    assert "run --trajectories" in said
    # one controller: no radar (it would be the full diamond), and a line that says why
    assert not [s for s in captured if s.startswith("radar")]
    assert "radar of slowdown-v1, N=3 skipped: 1 controller" in said
    assert main(["plot", str(out), "--seeds", "0"]) == 2


def test_plot_draws_gain_against_frequency_from_the_sweep_cache(
        tmp_path: Path, captured: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    from analysis.stability import PloegLoop, gamma_response
    from benchmark.sweep import SWEEP_OMEGAS_RAD_S, SweepCache, SweepResult

    out = tmp_path / "r"
    assert main([*[a if a != "cacc,ovm" else "cacc" for a in SWEEP], "--out", str(out)]) == 0
    omegas = tuple(SWEEP_OMEGAS_RAD_S)
    gains = tuple(float(g) for g in np.abs(gamma_response(np.array(omegas), PloegLoop())))
    cache = SweepCache(out)
    fields = {"controller": "cacc", "n_vehicles": 3, "comm_delay_s": 0.0, "packet_loss": 0.0,
              "lag_s": 0.0, "policy_sha256": "", "omegas_rad_s": omegas,
              "gains_per_omega": gains, "peak_gain": max(gains),
              "omega_at_peak_rad_s": omegas[int(np.argmax(gains))], "collided": False,
              "saturated": False, "scenario": ""}
    import dataclasses

    res = SweepResult(**{f.name: fields[f.name] for f in dataclasses.fields(SweepResult)
                         if f.name in fields})
    cache[res.key] = res
    cache.save()
    capsys.readouterr()
    assert main(["plot", str(out), "--no-energy-map", "--out", str(tmp_path / "f")]) == 0
    fig = next(f for stem, f in captured.items() if stem.startswith("gain_frequency__"))
    line = [ln for ln in fig.axes[0].get_lines() if ln.get_label() == "cacc"][0]
    np.testing.assert_allclose(line.get_xdata(), omegas)
    np.testing.assert_allclose(line.get_ydata(), gains)
    assert "gain-against-frequency figure skipped" not in capsys.readouterr().out
