"""The standard frequency sweep every leaderboard row carries (benchmark.sweep): equal to the
analytic |Gamma(jw)| for the linear laws, consistent with the time-domain gain on sine-v1, cached
per configuration, and the leaderboard's columns, mark and --rank-by."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from analysis.stability import PloegLoop, discrete_gamma_response
from benchmark import sweep as sw
from benchmark.export import LEADERBOARD_METRICS, SWEEP_COLUMNS, leaderboard_frame
from benchmark.rollout import rollout
from benchmark.string_gain import time_domain_string_gain
from controllers.registry import make_controller
from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.scenarios import make_scenario
from infra.errors import ConfigError

#: The sweep of a linear law against its exact discrete |Gamma(e^{jw dt})| on the grid, relative:
#: cacc's transient is gone after SWEEP_TRANSIENT_S (measured at most 1e-5), acc's, which grows
#: down the string, is not quite (measured 2.1e-3 ideal, 6.2e-3 with 0.2 s delay and 0.1 s lag).
CACC_RTOL = 1e-4
ACC_RTOL = 1e-2
#: The time-domain gain over the follower pairs of one sine-v1 episode (the sweep's amplitude, a
#: frequency of the grid) against the sweep's value there, relative, at the frequency where the
#: sweep peaks (there the disturbance reaches the platoon's tail, so the sinusoid dominates every
#: follower's acceleration; where it dies out, the start's transient sets the time-domain ratio).
#: Measured at most 2.0 % (duty), acc 1.5 %, ovm 0.9 %, cacc 0.3 %.
TIME_DOMAIN_RTOL = 0.03


@pytest.mark.parametrize("name", ["cacc", "acc"])
@pytest.mark.parametrize(("delay", "lag"), [(0.0, 0.0), (0.2, 0.1)])
def test_the_sweep_of_the_linear_laws_is_their_analytic_gain(name: str, delay: float,
                                                             lag: float) -> None:
    res = sw.sweep_peak(name, n_vehicles=8, comm_delay_s=delay, lag_s=lag)
    loop = PloegLoop.from_controller(make_controller(name), delay, lag)
    exact = np.abs(discrete_gamma_response(np.asarray(sw.SWEEP_OMEGAS_RAD_S), loop))
    rtol = CACC_RTOL if name == "cacc" else ACC_RTOL
    np.testing.assert_allclose(res.gains_per_omega, exact, rtol=rtol)
    assert res.peak_gain == pytest.approx(float(exact.max()), rel=rtol)
    assert res.omega_at_peak_rad_s == sw.SWEEP_OMEGAS_RAD_S[int(np.argmax(exact))]
    assert not res.collided and not res.saturated
    # the verdicts of the analysis: cacc string stable with ideal V2V only, acc never
    assert res.string_stable == (name == "cacc" and delay == 0.0)


@pytest.mark.parametrize(("name", "options", "delay", "lag"), [
    ("cacc", {}, 0.0, 0.0), ("cacc", {}, 0.2, 0.1), ("acc", {}, 0.0, 0.0), ("ovm", {}, 0.0, 0.0),
    ("duty", {"k": 4}, 0.0, 0.0),
])
def test_the_time_domain_gain_on_sine_v1_is_the_sweep_at_its_peak(name, options, delay, lag):
    """One sine-v1 episode at the sweep's peak frequency and amplitude: the time-domain gain of
    its followers (benchmark.string_gain) is the sweep's value within TIME_DOMAIN_RTOL."""
    res = sw.sweep_peak(name, options, n_vehicles=8, comm_delay_s=delay, lag_s=lag)
    w = res.omega_at_peak_rad_s
    sc = make_scenario("sine-v1", amplitude_mps=sw.SWEEP_LEADER_ACCEL_MPS2 / w,
                       frequency_hz=w / (2 * math.pi))
    params = PlatoonParams(lag_s=lag)
    traj = rollout(make_controller(name, **options), sc, 8, 2000, params,
                   ChannelConfig(delay, 0.0, params.dt_s))
    followers = time_domain_string_gain(traj.accel_mps2[1:])
    assert followers == pytest.approx(res.peak_gain, rel=TIME_DOMAIN_RTOL)


