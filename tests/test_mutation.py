"""Mutation testing in small (nightly-style): mutmut over ``marl/consensus.py`` must kill at least
85 % of its mutants. Marked ``slow`` and ``mutation``; it needs the ``mutation`` extra
(``pip install -e '.[dev,mutation]'``) and runs in a copy of the project, so a developer's own
``mutants/`` folder is left alone. The whole study: docs/mutation-testing.md."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
MODULE = "marl/consensus.py"
GOAL = 0.85

pytestmark = [pytest.mark.slow, pytest.mark.mutation]


def test_consensus_mutation_score(tmp_path: Path) -> None:
    mutmut = Path(sys.executable).with_name("mutmut")
    if not mutmut.exists():
        pytest.skip("mutmut is not installed: pip install -e '.[dev,mutation]'")
    copy = tmp_path / "project"
    shutil.copytree(ROOT, copy, ignore=shutil.ignore_patterns(
        ".venv", ".git", "mutants", "results", "logs", "*.pt", "__pycache__"))
    toml = (copy / "pyproject.toml").read_text()
    toml = re.sub(r"only_mutate = \[[^\]]*\]", f'only_mutate = ["{MODULE}"]', toml)
    toml = re.sub(r"pytest_add_cli_args_test_selection = \[[^\]]*\]",
                  'pytest_add_cli_args_test_selection = ["tests/test_marl/test_marl_kernels.py"]', toml)
    (copy / "pyproject.toml").write_text(toml)
    subprocess.run([str(mutmut), "run", "--max-children", "2"], cwd=copy, capture_output=True,
                   text=True, timeout=1800)
    res = subprocess.run([str(mutmut), "results", "--all", "true"], cwd=copy,
                         capture_output=True, text=True, timeout=300)
    status = [line.rsplit(": ", 1)[-1].strip() for line in res.stdout.splitlines() if ": " in line]
    killed = sum(s == "killed" for s in status)
    assert len(status) > 30, res.stdout[-2000:] + res.stderr[-2000:]
    assert killed / len(status) >= GOAL, f"{killed}/{len(status)} killed"
