"""The README never lies: its set-up and test commands are the ones CI runs, and its main
command works (in small form)."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from run_marks import FULL

ROOT = Path(__file__).resolve().parent.parent


def _blocks(section: str) -> list[str]:
    text = (ROOT / "README.md").read_text()
    m = re.search(rf"^## {re.escape(section)}\n(.*?)(?=^## )", text, re.S | re.M)
    assert m, f"README has no section {section!r}"
    return [ln.strip() for b in re.findall(r"```bash\n(.*?)```", m.group(1), re.S)
            for ln in b.strip().splitlines() if ln.strip() and not ln.startswith("#")]


def test_setup_has_exactly_two_commands_and_ci_uses_them() -> None:
    install, main_cmd = _blocks("Set up")
    ci = (ROOT / ".ci" / "run").read_text()
    assert install in ci
    (test_cmd,) = _blocks("Test")
    assert test_cmd in ci
    assert main_cmd.startswith(".venv/bin/cacc-bench run")


def _extras_modules() -> set[str]:
    """The top-level modules of every optional dependency (pyproject's extras), as installed
    here, and not of a base dependency."""
    import importlib.metadata
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]

    def dist(req: str) -> str:
        return re.split(r"[\[<>=!~; ]", req, maxsplit=1)[0].lower().replace("_", "-")

    base = {dist(r) for r in project["dependencies"]}
    extras = {dist(r) for reqs in project["optional-dependencies"].values() for r in reqs} - base
    out = set()
    for module, dists in importlib.metadata.packages_distributions().items():
        if any(d.lower().replace("_", "-") in extras for d in dists):
            out.add(module)
    return out


#: Runs the command line with the extras' modules unimportable, as on the base install.
BASE_INSTALL = """
import importlib.abc, sys
BLOCKED = set(sys.argv.pop(1).split(","))
class Extras(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r} (an extra)", name=name)
sys.meta_path.insert(0, Extras())
from commands.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_main_command_in_small_form_on_the_base_install(tmp_path: Path) -> None:
    """The README's install is the base package alone: the main command runs (in small form)
    with no module of an extra importable (Ray, Optuna, Gymnasium, PettingZoo, the test and
    documentation tools), and so do ``list`` and ``stability``."""
    blocked = _extras_modules()
    assert {"optuna", "gymnasium", "pettingzoo", "pytest"} <= blocked  # installed here, as CI's
    install, main_cmd = _blocks("Set up")
    assert install.endswith("pip install -e .")
    args = shlex.split(main_cmd)[2:]  # after ".venv/bin/cacc-bench run"
    small = ["--episodes", "1", "--out", str(tmp_path / "run")]

    def base(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", BASE_INSTALL, ",".join(sorted(blocked)),
                               *argv], cwd=tmp_path, capture_output=True, text=True, timeout=900)

    res = base("run", *args, *small)
    assert res.returncode == 0, res.stderr
    lb = pd.read_csv(tmp_path / "run" / "leaderboard.csv")
    assert len(lb) >= 2
    assert "leaderboard.csv" in res.stdout
    assert "next: `cacc-bench plot run`" in res.stdout
    for argv in (["list"], ["stability", "--out", str(tmp_path / "s")]):
        res = base(*argv)
        assert res.returncode == 0, (argv, res.stderr)
    res = base("tune", "--out", str(tmp_path / "t"))  # an extra's command: one line, exit 2
    assert res.returncode == 2 and res.stderr.count("\n") == 1
    assert "pip install -e '.[marl]'" in res.stderr


def test_tour_commands_in_small_form(tmp_path: Path) -> None:
    exe = str(Path(sys.executable).parent / "cacc-bench")
    out = tmp_path / "r"
    for cmd in (
        [exe, "list"],
        [exe, "run", "--controllers", "ovm", "--scenarios", "catchup-v1", "--vehicles", "2",
         "--episodes", "1", "--out", str(out)],
        [exe, "leaderboard", str(out)],
        [exe, "plot", str(out), "--no-energy-map"],
        [exe, "fit-power"],
    ):
        res = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, (cmd, res.stderr)
    assert any((out / "figures").glob("leaderboard.png"))


