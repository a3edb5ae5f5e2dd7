"""Issue 53, point 5: a fresh probe of the commands the issues filed with it added (the SUMO
backend, controllers and scenarios of one's own, vehicle classes, mixed traffic, string
stability), as a careless or hostile user would use them. Each case once gave a traceback, ran
work before refusing, changed a finished file, or was met with a wrong message; now: exit 2
and one line before any work, finished files byte-identical, one line at a signal.

Cases still failing in files other issues are editing are strict ``xfail`` marks naming the
file: they pass (and the mark must go) once that file refuses them."""

from __future__ import annotations

import hashlib
import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from run_marks import FULL

from commands.cli import main as cli
from controllers import registry

ROOT = Path(__file__).resolve().parents[2]
HAS_SUMO = all(importlib.util.find_spec(m) is not None for m in ("libsumo", "sumo"))
needs_sumo = pytest.mark.skipif(not HAS_SUMO, reason="needs the sumo extra: "
                                                     "pip install -e '.[sumo]'")
SMALL = ["--scenarios", "catchup-v1", "--vehicles", "2", "--episodes", "1", "--quiet"]


def _small(args: list[str]) -> list[str]:
    """``args`` with the small run's settings it does not give (``--seeds`` replaces
    ``--episodes``)."""
    given = set(args[::2]) | ({"--episodes"} if "--seeds" in args else set())
    fill = [a for flag, value in zip(SMALL[:-1:2], SMALL[1::2], strict=True)
            if flag not in given for a in (flag, value)]
    return [*args, *fill, "--quiet"]


def _exit_code(argv: list[str]) -> int:
    try:
        return cli(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def _one_line(err: str) -> str:
    """The one error line of a refused command (progress lines may come before it)."""
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("cacc-bench")]
    assert len(errors) == 1 and err.strip().splitlines()[-1] == errors[0], err
    return errors[0]


def _nothing_stored(folder: Path) -> None:
    assert not list(folder.rglob("store.sqlite")) and not list(folder.rglob("*.csv")), \
        sorted(folder.rglob("*"))


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name not in ("store.lock", "store.owner")}


# ---------------------------------------------------------------------------- the SUMO backend
#: ``(argv, message)``: refused before any run. The first six values ran, were stored, and then
#: made every later command refuse the folder's record (a spacing of 1e308 is no metric).
SUMO_REFUSED = [
    (["--controllers", "sumo:acc:time_gap_s=1e308"], "time_gap_s must be at most 10"),
    (["--controllers", "sumo:cacc:standstill_m=1e308"], "standstill_m must be at most 100"),
    (["--controllers", "plexe:ploeg:ploeg_h_s=1e308"], "ploeg_h_s must be at most 10"),
    (["--controllers", "plexe:path:spacing_m=1e308"], "spacing_m must be at most 100"),
    (["--controllers", "sumo:acc:time_gap_s=11"], "time_gap_s must be at most 10"),
    (["--controllers", "sumo:cacc:standstill_m=101"], "standstill_m must be at most 100"),
    (["--controllers", "sumo:acc:time_gap_s=nan"], "must be of type float"),
    (["--controllers", "sumo:acc:time_gap_s=-1"], "time_gap_s must be a finite number > 0"),
    (["--controllers", "plexe:ploeg:ploeg_kp=-1e308"], "ploeg_kp must be a finite number > 0"),
    (["--controllers", "plexe:path:omega_n=0,xi=0"], "omega_n must be a finite number > 0"),
    (["--controllers", "plexe:path:c1=inf"], "must be of type float"),
    (["--controllers", "plexe:path:bogus=1"], "plexe:path has no option 'bogus'"),
    (["--controllers", "safe:sumo:acc"], "the safety filter has none to correct"),
    (["--controllers", "sumo:bogus"], "module sumo has no 'bogus'"),
    (["--controllers", "plexe:"], "unknown controller 'plexe'"),
    (["--controllers", "sumo:acc", "--scenarios", "catchup-v1:humans=1"],
     "SUMO's IDM draws no acceleration noise"),
    (["--controllers", "cacc", "--scenarios",
      "catchup-v1:humans=1,human_model=ovm,human_noise_mps2=0"], "it has no ovm model"),
    (["--controllers", "cacc", "--scenarios", "catchup-v1:classes=bus+car"],
     "heterogeneous strings run in the built-in simulator"),
    (["--controllers", "cacc", "--scenarios", "ring-v1", "--vehicles", "22"],
     "add human_noise_mps2=0"),
    (["--controllers", "cacc", "--seeds", "99999999999"], "--seeds must lie in 0..2147483647"),
]


