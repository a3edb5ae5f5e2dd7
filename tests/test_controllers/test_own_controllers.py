"""Controllers and scenarios from the user's own code, without an edit to the package: the
contributor guide's example by ``module:Class`` through the command line (``run`` on the process
pool, ``stability``, ``generalise``, ``pareto``), installed packages' entry points, one-line
refusals, canonical labels, and Ray workers importing the user's module."""

from __future__ import annotations

import json
import os
import re
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import pandas as pd
import pytest

from commands.cli import main as cli
from controllers import registry

ROOT = Path(__file__).resolve().parents[2]
EXE = str(Path(sys.executable).parent / "cacc-bench")
LAW = "my_controller:HeardSpeed"


def _guide_example() -> str:
    """The example file of docs/contributing.md, "Add a controller" (its one Python block)."""
    text = (ROOT / "docs" / "contributing.md").read_text()
    text = text[text.index("## Add a controller"):]
    text = text[:text.index("\n## ", 1)]
    (code,) = re.findall(r"```python\n(.*?)```", text, re.S)
    return code


def _cacc_bench(cwd: Path, pythonpath: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    return subprocess.run([EXE, *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)


def _executor_of(folder: Path) -> str:
    with sqlite3.connect(folder / "store.sqlite") as db:
        (value,) = db.execute("select value from meta where key = 'last_sweep'").fetchone()
    return json.loads(value)["executor"]


def test_the_guides_example_runs_in_run_stability_generalise_and_pareto(tmp_path: Path) -> None:
    """The guide's file in a folder outside the package, on PYTHONPATH; the commands run from
    another folder; the process pool's workers import it by name."""
    ext, work = tmp_path / "ext", tmp_path / "work"
    ext.mkdir()
    work.mkdir()
    (ext / "my_controller.py").write_text(_guide_example())

    ran = _cacc_bench(work, ext, "run", "--controllers",
                      f"cacc,{LAW},{LAW}:speed_gain=0.5,{LAW}:speed_gain=0.8",
                      "--scenarios", "catchup-v1,slowdown-v1", "--vehicles", "3", "--episodes",
                      "2", "--executor", "process", "--workers", "2", "--out", "r")
    assert ran.returncode == 0, ran.stderr
    assert _executor_of(work / "r") == "process"
    runs = pd.read_csv(work / "r" / "runs.csv")
    assert set(runs["status"]) == {"ok"}
    # speed_gain=0.8 is the default: the same label as the bare name, run once (said once)
    assert set(runs["controller"]) == {"cacc", LAW, f"{LAW}[speed_gain=0.5]"}
    assert f"{LAW} named more than once" in ran.stderr
    assert set(runs[runs["controller"] == LAW]["family"]) == {"linear"}
    gains = runs.groupby("controller")["reward"].mean()
    assert gains[LAW] != gains[f"{LAW}[speed_gain=0.5]"]  # the option reached the law
    assert "wrote r/runs.csv (12 runs), r/leaderboard.csv and the store r/store.sqlite" \
        in ran.stdout
    assert "next: `cacc-bench plot r`" in ran.stdout

    stab = _cacc_bench(work, ext, "stability", "--controllers", f"cacc,{LAW}", "--empirical",
                       "--n-omega", "2", "--out", "s")
    assert stab.returncode == 0, stab.stderr
    summary = pd.read_csv(work / "s" / "stability_summary.csv")
    assert LAW in set(summary["controller"])
    assert stab.stdout.startswith("V2V delay 0.2 s, actuator lag 0.1 s (--delay and --lag at "
                                  "this command's defaults")

    gen = _cacc_bench(work, ext, "generalise", "--controllers", f"cacc,{LAW}:speed_gain=0.5",
                      "--columns", "brake", "--episodes", "1", "--out", "g")
    assert gen.returncode == 0, gen.stderr
    cells = pd.read_csv(work / "g" / "matrix.csv").set_index("row")
    assert cells.loc[f"{LAW}[speed_gain=0.5]", "episodes"] == 1
    assert _executor_of(work / "g" / "runs") == "process"

    par = _cacc_bench(work, ext, "pareto", "--families", "points", "--controllers", LAW,
                      "--episodes", "1", "--vehicles", "3", "--out", "p")
    assert par.returncode == 0, par.stderr
    assert LAW in set(pd.read_csv(work / "p" / "pareto.csv")["controller"])


def _module(folder: Path, name: str, body: str) -> None:
    (folder / f"{name}.py").write_text(textwrap.dedent(body))


@pytest.mark.parametrize("item, message", [
    ("nomodule_h3:Law", "controller nomodule_h3:Law: no module 'nomodule_h3' on the Python path "
                        "or in the working directory"),
    ("laws_h3:Missing", "controller laws_h3:Missing: module laws_h3 has no 'Missing'"),
    ("laws_h3:NOT_A_CLASS", "NOT_A_CLASS is not a controller class"),
    ("laws_h3:Half", "Half does not implement act, reset of controllers.base.Controller"),
    ("laws_h3:Alien", "family 'alien' is not one of human, linear, mpc, marl, data"),
    ("broken_h3:Law", "importing broken_h3 failed (ModuleNotFoundError: No module named "
                      "'not_installed_h3')"),
    ("laws_h3:Good:nope=1", "has no option 'nope'; its options are: speed_gain"),
    ("laws_h3:Good:speed_gain=fast", "option speed_gain of laws_h3:Good must be of type float"),
    ("cacc:kp", "an option is written key=value (cacc:key=value)"),
    ("nope", "or a controller class of your own as package.module:Class"),
])
def test_a_bad_reference_is_refused_with_one_line(
    item: str, message: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    _module(tmp_path, "laws_h3", """
        from controllers.base import Controller
        from controllers.linear import CACCController

        NOT_A_CLASS = 3

        class Half(Controller):
            pass

        class Alien(CACCController):
            family = "alien"

        class Good(Controller):
            def __init__(self, speed_gain: float = 0.8) -> None:
                super().__init__()

            def reset(self, ctx):
                pass

            def act(self, state, observation):
                return 0.0 * state.gap_m
        """)
    _module(tmp_path, "broken_h3", "import not_installed_h3\n")
    monkeypatch.chdir(tmp_path)  # found in the working directory, as `python -m` would
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(registry, "_PLUGINS", {})  # each case loads its classes afresh
    for name in ("laws_h3", "broken_h3"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    for argv in (["run", "--controllers", item, "--scenarios", "catchup-v1", "--out", "o"],
                 ["stability", "--controllers", item, "--empirical", "--out", "s"]):
        assert cli(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("cacc-bench: error: ") and err.count("\n") == 1, err
        assert message in err
    assert not (tmp_path / "o").exists()


def test_a_reference_has_one_label_however_it_is_spelled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A class re-exported by its package is named where it is defined; a label parses back."""
    from controllers.registry import controller_label, parse_controller_list, resolve
    from infra.naming import parse_label

    pkg = tmp_path / "pkg_h3"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from pkg_h3.laws import Law\n")
    _module(pkg, "laws", """
        from controllers.linear import CACCController

        class Law(CACCController):
            '''A law of the test's own.'''
        """)
    monkeypatch.syspath_prepend(str(tmp_path))
    given = parse_controller_list("pkg_h3:Law,pkg_h3.laws:Law:kp=0.3,safe:pkg_h3:Law")
    assert [n for n, _ in given] == ["pkg_h3.laws:Law", "pkg_h3.laws:Law", "safe:pkg_h3.laws:Law"]
    assert controller_label("pkg_h3:Law", {}) == "pkg_h3.laws:Law"
    label = controller_label("pkg_h3:Law", {"kp": "0.30"})
    assert label == "pkg_h3.laws:Law[kp=0.3]"
    assert parse_label(label) == ("pkg_h3.laws:Law", {"kp": "0.3"})
    assert resolve("pkg_h3:Law").description == "A law of the test's own."


HILL = '''

from envs.scenarios import EpisodeBatch, ScenarioSpec


def _hill(sc, seeds, u, n):
    import numpy as np

    t = np.linspace(0.0, np.pi, sc.n_steps + 1)
    leader = sc.target_speed_mps - sc.options["dip_mps"] * np.sin(t)
    b = len(seeds)
    return EpisodeBatch(np.asarray(seeds), np.asarray(u), np.full((b, n), sc.target_gap_m),
                        np.full((b, n), sc.target_speed_mps), np.tile(leader, (b, 1)))


HILL = ScenarioSpec("hill-v1", "the leader dips its speed once", 20.0, 15.0, 300, _hill,
                    defaults={"dip_mps": 2.0})
'''


def test_installed_packages_add_controllers_and_scenarios(tmp_path: Path) -> None:
    """Entry points of an installed package (its metadata on the path): listed, run by name
    with options, refused lines for those that cannot be used; a scenario by reference too."""
    site, work = tmp_path / "site", tmp_path / "work"
    meta = site / "myplug_h3-0.1.dist-info"
    meta.mkdir(parents=True)
    work.mkdir()
    (site / "myplug_h3.py").write_text(_guide_example() + HILL)
    (meta / "METADATA").write_text("Metadata-Version: 2.1\nName: myplug_h3\nVersion: 0.1\n")
    (meta / "entry_points.txt").write_text(
        "[cacc_bench.controllers]\nheard-speed = myplug_h3:HeardSpeed\n"
        "cacc = myplug_h3:HeardSpeed\nbroken = myplug_h3:Nope\n\n"
        "[cacc_bench.scenarios]\nhill-v1 = myplug_h3:HILL\n")
    listed = _cacc_bench(work, site, "list")
    assert listed.returncode == 0, listed.stderr
    assert re.search(r"^  heard-speed \[linear\] Gap error and the heard speed difference, fed "
                     r"back \(an example controller\)\. \(installed: myplug_h3:HeardSpeed\); V2V: "
                     r"predecessor's speed \(1 float\)$", listed.stdout, re.M)
    assert "myplug_h3:HeardSpeed is not used: cacc is a built-in controller" in listed.stdout
    assert "broken   (cacc_bench.controllers entry point myplug_h3:Nope) cannot be used" \
        in listed.stdout
    assert re.search(r"^  hill-v1 +d\*=20 m, v\*=15 m/s, 300 steps", listed.stdout, re.M)

    ran = _cacc_bench(work, site, "run", "--controllers", "heard-speed:speed_gain=0.5,cacc",
                      "--scenarios", "hill-v1:dip_mps=3,myplug_h3:HILL", "--vehicles", "3",
                      "--episodes", "1", "--out", "r")
    assert ran.returncode == 0, ran.stderr
    runs = pd.read_csv(work / "r" / "runs.csv")
    assert set(runs["status"]) == {"ok"}
    assert set(runs["controller"]) == {"heard-speed[speed_gain=0.5]", "cacc"}
    assert set(runs["scenario"]) == {"hill-v1[dip_mps=3.0]", "myplug_h3:HILL"}
    bad = _cacc_bench(work, site, "run", "--controllers", "broken", "--out", "b")
    assert bad.returncode == 2
    assert bad.stderr == ("cacc-bench: error: controller broken (myplug_h3:Nope): module "
                          f"myplug_h3 has no 'Nope' ({site / 'myplug_h3.py'})\n")


@pytest.mark.ray
def test_ray_workers_import_the_users_module(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    ext, work = tmp_path / "ext", tmp_path / "work"
    ext.mkdir()
    work.mkdir()
    (ext / "my_controller.py").write_text(_guide_example())
    small = ["--controllers", f"{LAW}:speed_gain=0.5", "--scenarios", "catchup-v1",
             "--vehicles", "3", "--episodes", "2", "--quiet"]
    assert _cacc_bench(work, ext, "run", *small, "--out", "s").returncode == 0
    ray = _cacc_bench(work, ext, "run", *small, "--out", "r", "--executor", "ray", "--workers",
                      "2")
    assert ray.returncode == 0, ray.stderr
    keep = ["controller", "seed", "reward", "energy_kwh", "gap_rmse_m"]
    pd.testing.assert_frame_equal(pd.read_csv(work / "r" / "runs.csv")[keep],
                                  pd.read_csv(work / "s" / "runs.csv")[keep])
