"""The layers (docs/contributing.md): envs -> marl -> controllers -> benchmark -> analysis -> commands.

``lint-imports`` checks the contract in ``pyproject.toml`` (CI runs it after mypy); these tests
show that it passes on the repository and fails on an upward import.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("infra", "envs", "marl", "controllers", "benchmark", "analysis", "studies",
            "commands")


def _lint(cwd: Path, *config: Path) -> subprocess.CompletedProcess[str]:
    exe = Path(sys.executable).with_name("lint-imports")
    return subprocess.run([str(exe), "--no-cache", *map(str, config)], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def test_the_contract_names_every_package_top_first() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    assert sorted(config["root_packages"]) == sorted(PACKAGES)
    (contract,) = config["contracts"]
    assert contract["type"] == "layers"
    assert contract["layers"] == list(reversed(PACKAGES))


def test_the_repository_keeps_the_layers() -> None:
    res = _lint(ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "1 kept, 0 broken" in res.stdout


def test_a_planted_upward_import_fails(tmp_path: Path) -> None:
    """A copy of the sources with one upward import (infra -> commands) breaks the contract."""
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, tmp_path / pkg,
                        ignore=lambda d, names: [n for n in names
                                                 if not (n.endswith(".py") or (Path(d) / n).is_dir())
                                                 or n == "__pycache__"])
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    assert _lint(tmp_path).returncode == 0  # the copy alone keeps the layers
    planted = tmp_path / "infra" / "limits.py"
    planted.write_text(planted.read_text() + "\nimport commands.cli  # planted upward import\n")
    res = _lint(tmp_path)
    assert res.returncode != 0
    assert "infra.limits -> commands.cli" in res.stdout


def test_the_checker_fails_with_the_layers_reversed(tmp_path: Path) -> None:
    """The same repository against the order upside down: every real import is a violation."""
    config = tmp_path / "reversed.toml"
    layers = ", ".join(f'"{p}"' for p in PACKAGES)
    config.write_text(f"[tool.importlinter]\nroot_packages = [{layers}]\n\n"
                      f'[[tool.importlinter.contracts]]\nid = "reversed"\nname = "reversed"\n'
                      f'type = "layers"\nlayers = [{layers}]\n')
    res = _lint(ROOT, config)
    assert res.returncode != 0
    assert "BROKEN" in res.stdout or "broken" in res.stdout
