"""Issue 53, point 5: the cases of the fresh probe (``test_probe_round3.py``) that it had no
test for, now refused before any work with exit 2 and one line, or reported as what they are:
a bound on a time gap, a scenario of one's own checked when it is loaded and built once before
any run, a controller's failure in ``stability``/``perf`` in one line and in ``run`` as the
run's (a wrong dtype, ``sys.exit()`` in ``act``), a plug-in scenario named by its reference in
``train`` and ``penetration``, ``list`` giving the sumo extra's install command, a recorded
platoon refused where its rows would be mislabelled, a sweep cache's peak checked against its
gains, and the lock file a report folder under ``docs/`` keeps ignored by git."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from commands.cli import main as cli
from controllers import registry

ROOT = Path(__file__).resolve().parents[2]
HAS_SUMO = all(importlib.util.find_spec(m) is not None for m in ("libsumo", "sumo"))
SMALL = ["--scenarios", "catchup-v1", "--vehicles", "2", "--episodes", "1", "--quiet"]


def _exit_code(argv: list[str]) -> int:
    try:
        return cli(argv)
    except SystemExit as exc:  # a command that ended the process: the bug these tests catch
        pytest.fail(f"the command raised SystemExit({exc.code!r})")


def _one_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert lines and lines[-1].startswith("cacc-bench: error: "), err
    assert sum(line.startswith("cacc-bench") for line in lines) == 1, err
    return lines[-1]


# ------------------------------------------------------------------- user modules of the tests
LAWS = '''
import sys

import numpy as np

from controllers.base import Controller


class Zero(Controller):
    """Always zero."""

    family = "linear"

    def reset(self, ctx):
        pass

    def act(self, state, observation):
        return np.zeros_like(state.gap_m)


class Boom(Zero):
    def act(self, state, observation):
        raise RuntimeError("boom in act")


class Words(Zero):
    def act(self, state, observation):
        return np.full(state.gap_m.shape, "brake")


class Exits(Zero):
    def act(self, state, observation):
        sys.exit(3)
'''

SCENARIOS = '''
import sys

import numpy as np

from envs.scenarios import EpisodeBatch, ScenarioSpec


def _flat(sc, seeds, u, n):
    b = len(seeds)
    return EpisodeBatch(np.asarray(seeds), np.asarray(u), np.full((b, n), sc.target_gap_m),
                        np.full((b, n), sc.target_speed_mps),
                        np.full((b, sc.n_steps + 1), sc.target_speed_mps))


def _fails(sc, seeds, u, n):
    raise RuntimeError("builder boom")


def _wide(sc, seeds, u, n):
    b = len(seeds)
    return EpisodeBatch(np.asarray(seeds), np.asarray(u), np.full((b, n + 1), 20.0),
                        np.full((b, n), 15.0), np.full((b, sc.n_steps + 1), 15.0))


def _exits(opts):
    sys.exit(5)


HILL = ScenarioSpec("hill-v1", "a flat hill", 20.0, 15.0, 50, _flat, defaults={"grade": 0.0})
NEG = ScenarioSpec("neg-v1", "x", 20.0, 15.0, -3, _flat)
HALF = ScenarioSpec("half-v1", "x", 20.0, 15.0, 300.5, _flat)
HUGE = ScenarioSpec("huge-v1", "x", 20.0, 15.0, 10**12, _flat)
MANY = ScenarioSpec("many-v1", "x", 20.0, 15.0, 50, _flat, default_vehicles=10**6)
NANGAP = ScenarioSpec("nangap-v1", "x", float("nan"), 15.0, 50, _flat)
FIXED = ScenarioSpec("fixed-v1", "x", 20.0, 15.0, 50, _flat, fixed={"cavs": 1})
FAILS = ScenarioSpec("fails-v1", "x", 20.0, 15.0, 50, _fails)
WIDE = ScenarioSpec("wide-v1", "x", 20.0, 15.0, 50, _wide)
EXITS = ScenarioSpec("exits-v1", "x", 20.0, 15.0, 50, _flat, check=_exits)


class NotASpec:
    pass
'''


@pytest.fixture
def user_code(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The user's modules in the working directory, loaded afresh by each test."""
    import envs.scenarios

    (tmp_path / "laws_h9.py").write_text(LAWS)
    (tmp_path / "scen_h9.py").write_text(SCENARIOS)
    (tmp_path / "kbi_h9.py").write_text("raise KeyboardInterrupt\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(registry, "_PLUGINS", {})
    monkeypatch.setattr(envs.scenarios, "_PLUGINS", {})
    for name in ("laws_h9", "scen_h9", "kbi_h9"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    return tmp_path


# -------------------------------------------------------------- stability and perf (points 2, 7)
def test_stability_refuses_a_time_gap_beyond_any_platoon(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--time-gap 1e308`` ran with overflow warnings and exit 0 (NaN gains)."""
    out = tmp_path / "s"
    assert _exit_code(["stability", "--time-gap", "1e308", "--out", str(out)]) == 2
    assert "--time-gap must be at most 10 s, got 1e+308" in _one_line(capsys.readouterr().err)
    assert not out.exists()


@pytest.mark.parametrize("argv", [
    ["stability", "--controllers", "laws_h9:Boom", "--empirical", "--n-omega", "2",
     "--out", "s"],
    ["perf", "--quick", "--only", "controllers", "--controllers", "laws_h9:Boom"],
], ids=["stability", "perf"])
def test_a_controller_raising_in_act_is_one_line_before_any_work(
        argv: list[str], user_code: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(argv) == 2
    line = _one_line(capsys.readouterr().err)
    assert "controller laws_h9:Boom failed in its first 10 steps" in line
    assert "(RuntimeError: boom in act)" in line
    assert not (user_code / "s").exists()


# ---------------------------------------------- a controller's failure inside run (point 10)
@pytest.mark.parametrize("law, error", [
    ("Words", "ControllerContractError: laws_h9:Words: act returned values of dtype <U5, "
              "expected (B, N) = (1, 2) accelerations as real numbers (float)"),
    ("Exits", "ControllerContractError: laws_h9:Exits: act called sys.exit(3); a controller "
              "reports a failure by raising an exception, never by ending the process"),
])
def test_a_wrong_dtype_or_sys_exit_in_act_is_the_runs_failure(
        law: str, error: str, user_code: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Strings gave a raw ``TypeError: ufunc 'isfinite'`` as the failure; ``sys.exit(3)``
    inside ``act`` ended ``run`` with status 3 and no word. Now both are the run's failure
    (stored, exit 1 as for any failed run), and the command goes on to write its tables."""
    from benchmark.store import ResultStore

    assert _exit_code(["run", "--controllers", f"laws_h9:{law}", *SMALL, "--out", "o"]) == 1
    assert error in capsys.readouterr().err
    with ResultStore(user_code / "o", create=False) as store:
        records = store.records()
    assert [r["status"] for r in records] == ["failed"] and records[0]["error"] == error
    assert (user_code / "o" / "runs.csv").exists()


def test_a_keyboard_interrupt_raised_at_import_is_not_taken_for_a_signal(
        user_code: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It was reported as "interrupted (SIGINT)" with status 130."""
    assert _exit_code(["run", "--controllers", "kbi_h9:Law", *SMALL, "--out", "o"]) == 2
    assert _one_line(capsys.readouterr().err) == (
        "cacc-bench: error: controller kbi_h9:Law: importing kbi_h9 failed (it raised "
        "KeyboardInterrupt itself; no signal was received)")
    assert not (user_code / "o").exists()


# ---------------------------------------------------- a scenario of one's own (point 3)
@pytest.mark.parametrize("name, message", [
    ("NEG", "its n_steps must be a whole number of 0.1 s steps in 1..6000, got -3"),
    ("HALF", "its n_steps must be a whole number of 0.1 s steps in 1..6000, got 300.5"),
    ("HUGE", "its n_steps must be a whole number of 0.1 s steps in 1..6000, got 1000000000000"),
    ("MANY", "its default_vehicles must be a whole number from 2 to 64, got 1000000"),
    ("NANGAP", "its target_gap_m must be a finite number in (0, 100] m, got nan"),
    ("FIXED", "its fixed name cavs, an option every scenario takes"),
    ("FAILS", "scenario scen_h9:FAILS: building an episode with N = 8 failed (RuntimeError: "
              "builder boom); fix its builder"),
    ("WIDE", "its builder's gap_m has shape (1, 9), expected (1, 8)"),
    ("EXITS", "scenario scen_h9:EXITS: its check of the options failed (it called "
              "sys.exit(5))"),
    ("NotASpec", "scenario scen_h9:NotASpec: NotASpec is a class, not a ScenarioSpec"),
])
def test_a_broken_scenario_spec_is_refused_before_any_run(
        name: str, message: str, user_code: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """n_steps of -3, 300.5 or 10**12 and a builder that fails became failed runs (one asked
    for 7 TiB); 10**6 followers ran, then the stored record was refused."""
    assert _exit_code(["run", "--controllers", "cacc", "--scenarios", f"scen_h9:{name}",
                       "--episodes", "1", "--quiet", "--out", "o"]) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert not (user_code / "o").exists()


def test_a_sound_scenario_of_ones_own_still_runs(user_code: Path) -> None:
    from envs.scenarios import make_scenario

    sc = make_scenario("scen_h9:HILL", grade="0.5")
    assert (sc.id, sc.label, sc.base_name) == ("hill-v1", "scen_h9:HILL[grade=0.5]",
                                                "scen_h9:HILL")
    assert make_scenario("catchup-v1").base_name == "catchup-v1"
    assert _exit_code(["run", "--controllers", "cacc", "--scenarios", "scen_h9:HILL",
                       "--vehicles", "2", "--episodes", "1", "--quiet", "--out", "o"]) == 0


def test_training_on_a_scenario_named_by_its_reference_says_how(
        user_code: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It advised "train on hill-v1", an id that names nothing."""
    assert _exit_code(["train", "--algo", "ippo", "--scenario", "scen_h9:HILL", "--vehicles",
                       "2", "--steps", "4096", "--out", "t"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "scen_h9:HILL is a scenario of your own whose id hill-v1 names nothing by itself" in line
    assert "entry-point group cacc_bench.scenarios" in line and not (user_code / "t").exists()


def test_penetration_builds_a_scenario_of_ones_own_by_its_reference(
        user_code: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It said "unknown scenario 'hill-v1'"; now the reference is built (and an option the
    study sets itself is refused as for a built-in)."""
    assert _exit_code(["penetration", "--scenarios", "scen_h9:HILL:cavs=1", "--episodes", "1",
                       "--out", "p"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "--scenarios scen_h9:HILL[cavs=1]: the study sets which followers are automated" in line


# -------------------------------------------------------------- cacc's bounds (point 4)
def test_the_linear_laws_spacing_bounds_are_the_one_constant() -> None:
    from controllers.linear import PloegConfig
    from infra import limits
    from infra.errors import ConfigError

    assert PloegConfig(time_gap_s=limits.MAX_TIME_GAP_S, standstill_m=limits.MAX_SPACING_M)
    with pytest.raises(ConfigError, match=r"time_gap_s must be at most 10 s, got 10\.001"):
        PloegConfig(time_gap_s=10.001)
    with pytest.raises(ConfigError, match=r"standstill_m must be at most 100 m, got 100\.5"):
        PloegConfig(standstill_m=100.5)
    if HAS_SUMO:
        from controllers import sumo_models

        assert (sumo_models.MAX_TIME_GAP_S, sumo_models.MAX_DISTANCE_M) == (
            limits.MAX_TIME_GAP_S, limits.MAX_SPACING_M)


# -------------------------------------------------------- the sweep cache's peak (point 5)
def _entry() -> dict[str, object]:
    from benchmark.sweep import SweepResult, _encode

    return _encode(SweepResult(
        controller="acc", scenario="", n_vehicles=2, comm_delay_s=0.0, packet_loss=0.0,
        lag_s=0.0, policy_sha256="", omegas_rad_s=(0.1, 0.5, 1.0),
        gains_per_omega=(0.9, 1.2, float("nan")), peak_gain=1.2, omega_at_peak_rad_s=0.5,
        collided=False, saturated=False))


@pytest.mark.parametrize("change, message", [
    ({"peak_gain": 1e308}, "not the largest of its gains"),
    ({"peak_gain": 0.9}, "not the largest of its gains"),
    ({"omega_at_peak_rad_s": 0.1}, "not the largest of its gains (1.2) at its frequency"),
    ({"omega_at_peak_rad_s": 0.7}, "the frequency of its peak is not one of its frequencies"),
    ({"peak_gain": math.inf}, "not the largest of its gains"),
])
def test_a_cached_peak_must_be_the_largest_measured_gain(change: dict[str, object],
                                                           message: str) -> None:
    from benchmark.sweep import _decode

    assert _decode(_entry()).peak_gain == 1.2  # as measured: read back
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        _decode({**_entry(), **change})


# ------------------------------------------------- list without the sumo extra (point 9)
NO_SUMO = '''
import sys
from importlib.machinery import PathFinder


class _NoSumo(PathFinder):
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name.split(".")[0] in ("libsumo", "sumo", "traci", "sumolib"):
            return None
        return super().find_spec(name, path, target)


sys.meta_path[:] = [_NoSumo if f is PathFinder else f for f in sys.meta_path]
'''


def test_list_without_the_sumo_extra_gives_its_install_command(tmp_path: Path) -> None:
    (tmp_path / "sitecustomize.py").write_text(NO_SUMO)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    proc = subprocess.run([sys.executable, "-m", "commands", "list"], capture_output=True,
                          text=True, env=env, cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stdout.splitlines()
             if line.lstrip().startswith(("sumo:", "plexe:"))]
    assert len(lines) == 4, proc.stdout
    assert all(line.endswith("(needs libsumo, sumo; install it with: pip install -e "
                             "'.[sumo]')") for line in lines), lines


# ------------------------------------------------ a recorded platoon mislabelled (point 11)
@pytest.mark.parametrize("args, message", [
    (["--simulator", "sumo", "--scenarios", "openacc-s-v1"],
     "openacc-real is a recorded platoon that no simulator drives, so its rows would be "
     "labelled as sumo's; run it without --simulator sumo"),
    (["--scenarios", "openacc-s-v1:classes=bus*4"],
     "openacc-real is a recorded platoon, the vehicles as they drove; vehicle classes (bus*4) "
     "would label the recording as vehicles it is not"),
    (["--scenarios", "openacc-s-v1:class_mix=bus+car*3"], "vehicle classes (bus+car*3)"),
], ids=["sumo", "classes", "class_mix"])
def test_the_recorded_platoon_is_refused_where_its_rows_would_be_mislabelled(
        args: list[str], message: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    if "--simulator" in args and not HAS_SUMO:
        pytest.skip("needs the sumo extra: pip install -e '.[sumo]'")
    out = tmp_path / "o"
    assert _exit_code(["run", "--controllers", "openacc-real", *args, "--vehicles", "4",
                       "--episodes", "1", "--quiet", "--out", str(out)]) == 2
    assert message in _one_line(capsys.readouterr().err) and not out.exists()


# ------------------------------------------------ a report folder's lock file (point 12)
@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                    reason="needs git and the repository")
@pytest.mark.parametrize("name", ["docs/sumo/store.lock", "docs/sumo/store.owner",
                                  "docs/penetration/store.lock"])
def test_the_lock_file_of_a_report_folder_under_docs_is_ignored_by_git(name: str) -> None:
    """``sumo-compare`` writes ``docs/sumo`` by default: its ``store.lock`` (kept after the
    command, as every folder lock's: removing it would race the next writer) stayed untracked
    there; it is ignored as the checkpoints folder's is, and the reports themselves are not."""
    ignored = subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", name], timeout=30)
    assert ignored.returncode == 0
    report = subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q",
                             "docs/sumo/report.md"], timeout=30)
    assert report.returncode == 1


def test_the_sweep_note_of_a_model_that_runs_in_sumo(tmp_path: Path) -> None:
    """Without running SUMO: the standard sweep's note for such a model says why it has none
    (it said "add --simulator sumo" to a sweep that had it)."""
    if not HAS_SUMO:
        pytest.skip("needs the sumo extra: pip install -e '.[sumo]'")
    from benchmark.sweep import row_sweeps

    notes: list[str] = []
    rec = {"controller": "sumo:acc@sumo", "name": "sumo:acc", "options": json.dumps({}),
           "scenario": "catchup-v1", "n_vehicles": 2, "comm_delay_s": 0.0,
           "packet_loss": 0.0, "lag_s": 0.0, "status": "ok", "policy_sha256": ""}
    assert list(row_sweeps([rec], notes=notes).values()) == [None]
    assert notes == ["no frequency sweep for sumo:acc@sumo on catchup-v1 (N = 2): sumo:acc is a "
                     "model that runs inside SUMO only, and the standard frequency sweep runs "
                     "in the built-in simulator, so it has none (its runs' string_gain is "
                     "measured in SUMO)"]


@pytest.mark.parametrize("given", ["", " , "])
def test_string_stability_refuses_an_empty_controller_list_before_work(
        tmp_path: Path, given: str, capsys: pytest.CaptureFixture[str]) -> None:
    from commands.cli import main

    assert main(["string-stability", "--controllers", given, "--out", str(tmp_path / "s")]) == 2
    assert "--controllers names no controller" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


LATE = '''
import numpy as np
from controllers.base import Controller


class LateFail(Controller):
    name = "late-fail"
    family = "linear"

    def reset(self, ctx):
        self.steps = 0

    def act(self, state, observation=None):
        self.steps += 1
        if self.steps > 50:  # past the contract check's first steps
            raise RuntimeError("broke after fifty steps")
        return np.zeros(np.shape(state.gap_m))
'''


def test_stability_a_users_law_failing_past_its_first_steps_is_one_line(
        user_code: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It was a traceback (the contract check runs the first 10 steps only)."""
    (user_code / "late_h9.py").write_text(LATE)
    out = user_code / "s"
    assert _exit_code(["stability", "--controllers", "late_h9:LateFail", "--empirical",
                       "--n-omega", "3", "--out", str(out)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert "late_h9:LateFail" in err and "broke after fifty steps" in err
    assert not (out / "stability_summary.csv").exists()


@pytest.mark.parametrize("option", ["kp=1e308", "kd=1e13", "kp=101"])
def test_a_linear_gain_beyond_any_law_is_refused_before_work(
        tmp_path: Path, option: str, capsys: pytest.CaptureFixture[str]) -> None:
    """``cacc:kp=1e308`` ran as a switch between the bounds, and its sweep called it stable."""
    out = tmp_path / "r"
    assert _exit_code(["run", "--controllers", f"cacc:{option}", "--scenarios", "catchup-v1",
                       "--episodes", "1", "--out", str(out)]) == 2
    assert "must be at most 100" in _one_line(capsys.readouterr().err)
    assert not (out / "runs.csv").exists()