def test_the_grid_and_its_constants() -> None:
    assert sw.SWEEP_FREQUENCIES_HZ == (0.05, 0.1, 0.2, 0.4)
    assert 0.2 in sw.SWEEP_FREQUENCIES_HZ  # sine-v1's own frequency is on the grid
    assert sw.SWEEP_TRANSIENT_S + sw.SWEEP_WINDOW_S == make_scenario("sine-v1").n_steps * 0.1
    assert sw.SWEEP_WINDOW_S >= 1.0 / min(sw.SWEEP_FREQUENCIES_HZ)  # a whole period is fitted


def test_a_sampled_policy_is_measured_as_it_ran(monkeypatch) -> None:
    """bdc (sampled, adapts to the scenario) is swept with the checkpoint of the row's
    scenario, over SWEEP_REPLICAS episodes per frequency; the label stays the run's."""
    seen = {}
    real = sw.measure_gains

    def spy(ctrl, *args, **kwargs):
        seen["replicas"], seen["scenario"] = kwargs["replicas"], ctrl.scenario
        return real(ctrl, *args, **kwargs)

    monkeypatch.setattr(sw, "measure_gains", spy)
    res = sw.sweep_peak("bdc", n_vehicles=8, scenario="catchup-v1")
    assert seen == {"replicas": sw.SWEEP_REPLICAS, "scenario": "catchup-v1"}
    assert res.controller == "bdc" and res.scenario == "catchup-v1" and res.policy_sha256
    assert math.isfinite(res.peak_gain)
    with pytest.raises(ConfigError, match="changed since its runs"):
        sw.sweep_peak("bdc", n_vehicles=8, scenario="catchup-v1", policy_sha256="0" * 64)
    assert not sw.adapts_to_scenario("bdc", {"scenario": "slowdown-v1"})
    assert sw.adapts_to_scenario("duty", {}) and not sw.adapts_to_scenario("duty", {"k": 3})
    assert not sw.adapts_to_scenario("cacc", {})


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ConfigError):
        sw.sweep_peak("cacc", comm_delay_s=0.15)  # not whole steps
    with pytest.raises(ConfigError):
        sw.sweep_peak("cacc", packet_loss=1.5)
    with pytest.raises(ConfigError):
        sw.sweep_peak("cacc", n_vehicles=1)
    with pytest.raises(ConfigError, match="recorded platoon"):
        sw.sweep_peak("openacc-real", n_vehicles=4)


# ------------------------------------------------------------------------------------ cache


def _record(controller: str, scenario: str, seed: int = 2000, **extra) -> dict:
    rec = {"controller": controller, "name": controller, "options": "{}", "scenario": scenario,
           "n_vehicles": 8, "comm_delay_s": 0.0, "packet_loss": 0.0, "lag_s": 0.0,
           "seed": seed, "status": "ok", "policy_sha256": "", "family": "linear",
           "deterministic": True, "collision": False, "solver_failures": 0,
           "string_stable": True}
    rec.update(extra)
    return rec


def test_one_sweep_per_configuration_cached_in_the_folder(tmp_path: Path, monkeypatch) -> None:
    calls = []
    real = sw.measure_gains

    def counting(ctrl, *args, **kwargs):
        calls.append(ctrl.name)
        return real(ctrl, *args, **kwargs)

    monkeypatch.setattr(sw, "measure_gains", counting)
    records = [_record("cacc", sc, seed) for sc in ("catchup-v1", "slowdown-v1")
               for seed in (2000, 2010)]
    cache = sw.SweepCache(tmp_path)
    found = sw.row_sweeps(records, cache)
    assert calls == ["cacc"]  # two scenarios, two seeds: one configuration, one sweep
    assert len(found) == 2 and len({id(v) for v in found.values()}) == 1
    cache.save()
    data = json.loads((tmp_path / sw.CACHE_NAME).read_text())
    assert data["format"] == sw.SweepCache.FORMAT and len(data["entries"]) == 1
    again = sw.row_sweeps(records, sw.SweepCache(tmp_path))
    assert calls == ["cacc"]  # read back, not measured again
    assert again == found


