"""The contributor guide's worked example (docs/contributing.md): a PPO-family learner added by
one file and one registry entry, taken from the page, trains and runs on a copy of the package."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("infra", "envs", "marl", "controllers", "benchmark", "analysis", "studies",
            "commands")


def _blocks() -> tuple[str, str]:
    text = (ROOT / "docs" / "contributing.md").read_text()
    section = text[text.index("### Worked example: a PPO-family learner"):]
    module, entry = re.findall(r"```python\n(.*?)```", section, re.S)[:2]
    return module, entry


def _cli(tree: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    code = "import sys; from commands.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], cwd=tree, env=env,
                          capture_output=True, text=True, timeout=600)


def test_the_worked_example_learner_lists_trains_and_runs(tmp_path: Path) -> None:
    module, entry = _blocks()
    tree = tmp_path / "src"
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, tree / pkg, ignore=shutil.ignore_patterns(
            "__pycache__", "checkpoints"))
    (tree / "controllers" / "checkpoints").symlink_to(ROOT / "controllers" / "checkpoints")
    (tree / "marl" / "ippo_kl.py").write_text(module)
    registry = tree / "marl" / "learners.py"
    source = registry.read_text()
    end = source.index(")}\n", source.index("LEARNERS: dict[str, LearnerSpec]"))
    registry.write_text(source[:end] + entry + source[end:])

    listed = _cli(tree, "list")
    assert listed.returncode == 0, listed.stderr
    assert "ippo-kl" in listed.stdout
    out = tmp_path / "ckpt"
    trained = _cli(tree, "train", "--algo", "ippo-kl", "--scenario", "catchup-v1",
                   "--steps", "2048", "--set", "n_envs=4", "--set", "rollout_steps=64",
                   "--set", "eval_every_steps=1024", "--set", "kl_coef=0.5", "--out", str(out))
    assert trained.returncode == 0, trained.stderr
    assert (out / "ippo-kl__catchup-v1__n8__s0.pt").is_file()  # a shared policy: any N
    bad = _cli(tree, "train", "--algo", "ippo-kl", "--scenario", "catchup-v1", "--set",
               "kl_coef=-1", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "kl_coef must lie in [0, 100]" in bad.stderr
    ran = _cli(tree, "run", "--controllers", f"ippo-kl[checkpoint_dir={out}]", "--scenarios",
               "catchup-v1", "--vehicles", "3", "--seeds", "1000,1001", "--out",
               str(tmp_path / "runs"))
    assert ran.returncode == 0, ran.stderr
    assert "ippo-kl" in (tmp_path / "runs" / "leaderboard.csv").read_text()
