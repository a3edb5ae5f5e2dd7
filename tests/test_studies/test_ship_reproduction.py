"""studies/ship_reproduction.py: a reproduction's trained policies into the shipped
variant folders, never over a shipped file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from infra.errors import ConfigError
from studies import ship_reproduction


def _module(variants: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(ship_reproduction, "VARIANT_DIR", variants)
    monkeypatch.setattr(ship_reproduction, "ROOT", variants.parent)
    return ship_reproduction


def _run(folder: Path, stem: str, source: str, payload: str = "w") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for suffix in (".pt", ".curve.csv", ".log"):
        (folder / f"{stem}{suffix}").write_text(f"{payload}{suffix}")
    (folder / f"{stem}.source.json").write_text(json.dumps({"source": source}))


def test_trained_runs_ship_to_their_variant_and_copied_ones_stay(tmp_path: Path,
                                                                 monkeypatch) -> None:
    mod = _module(tmp_path / "repo" / "variants", monkeypatch)
    out = tmp_path / "out"
    _run(out / "checkpoints", "bdc__slowdown-v1__n8__s0", "trained")
    _run(out / "checkpoints", "bdc__catchup-v1__n8__s0", "shipped")  # copied: already shipped
    _run(out / "checkpoints" / "bdc-noqsgd", "bdc__catchup-v1__n8__s1", "trained")
    got = {p.relative_to(tmp_path / "repo").as_posix() for p in mod.ship(out)}
    assert got == {f"variants/paper/bdc__slowdown-v1__n8__s0{x}" for x in mod.SUFFIXES} | {
        f"variants/bdc-noqsgd/bdc__catchup-v1__n8__s1{x}" for x in mod.SUFFIXES}
    assert mod.ship(out) == []  # equal files: nothing more, nothing refused
    _run(out / "checkpoints", "bdc__slowdown-v1__n8__s0", "trained", payload="other")
    with pytest.raises(ConfigError, match="shipped with other contents"):
        mod.ship(out)
    assert (tmp_path / "repo" / "variants" / "paper" / "bdc__slowdown-v1__n8__s0.pt"
            ).read_text() == "w.pt"


def test_an_unfinished_run_ships_nothing(tmp_path: Path, monkeypatch) -> None:
    mod = _module(tmp_path / "repo" / "variants", monkeypatch)
    out = tmp_path / "out"
    _run(out / "checkpoints", "ia2c__catchup-v1__n2__s1", "trained")
    (out / "checkpoints" / "ia2c__catchup-v1__n2__s1.log").unlink()
    with pytest.raises(ConfigError, match="missing"):
        mod.ship(out)
    assert not (tmp_path / "repo" / "variants").exists()