@pytest.mark.parametrize("text", [
    "{not json", json.dumps([1, 2]), json.dumps({"format": "other", "entries": []}),
    json.dumps({"format": "cacc-bench string sweeps", "entries": [{"controller": "cacc"}]}),
])
def test_a_damaged_cache_is_refused_in_one_line(tmp_path: Path, text: str) -> None:
    (tmp_path / sw.CACHE_NAME).write_text(text)
    with pytest.raises(ConfigError, match="string-sweep cache .* is damaged") as err:
        sw.SweepCache(tmp_path)
    assert "\n" not in str(err.value) and "remove it" in str(err.value)


def test_the_cache_round_trips_a_collision(tmp_path: Path) -> None:
    res = sw.SweepResult("acc", "", 12, 0.2, 0.3, 0.5, "", sw.SWEEP_OMEGAS_RAD_S,
                         (1.2, math.nan, 0.5, 0.2), math.inf, sw.SWEEP_OMEGAS_RAD_S[1],
                         True, True)
    cache = sw.SweepCache(tmp_path)
    cache[res.key] = res
    cache.save()
    back = sw.SweepCache(tmp_path)[res.key]
    assert back.peak_gain == math.inf and not back.string_stable
    assert back.gains_per_omega[0] == 1.2 and math.isnan(back.gains_per_omega[1])