def test_the_example_controller_runs_as_the_readme_says(tmp_path: Path) -> None:
    """The example controller file (docs/contributing.md, "Add a controller", which the README
    links): saved and run, it passes the contract check and prints what the page says it
    prints."""
    text = (ROOT / "docs" / "contributing.md").read_text()
    text = text[text.index("## Add a controller"):]
    text = text[:text.index("\n## ", 1)]  # the section alone
    (code,) = re.findall(r"```python\n(.*?)```", text, re.S)
    (claim,) = re.findall(r"It prints `([^`]*)`", text)
    (tmp_path / "my_controller.py").write_text(code)
    res = subprocess.run([sys.executable, "my_controller.py"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=600, env={"PYTHONPATH": str(ROOT), "PATH": ""})
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == claim


def test_the_readme_table_is_rows_of_the_full_one() -> None:
    """The README's small results table is rows of the full table in docs/results.md, copied
    verbatim (so the numbers the tests pin there are the README's too)."""
    rows = [ln for ln in (ROOT / "README.md").read_text().splitlines()
            if re.match(r"^\| (catchup|slowdown)-v1 \|", ln)]
    assert len(rows) >= 3
    full = set((ROOT / "docs" / "results.md").read_text().splitlines())
    assert [r for r in rows if r not in full] == []


def test_the_readme_stays_a_short_guide() -> None:
    """A user's guide, not lab notes: about 250 lines at most and no dated measurement."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text)


@FULL
def test_the_main_table_on_the_test_seeds_is_what_the_controllers_score() -> None:
    """The README's main table (the test seeds): the `cacc` row and the pooled rewards of the
    learned rows, recomputed from the shipped checkpoints; the residual within 1 % of `cacc`,
    the time-aware residual ahead of it."""
    import numpy as np

    from benchmark.rollout import rollout_batch
    from controllers.registry import make_controller
    from envs.params import TEST_SEEDS
    from envs.scenarios import make_scenario

    text = (ROOT / "README.md").read_text()
    row = {m.group(1): m.group(2) for m in re.finditer(
        r"^\| catchup-v1 \| \d+ \| `([^`]+)` \| \d+/\d+ \| (-?\d+\.\d\d) ", text, re.M)}
    sc, seeds = make_scenario("catchup-v1"), list(TEST_SEEDS[:50])

    def mean(name: str, **opts: str) -> float:
        return float(np.mean([t.reward.mean() for t in rollout_batch(
            make_controller(name, **opts), sc, 8, seeds)]))

    cacc = mean("cacc")
    assert f"{cacc:.2f}" == row["cacc"]
    for label, opts in (("ippo[scenario=mixed-v1,seeds=0+1+2]", {"scenario": "mixed-v1"}),
                        ("ippo[seeds=0+1+2,variant=residual-cacc]", {"variant": "residual-cacc"}),
                        ("ippo[seeds=0+1+2,variant=residual-timed]", {"variant": "residual-timed"})):
        pooled = np.mean([mean("ippo", **opts, seed=str(s)) for s in (0, 1, 2)])
        assert pooled == pytest.approx(float(row[label]), rel=5e-4), label  # across CPUs
    assert (cacc - float(row["ippo[seeds=0+1+2,variant=residual-cacc]"])) / -cacc < 0.01
    assert float(row["ippo[seeds=0+1+2,variant=residual-timed]"]) > cacc  # the reading's lead


def test_the_string_stability_readings_are_the_committed_tables() -> None:
    """The main table's reading (only `cacc` and `cmpc` string stable; the leading residual's
    sweep peak against its time-domain gain), the mark's threshold, and the string-stability
    bullet's "fixed gains at the segment's ends score as well" (docs/string-stability)."""
    import pandas as pd

    from benchmark.sweep import SWEEP_TOL

    text = (ROOT / "README.md").read_text()
    flat = " ".join(text.split())
    assert f"**string stable** `yes` when at most {1 + SWEEP_TOL:g}" in flat
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in text.splitlines()
            if ln.startswith("| catchup-v1 |")]
    stable = sorted(r[2].strip("`") for r in rows if r[11] == "yes")
    assert stable == ["cacc", "cmpc"] and "only `cacc` and `cmpc` are string stable" in flat
    lead = next(r for r in rows if r[1] == "1")
    assert f"oscillation {float(lead[10]):.1f}-fold per vehicle" in flat
    assert f"its time-domain gain on this scenario, {lead[9]}, does not show it" in flat
    rewards = pd.read_csv(ROOT / "docs" / "string-stability" / "rewards.csv")
    ideal = rewards[rewards["channel"] == "ideal"].groupby(["entry", "scenario"])["reward"].first()
    assert "fixed gains at the segment's ends score as well" in flat
    for sc in ("catchup-v1", "slowdown-v1"):
        ends = max(ideal[(f"cacc (segment's {e} end)", sc)] for e in ("stiff", "soft"))
        assert ends >= ideal[("ippo-gains", sc)], sc