@needs_sumo
@pytest.mark.parametrize("args, message", SUMO_REFUSED,
                         ids=[" ".join(a)[:60] for a, _ in SUMO_REFUSED])
def test_a_bad_sumo_setting_is_refused_before_any_run(
        args: list[str], message: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["run", "--simulator", "sumo", *_small(args), "--out", str(tmp_path / "out")]
    assert _exit_code(argv) == 2
    assert message in _one_line(capsys.readouterr().err)
    _nothing_stored(tmp_path)


@pytest.mark.parametrize("model", ["sumo:acc", "plexe:ploeg"])
def test_a_sumo_model_in_the_builtin_simulator_says_to_add_the_simulator(
        model: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if not HAS_SUMO:
        pytest.skip("without the extra the model is refused with the install command")
    assert _exit_code(["run", "--controllers", model, *SMALL, "--out", str(tmp_path / "o")]) == 2
    assert "add --simulator sumo" in _one_line(capsys.readouterr().err)
    _nothing_stored(tmp_path)


def _fake_sumo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """libsumo installed but failing to load (a wheel built for another system), first on the
    path: every SUMO run of a sweep failed with its ImportError, one by one, and
    ``sumo-compare`` ended in a traceback."""
    site = tmp_path / "site"
    (site / "libsumo").mkdir(parents=True)
    (site / "libsumo" / "__init__.py").write_text(
        "raise ImportError('libsumo.so: cannot open shared object file')\n")
    (site / "sumo").mkdir()
    (site / "sumo" / "__init__.py").write_text("")
    for name in ("libsumo", "sumo"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.syspath_prepend(str(site))


@pytest.mark.parametrize("argv", [
    ["run", "--simulator", "sumo", "--controllers", "cacc", *SMALL],
    ["run", "--simulator", "sumo-euler", "--controllers", "sumo:acc", *SMALL],
    ["sumo-compare", "--episodes", "1"],
], ids=["run", "run sumo:acc", "sumo-compare"])
def test_a_libsumo_that_does_not_load_is_refused_with_the_install_command(
        argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    _fake_sumo(tmp_path, monkeypatch)
    out = tmp_path / "out"
    assert _exit_code([*argv, "--out", str(out)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "libsumo is installed but does not load (ImportError: libsumo.so" in line
    assert "pip install -e '.[sumo]'" in line and not out.exists()


#: A ``sitecustomize`` that hides SUMO from the import system, as an install without the extra.
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


@pytest.mark.parametrize("argv, message", [
    (["run", "--simulator", "sumo", "--controllers", "cacc", *SMALL],
     "the SUMO simulator needs the sumo extra"),
    (["run", "--controllers", "sumo:acc", *SMALL], "sumo:acc needs libsumo, sumo"),
], ids=["simulator", "model"])
def test_without_the_extra_in_a_fresh_process_the_install_command_is_said(
        argv: list[str], message: str, tmp_path: Path) -> None:
    (tmp_path / "sitecustomize.py").write_text(NO_SUMO)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    proc = subprocess.run([sys.executable, "-m", "commands", *argv, "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, env=env,
                          cwd=tmp_path, timeout=120)
    assert proc.returncode == 2, proc.stderr
    line = _one_line(proc.stderr)
    assert message in line and "pip install -e '.[sumo]'" in line
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- sumo-compare
def _small_report(monkeypatch: pytest.MonkeyPatch, stop_at: str | None = None) -> list[str]:
    """Replace the study's measurements by small tables (the command's own logic stays);
    with ``stop_at`` that measurement is interrupted as a Ctrl-C would. Returns the calls."""
    import pandas as pd

    from studies import sumo_compare as sc

    calls: list[str] = []

    def table(name: str):  # type: ignore[no-untyped-def]
        def measure(*args: object, **kwargs: object) -> pd.DataFrame:
            calls.append(name)
            if name == stop_at:
                raise KeyboardInterrupt
            return pd.DataFrame({"what": [name], "value": [float(len(calls))]})
        return measure

    for name, func in (("agreement", "trajectory_agreement"), ("families", "family_table"),
                       ("ploeg", "ploeg_comparison"), ("energy", "energy_comparison"),
                       ("humans", "human_comparison"), ("speed", "speed_comparison")):
        monkeypatch.setattr(sc, func, table(name))
    return calls


@needs_sumo
def test_sumo_compare_refuses_a_report_folder_and_overwrites_only_when_asked(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Run twice, ``sumo-compare`` rewrote the finished report without a word (its default
    folder is the committed ``docs/sumo``); now refused unless ``--overwrite``, which replaces
    the files together once the new report is whole: an interruption leaves the old one."""
    calls = _small_report(monkeypatch)
    out = tmp_path / "rep"
    argv = ["sumo-compare", "--episodes", "1", "--out", str(out)]
    assert _exit_code(argv) == 0 and len(calls) == 6
    first = _digests(out)
    assert set(first) == {"report.md", "agreement.csv", "families.csv", "ploeg.csv",
                          "energy.csv", "humans.csv", "speed.csv"}
    capsys.readouterr()
    assert _exit_code(argv) == 2
    line = _one_line(capsys.readouterr().err)
    assert "already holds a SUMO report (report.md); add --overwrite" in line
    assert len(calls) == 6 and _digests(out) == first  # refused before any measurement

    _small_report(monkeypatch, stop_at="humans")  # a Ctrl-C in the fifth measurement
    assert _exit_code([*argv, "--overwrite"]) == 130
    assert _digests(out) == first and not list(out.glob(".*.tmp"))

    _small_report(monkeypatch)
    (out / "speed.csv").unlink()  # a report with a table missing is still a report
    capsys.readouterr()
    assert _exit_code([*argv, "--overwrite"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"--overwrite: {out} holds a SUMO report (report.md); making it again: its "
                   "files are replaced together once the new report is whole"]
    assert set(_digests(out)) == set(first)


@needs_sumo
def test_sumo_compare_refuses_a_second_writer_and_a_folder_where_a_file_goes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    from benchmark.folder_lock import folder_lock

    calls = _small_report(monkeypatch)
    out = tmp_path / "rep"
    with folder_lock(out):  # another command writes the folder
        assert _exit_code(["sumo-compare", "--episodes", "1", "--out", str(out)]) == 2
    assert "is being written by pid" in _one_line(capsys.readouterr().err) and not calls
    (out / "report.md").mkdir()
    assert _exit_code(["sumo-compare", "--episodes", "1", "--out", str(out),
                       "--overwrite"]) == 2
    assert "report.md is a folder, where the report writes a file" in _one_line(
        capsys.readouterr().err) and not calls


# ------------------------------------------------------------ controllers of one's own (56)
LAWS = '''
import numpy as np

from controllers.base import Controller


class Zero(Controller):
    """Always zero."""

    family = "linear"

    def __init__(self, gain: float = 1.0) -> None:
        super().__init__()
        self.gain = gain

    def reset(self, ctx):
        pass

    def act(self, state, observation):
        return np.zeros_like(state.gap_m) * self.gain


class NaNs(Zero):
    def act(self, state, observation):
        return np.full_like(state.gap_m, np.nan)


class RaisesInit(Zero):
    def __init__(self, gain: float = 1.0) -> None:
        raise RuntimeError("boom in init")


class NoDefault(Zero):
    def __init__(self, gain: float) -> None:
        super().__init__()


class Untyped(Zero):
    def __init__(self, gain=1.0, name="x", flag=False):
        super().__init__()
        self.gain, self.given_name = gain, name
'''


@pytest.fixture
def own_laws(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The user's modules in the working directory, loaded afresh by each test."""
    (tmp_path / "laws_h8.py").write_text(LAWS)
    (tmp_path / "exits_h8.py").write_text("import sys\nsys.exit(4)\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(registry, "_PLUGINS", {})
    for name in ("laws_h8", "exits_h8"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    return tmp_path


@pytest.mark.parametrize("item, message", [
    # a constructor that raised, or needed an argument: a TypeError or RuntimeError traceback
    ("laws_h8:RaisesInit", "controller laws_h8:RaisesInit: building it failed (RuntimeError: "
                           "boom in init)"),
    ("laws_h8:NoDefault", "NoDefault() needs gain; give every argument of its constructor a "
                          "default"),
    # ... and with the option given, "has no option 'gain'; its options are: none"
    ("laws_h8:NoDefault:gain=2", "NoDefault() needs gain"),
    ("controllers.sumo_models:SumoModelController", "SumoModelController() needs model"),
    # sys.exit() at import ended `run` (and `list`) with its status and no word
    ("exits_h8:Law", "controller exits_h8:Law: importing exits_h8 failed (it called "
                     "sys.exit(4))"),
])
def test_a_controller_class_that_cannot_be_built_is_refused_in_one_line(
        item: str, message: str, own_laws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(["run", "--controllers", item, *SMALL, "--out", "o"]) == 2
    assert message in _one_line(capsys.readouterr().err)
    _nothing_stored(own_laws)


def test_an_option_named_like_the_registrys_own_arguments_reaches_the_class(
        own_laws: Path) -> None:
    """``Untyped:name=y``: ``make_controller() got multiple values for argument 'name'``."""
    ctrl = registry.make_controller("laws_h8:Untyped", name="y", gain="2")
    assert (ctrl.given_name, ctrl.gain) == ("y", 2.0)


def test_the_harness_names_a_users_class_by_its_reference(own_laws: Path,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    """Its contract errors said ``controller: act returned a non-finite command``."""
    assert registry.make_controller("laws_h8:NaNs").name == "laws_h8:NaNs"
    assert _exit_code(["run", "--controllers", "laws_h8:NaNs", *SMALL, "--out", "o"]) == 1
    assert "laws_h8:NaNs: act returned a non-finite command" in capsys.readouterr().err


def test_list_goes_on_past_an_entry_point_whose_module_exits(tmp_path: Path) -> None:
    """``cacc-bench list`` ended with status 4 and half its output at such a module."""
    site = tmp_path / "site"
    meta = site / "exitplug_h8-0.1.dist-info"
    meta.mkdir(parents=True)
    (site / "exits_h8.py").write_text("import sys\nsys.exit(4)\n")
    (meta / "METADATA").write_text("Metadata-Version: 2.1\nName: exitplug_h8\nVersion: 0.1\n")
    (meta / "entry_points.txt").write_text("[cacc_bench.controllers]\nexiter = exits_h8:Law\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    proc = subprocess.run([sys.executable, "-m", "commands", "list"], capture_output=True,
                          text=True, env=env, cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "exiter   (cacc_bench.controllers entry point exits_h8:Law) cannot be used: " \
           "controller exiter (exits_h8:Law): importing exits_h8 failed (it called " \
           "sys.exit(4))" in proc.stdout
    assert "safe:<name>" in proc.stdout  # the listing's last entry: nothing cut off


# ------------------------------------------------------------------- vehicle classes (55)
@pytest.mark.parametrize("scenario, message", [
    # an OverflowError traceback, and minutes allocating a list of 1e9 names
    ("catchup-v1:classes=car*99999999999999999999", "names more than 64 vehicles"),
    ("catchup-v1:classes=car*999999999", "names more than 64 vehicles"),
    ("catchup-v1:class_mix=car*64+bus", "names more than 64 vehicles"),
    # str.isdigit() takes '²', int() does not: a ValueError traceback
    ("catchup-v1:classes=car*²", "a repeat is name*k with a whole k >= 1"),
    ("catchup-v1:classes=car*١+bus", "a repeat is name*k with a whole k >= 1"),
    ("catchup-v1:classes=car*0", "a repeat is name*k with a whole k >= 1"),
    ("catchup-v1:classes=CAR*2", "unknown vehicle class 'CAR'"),
    ("catchup-v1:classes=car+", "has an empty item"),
    ("catchup-v1:classes=", "names no class"),
    ("catchup-v1:classes=car*2,class_mix=car*2", "classes and class_mix both say"),
    ("catchup-v1:class_mix=bus+car,class_seed=99999999999999999999999",
     "class_seed must lie in 0..2147483647"),
    ("catchup-v1:class_mix=bus+car,class_seed=nan", "must be of type int"),
    ("catchup-v1:class_seed=3", "class_seed shuffles a class_mix"),
    ("catchup-v1:drag_saving=nope", "drag_saving must be one of"),
    ("catchup-v1:class_mix=bus+car", "class_mix names 2 vehicles but the run has 3"),
])
def test_a_bad_class_string_is_refused_before_any_run(
        scenario: str, message: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(["run", "--controllers", "cacc", "--scenarios", scenario,
                       "--vehicles", "2,3", "--episodes", "1", "--quiet",
                       "--out", str(tmp_path / "o")]) == 2
    assert message in _one_line(capsys.readouterr().err)
    _nothing_stored(tmp_path)


@pytest.mark.parametrize("args, message", [
    (["--controllers", "cacc", "--lag", "0,0.2", "--scenarios", "catchup-v1:classes=bus+car"],
     "a run-wide lag (0.2 s) would replace them"),
    (["--controllers", "cacc:time_gap_rule=XIAO"], "time_gap_rule must be one of fixed, xiao"),
    (["--controllers", "cacc:time_gap_rule=xiao,standstill_m=2"], "leave standstill_m out"),
    (["--controllers", "bdc", "--scenarios", "catchup-v1:classes=bus+van+car*6",
      "--vehicles", "8"], "trained on the homogeneous string of one car"),
])
def test_classes_with_lags_and_rules_that_exclude_them_are_refused(
        args: list[str], message: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(["run", *_small(args), "--out", str(tmp_path / "o")]) == 2
    assert message in _one_line(capsys.readouterr().err)
    _nothing_stored(tmp_path)


# ----------------------------------------------------------- signals and finished folders
def _session_left(sid: int) -> list[int]:
    left = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                text = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            fields = text[text.rindex(")") + 2:].split()
            if fields[0] != "Z" and int(fields[3]) == sid:
                left.append(int(entry))
    return left


def _handles_sigterm(pid: int) -> bool:
    """Whether the command line's signal handlers are installed in ``pid``."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:"))
    return bool(int(caught, 16) & (1 << (signal.SIGTERM - 1)))


def _signal_mid_run(argv: list[str], sig: int, after_s: float, cwd: Path) -> tuple[int, str]:
    """Run ``cacc-bench argv``, send ``sig`` twice ``after_s`` after its handlers are
    installed; its exit status and stderr, once no process of it is left."""
    proc = subprocess.Popen([sys.executable, "-m", "commands", *argv], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    deadline = time.monotonic() + 60
    while not _handles_sigterm(proc.pid) and time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.01)
    time.sleep(after_s)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(sig)
    time.sleep(0.02)
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("hung after the signals")
    deadline = time.monotonic() + 5
    while _session_left(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _session_left(proc.pid), "processes left behind"
    return proc.returncode, err


@needs_sumo
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_a_sigint_in_a_sumo_sweep_ends_it_in_one_line_and_stores_whole_runs(
        tmp_path: Path) -> None:
    from benchmark.store import ResultStore

    rc, err = _signal_mid_run(
        ["run", "--simulator", "sumo", "--controllers", "cacc,sumo:acc,plexe:ploeg",
         "--scenarios", "catchup-v1,slowdown-v1", "--vehicles", "4", "--episodes", "10",
         "--executor", "serial", "--quiet", "--out", "s"], signal.SIGINT, 2.0, tmp_path)
    assert rc == 130 and err.strip().splitlines() == [
        "cacc-bench: interrupted (SIGINT); the run in flight was not stored, finished runs "
        "are (complete with --resume)"], err
    if (tmp_path / "s" / "store.sqlite").exists():
        with ResultStore(tmp_path / "s", create=False) as store:
            assert all(r["status"] == "ok" for r in store.records())


@FULL
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_an_interrupted_heterogeneous_study_is_told_to_resume(tmp_path: Path) -> None:
    """It said "rerun it", which its folder then refuses without --resume."""
    rc, err = _signal_mid_run(["heterogeneous", "--episodes", "1", "--scenarios", "catchup-v1",
                               "--controllers", "cacc,mpc-qp", "--out", "h"],
                              signal.SIGTERM, 3.0, tmp_path)
    assert rc == 143, err
    assert err.strip().splitlines()[-1] == (
        "cacc-bench: interrupted (SIGTERM); the run in flight was not stored, finished runs "
        "are (complete with --resume)")


@FULL
@needs_sumo
def test_a_finished_sumo_sweep_is_refused_and_resume_changes_nothing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import sqlite3

    out = tmp_path / "f"
    argv = ["run", "--simulator", "sumo", "--controllers", "cacc,sumo:acc", *SMALL,
            "--out", str(out)]
    assert _exit_code(argv) == 0

    def content() -> dict[str, object]:
        with sqlite3.connect(out / "store.sqlite") as db:
            rows = sorted(db.execute("select * from runs").fetchall())
        return {"runs": rows, **{k: v for k, v in _digests(out).items()
                                 if not k.endswith(".sqlite")}}

    before = content()
    capsys.readouterr()
    assert _exit_code(argv) == 2
    assert "already holds 2 stored runs; add --resume" in _one_line(capsys.readouterr().err)
    assert _exit_code([*argv, "--resume"]) == 0 and content() == before


# ------------------------------- once failing, in files other issues edit (one still xfail)
@needs_sumo
@pytest.mark.parametrize("extra", [[], ["--empirical"]])
def test_stability_refuses_a_model_that_runs_in_sumo(
        extra: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(["stability", "--controllers", "sumo:acc", *extra,
                       "--out", str(tmp_path / "s")]) == 2
    assert "runs in sumo only" in _one_line(capsys.readouterr().err)


@pytest.mark.parametrize("argv", [
    ["stability", "--controllers", "laws_h8:NaNs", "--empirical", "--n-omega", "2",
     "--out", "s"],
    ["perf", "--quick", "--only", "controllers", "--controllers", "laws_h8:NaNs"],
], ids=["stability", "perf"])
def test_a_controller_breaking_the_contract_is_one_line_in_stability_and_perf(
        argv: list[str], own_laws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(argv) == 2
    assert "laws_h8:NaNs: act returned a non-finite command" in _one_line(
        capsys.readouterr().err)


SCENARIOS = '''
import numpy as np

from envs.scenarios import EpisodeBatch, ScenarioSpec


def _flat(sc, seeds, u, n):
    b = len(seeds)
    return EpisodeBatch(np.asarray(seeds), np.asarray(u), np.full((b, n), sc.target_gap_m),
                        np.full((b, n), sc.target_speed_mps),
                        np.full((b, sc.n_steps + 1), sc.target_speed_mps))


SHADOW = ScenarioSpec("shadow-v1", "its option shadows humans=", 20.0, 15.0, 50, _flat,
                      defaults={"humans": 3})
BADCHECK = ScenarioSpec("badcheck-v1", "its check raises", 20.0, 15.0, 50, _flat,
                        check=lambda opts: 1 / 0)
ONE = ScenarioSpec("one-v1", "one follower by default", 20.0, 15.0, 50, _flat,
                   default_vehicles=1)
'''


@pytest.mark.parametrize("name", ["SHADOW", "BADCHECK", "ONE"])
def test_a_broken_scenario_of_ones_own_is_refused_before_any_run(
        name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    import envs.scenarios

    (tmp_path / "scen_h8.py").write_text(SCENARIOS)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(envs.scenarios, "_PLUGINS", {})
    monkeypatch.delitem(sys.modules, "scen_h8", raising=False)
    assert _exit_code(["run", "--controllers", "cacc", "--scenarios", f"scen_h8:{name}",
                       "--episodes", "1", "--quiet", "--out", "o"]) == 2
    _one_line(capsys.readouterr().err)
    _nothing_stored(tmp_path)


@pytest.mark.parametrize("option", ["cacc:standstill_m=1e308", "cacc:time_gap_s=1e13"])
def test_a_cacc_spacing_beyond_any_platoon_is_refused_before_any_run(
        option: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(["run", "--controllers", option, *SMALL,
                       "--out", str(tmp_path / "o")]) == 2
    _one_line(capsys.readouterr().err)
    _nothing_stored(tmp_path)


def test_a_sweep_cache_with_an_impossible_peak_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    out = tmp_path / "r"
    assert _exit_code(["run", "--controllers", "acc", *SMALL, "--out", str(out)]) == 0
    cache = out / "string_sweeps.json"
    data = json.loads(cache.read_text())
    data["entries"][0]["peak_gain"] = 1e308
    cache.write_text(json.dumps(data))
    capsys.readouterr()
    assert _exit_code(["leaderboard", str(out), "--quiet"]) == 2
    assert "string_sweeps.json is damaged" in _one_line(capsys.readouterr().err)


@needs_sumo
def test_a_sumo_models_missing_frequency_sweep_is_not_blamed_on_the_user(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(["run", "--simulator", "sumo", "--controllers", "sumo:acc", *SMALL,
                       "--out", str(tmp_path / "o")]) == 0
    assert "add --simulator sumo" not in capsys.readouterr().err


@pytest.mark.parametrize("orders", ["", " , "])
def test_heterogeneous_refuses_an_empty_selection_of_orders(
        orders: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = _exit_code(["heterogeneous", "--orders", orders, "--episodes", "1", "--scenarios",
                       "catchup-v1", "--controllers", "cacc", "--executor", "serial",
                       "--out", str(tmp_path / "h")])
    assert code == 2
    assert "--orders: no order named" in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "h").exists()


@FULL
def test_string_stability_of_cacc_alone_writes_its_report(tmp_path: Path) -> None:
    """Without a learned entry the goal table is empty with its header (it was written empty
    and read back as damaged: exit 2 after the study's work)."""
    out = tmp_path / "ss"
    assert _exit_code(["string-stability", "--controllers", "cacc", "--episodes", "1",
                       "--validation-episodes", "1", "--design", "small", "--sizes", "4",
                       "--scenarios", "catchup-v1", "--executor", "serial",
                       "--out", str(out)]) == 0
    assert (out / "report.md").exists()
    import pandas as pd

    assert list(pd.read_csv(out / "goal.csv").columns) == ["entry", "scenario", "goal_met"]