def test_the_cli_refuses_a_damaged_cache_before_any_run(tmp_path: Path, capsys) -> None:
    from commands.cli import main

    (tmp_path / sw.CACHE_NAME).write_text("{broken")
    rc = main(["run", "--controllers", "cacc", "--scenarios", "catchup-v1", "--episodes", "1",
               "--vehicles", "4", "--out", str(tmp_path), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "string-sweep cache" in err[0]
    assert not (tmp_path / "store.sqlite").exists()  # refused before the store was made


# ------------------------------------------------------------------------------ leaderboard


def _runs(rows: list[tuple[str, float]]) -> pd.DataFrame:
    out = []
    for name, reward in rows:
        rec = _record(name, "catchup-v1")
        for m in LEADERBOARD_METRICS:
            rec[m] = 1.0
        rec["reward"] = reward
        out.append(rec)
    return pd.DataFrame(out)


def _result(label: str, peak: float) -> sw.SweepResult:
    return sw.SweepResult(label, "", 8, 0.0, 0.0, 0.0, "", sw.SWEEP_OMEGAS_RAD_S,
                          (peak, 0.9, 0.8, 0.7), peak, sw.SWEEP_OMEGAS_RAD_S[0],
                          math.isinf(peak), False)


def test_the_leaderboard_carries_the_sweep_and_ranks_by_it() -> None:
    runs = _runs([("fast_unstable", -100.0), ("slow_stable", -200.0), ("unknown", -50.0)])
    sweeps = {sw.row_key(r): (None if r["controller"] == "unknown" else
                              _result(r["controller"],
                                      1.3 if r["controller"] == "fast_unstable" else 1.005))
              for r in runs.to_dict("records")}
    plain = leaderboard_frame(runs)
    assert not set(SWEEP_COLUMNS) & set(plain.columns)  # without sweeps: as before
    lb = leaderboard_frame(runs, sweeps=sweeps).set_index("controller")
    assert lb.loc["fast_unstable", "sweep_peak_gain"] == 1.3
    assert lb.loc["fast_unstable", "sweep_string_stable"] == False  # noqa: E712
    assert lb.loc["slow_stable", "sweep_string_stable"] == True  # noqa: E712 - within 1 + tol
    assert math.isnan(lb.loc["unknown", "sweep_peak_gain"])
    assert lb.loc["unknown", "sweep_string_stable"] is None
    assert lb["rank"].to_dict() == {"unknown": 1, "fast_unstable": 2, "slow_stable": 3}
    ss = leaderboard_frame(runs, sweeps=sweeps, rank_by="string-stability")
    assert ss.set_index("controller")["rank"].to_dict() == {
        "slow_stable": 1, "unknown": 2, "fast_unstable": 3}
    with pytest.raises(ConfigError, match="rank by one of"):
        leaderboard_frame(runs, rank_by="speed")


def test_a_pooled_row_takes_its_worst_training_seed() -> None:
    rows = []
    for seed in (0, 1, 2):
        for k in range(2):
            rec = _record(f"bdc[seed={seed}]" if seed else "bdc", "catchup-v1", 2000 + 10 * k,
                          family="marl", name="bdc", controller_name="bdc",
                          options=json.dumps({"seed": seed} if seed else {}))
            for m in LEADERBOARD_METRICS:
                rec[m] = 1.0
            rows.append(rec)
    runs = pd.DataFrame(rows)
    peaks = {"bdc": 1.1, "bdc[seed=1]": 1.4, "bdc[seed=2]": 0.99}
    sweeps = {sw.row_key(r): _result(r["controller"], peaks[r["controller"]])
              for r in runs.to_dict("records")}
    lb = leaderboard_frame(runs, pool_seeds=True, sweeps=sweeps)
    assert len(lb) == 1 and lb["sweep_peak_gain"].iloc[0] == 1.4
    assert lb["sweep_string_stable"].iloc[0] == False  # noqa: E712


def test_the_tables_show_the_mark() -> None:
    from analysis.tables import format_leaderboard, markdown_leaderboard

    runs = _runs([("a", -100.0), ("b", -200.0)])
    sweeps = {sw.row_key(r): _result(r["controller"], 0.99 if r["controller"] == "a" else math.inf)
              for r in runs.to_dict("records")}
    lb = leaderboard_frame(runs, sweeps=sweeps)
    md = markdown_leaderboard(lb)
    assert "| time-domain string gain | sweep peak | string stable |" in md
    assert "| 0.990 | yes |" in md and "| collides | **no** |" in md
    assert "sweep peak" not in markdown_leaderboard(leaderboard_frame(runs))
    text = format_leaderboard(lb)
    assert "0.990 yes" in text and "collides no" in text


# ------------------------------------------------------------------------- the README's table


def _readme_sweeps() -> dict[str, tuple[str, str]]:
    """The README main table's sweep peak and mark of each controller label."""
    import re

    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    head = next(ln for ln in text.splitlines() if ln.startswith("| scenario | rank |"))
    cols = [c.strip() for c in head.strip("|").split("|")]
    out = {}
    for ln in text.splitlines():
        if re.match(r"^\| catchup-v1 \| \d+ \| `", ln):
            cells = [c.strip() for c in ln.strip("|").split("|")]
            row = dict(zip(cols, cells, strict=True))
            out[row["controller"].strip("`")] = (row["sweep peak"], row["string stable"])
    return out


@pytest.mark.parametrize(("label", "name", "options"), [
    ("cacc", "cacc", {}), ("ovm", "ovm", {}), ("duty", "duty", {})])
def test_the_readme_sweep_column_is_the_sweep(label: str, name: str, options: dict) -> None:
    """The README main table (catchup-v1, N = 8, ideal V2V): the sweep peak and the mark of the
    cheap deterministic rows are what sweep_peak measures (duty with the period it picks on
    catchup-v1)."""
    peak, mark = _readme_sweeps()[label]
    res = sw.sweep_peak(name, options, n_vehicles=8, scenario="catchup-v1")
    assert peak == f"{res.peak_gain:.3f}"
    assert mark == ("yes" if res.string_stable else "**no**")


@pytest.mark.parametrize("variant", ["residual-timed", "residual-cacc"])
def test_the_readme_sweep_of_a_pooled_policy_is_its_worst_seed(variant: str) -> None:
    """A pooled learned row's sweep peak is the largest of its three training seeds' sweeps,
    recomputed from the shipped checkpoints (within 0.05 %: across CPUs)."""
    peak, mark = _readme_sweeps()[f"ippo[seeds=0+1+2,variant={variant}]"]
    peaks = [sw.sweep_peak("ippo", {"variant": variant, "seed": str(s)}, n_vehicles=8,
                           scenario="catchup-v1").peak_gain for s in (0, 1, 2)]
    assert max(peaks) == pytest.approx(float(peak), rel=5e-4, abs=5e-4)
    assert mark == "**no**" and max(peaks) > 1.0 + sw.SWEEP_TOL
