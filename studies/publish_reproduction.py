"""Publish a finished paper-budget ``cacc-bench reproduce`` folder as the committed report
(``docs/paper-reproduction``), replacing the one there.

    .venv/bin/python -m studies.publish_reproduction OUT HEADER.md

``README.md`` is ``HEADER.md`` (how the run was made, written by hand) followed by
``OUT/report.md`` as the command wrote it; beside it the CSV behind every table,
``leaderboard.csv`` (``OUT/runs/leaderboard.csv``), ``reproduce.json``, every policy's
``sources/*.source.json`` and the figures, re-encoded with 128 colours to keep the clone small.
The results store and the checkpoints stay in OUT.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from infra.atomic import signals_held
from infra.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / "docs" / "paper-reproduction"
#: The report's tables, as ``reproduce`` writes them into OUT.
TABLES = ("claims.csv", "table1.csv", "table2.csv", "table3.csv", "sizes.csv", "power_basis.csv")
COLOURS = 128


def publish(out: Path, header: str, dest: Path = DEST) -> list[Path]:
    """Write ``dest`` from ``out``; the files written."""
    manifest = json.loads((out / "reproduce.json").read_text())
    if manifest.get("status") != "done" or not (out / "report.md").exists():
        raise ConfigError(f"{out}: no finished reproduction (reproduce.json status "
                          f"{manifest.get('status')!r}); complete it with --resume first")
    from PIL import Image

    staged = dest.with_name(dest.name + ".new")
    if staged.exists():
        shutil.rmtree(staged)
    (staged / "figures").mkdir(parents=True)
    (staged / "README.md").write_text(
        f"<!-- Copied from OUT/report.md by studies/publish_reproduction.py (figures "
        f"re-encoded with {COLOURS} colours; every number as the command printed it). -->\n\n"
        f"{header.strip()}\n\n{(out / 'report.md').read_text()}")
    for name in TABLES:
        shutil.copyfile(out / name, staged / name)
    shutil.copyfile(out / "runs" / "leaderboard.csv", staged / "leaderboard.csv")
    shutil.copyfile(out / "reproduce.json", staged / "reproduce.json")
    for png in sorted((out / "figures").glob("*.png")):
        with Image.open(png) as im:
            im.convert("RGB").quantize(colors=COLOURS).save(staged / "figures" / png.name,
                                                            optimize=True)
    checkpoints = out / "checkpoints"
    for src in sorted(checkpoints.rglob("*.source.json")):
        target = staged / "sources" / src.relative_to(checkpoints)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, target)
    # the committed report is set aside, not deleted, until the new one is in its place, and put
    # back if that fails, so an interruption leaves the old report or the new one, whole
    old = dest.with_name(dest.name + ".old")
    if old.exists():
        shutil.rmtree(old)
    with signals_held():
        if dest.exists():
            dest.replace(old)
        try:
            staged.replace(dest)
        except BaseException:
            if old.exists():
                old.replace(dest)
            raise
    if old.exists():
        shutil.rmtree(old)
    return sorted(p for p in dest.rglob("*") if p.is_file())


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m studies.publish_reproduction OUT HEADER.md")
    try:
        written = publish(Path(sys.argv[1]), Path(sys.argv[2]).read_text())
    except ConfigError as err:
        sys.exit(str(err))
    print(f"wrote {len(written)} files into {DEST.relative_to(ROOT)}")
