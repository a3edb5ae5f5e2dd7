"""studies/publish_reproduction.py: a finished reproduce folder as the committed report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from infra.errors import ConfigError
from studies import publish_reproduction as mod


def _out(tmp_path: Path, status: str = "done") -> Path:
    from PIL import Image

    out = tmp_path / "out"
    (out / "runs").mkdir(parents=True)
    (out / "figures").mkdir()
    (out / "checkpoints" / "bdc-noqsgd").mkdir(parents=True)
    (out / "reproduce.json").write_text(json.dumps({"status": status, "command": "c --out OUT"}))
    (out / "report.md").write_text("# The report\n\n![radar](figures/radar.png)\n")
    for name in mod.TABLES:
        (out / name).write_text(f"{name}\n1\n")
    (out / "runs" / "leaderboard.csv").write_text("rank\n1\n")
    (out / "runs" / "runs.csv").write_text("id\n1\n")
    Image.new("RGB", (40, 30), (200, 10, 10)).save(out / "figures" / "radar.png")
    for rel in ("bdc__catchup-v1__n8__s0", "bdc-noqsgd/bdc__catchup-v1__n8__s0"):
        (out / "checkpoints" / f"{rel}.source.json").write_text('{"source": "shipped"}')
        (out / "checkpoints" / f"{rel}.pt").write_bytes(b"weights")
    return out


def test_the_report_its_tables_figures_and_sources_replace_the_committed_ones(
        tmp_path: Path) -> None:
    dest = tmp_path / "docs" / "paper-reproduction"
    (dest / "figures").mkdir(parents=True)
    (dest / "figures" / "stale.png").write_bytes(b"old")
    written = {p.relative_to(dest).as_posix() for p in mod.publish(_out(tmp_path), "How.", dest)}
    assert written == {"README.md", *mod.TABLES, "leaderboard.csv", "reproduce.json",
                       "figures/radar.png", "sources/bdc__catchup-v1__n8__s0.source.json",
                       "sources/bdc-noqsgd/bdc__catchup-v1__n8__s0.source.json"}
    readme = (dest / "README.md").read_text()
    assert readme.startswith("<!-- Copied from OUT/report.md") and "How.\n\n# The report" in readme
    from PIL import Image

    with Image.open(dest / "figures" / "radar.png") as im:
        assert im.mode == "P" and im.getpixel((5, 5)) is not None
    assert not dest.with_name(dest.name + ".new").exists()


def test_an_unfinished_reproduction_is_refused_and_the_committed_report_kept(
        tmp_path: Path) -> None:
    dest = tmp_path / "docs" / "paper-reproduction"
    dest.mkdir(parents=True)
    (dest / "README.md").write_text("committed")
    with pytest.raises(ConfigError, match="no finished reproduction"):
        mod.publish(_out(tmp_path, status="started"), "How.", dest)
    assert (dest / "README.md").read_text() == "committed"


def test_an_interrupted_swap_leaves_one_whole_report(tmp_path: Path, monkeypatch) -> None:
    """If the new report cannot be moved into place, the committed one is back where it was."""
    out = _out(tmp_path)
    dest = tmp_path / "docs" / "paper-reproduction"
    dest.mkdir(parents=True)
    (dest / "README.md").write_text("the committed report\n")
    real = Path.replace

    def failing(self: Path, target):
        if self.name.endswith(".new"):
            raise KeyboardInterrupt
        return real(self, target)

    monkeypatch.setattr(Path, "replace", failing)
    with pytest.raises(KeyboardInterrupt):
        mod.publish(out, "header", dest)
    monkeypatch.setattr(Path, "replace", real)
    assert (dest / "README.md").read_text() == "the committed report\n"
    assert not dest.with_name(dest.name + ".old").exists()
