"""Ship the policies a paper-budget ``cacc-bench reproduce`` trained, so that the command copies
them on any machine instead of training them (``--retrain`` trains them again).

    .venv/bin/python -m studies.ship_reproduction OUT

Each trained run of ``OUT/checkpoints`` (its ``.source.json`` says ``trained``) goes with its
curve and log to the variant folder ``controllers/checkpoints/variants/paper``, or, for an
ablation (a subfolder of ``checkpoints`` named after it), to ``variants/<ablation>``. A file
already shipped there is left as it is when equal and refused when not: nothing shipped is
overwritten. Prints each file it ships, relative to the repository.
"""

from __future__ import annotations

import filecmp
import functools
import json
import shutil
import sys
from pathlib import Path

from controllers.policy import VARIANT_DIR
from infra.atomic import StagedFiles
from infra.errors import ConfigError

#: The repository, which the shipped files are named relative to.
ROOT = VARIANT_DIR.parents[2]
#: The variant folder of the report's own (non-ablation) policies.
PAPER_VARIANT = "paper"
SUFFIXES = (".pt", ".curve.csv", ".log")


def destination(checkpoints: Path, source: Path) -> Path:
    """The shipped folder of the run whose record is ``source`` (below ``checkpoints``)."""
    rel = source.parent.relative_to(checkpoints)
    return VARIANT_DIR / (rel.parts[0] if rel.parts else PAPER_VARIANT)


def ship(out: Path) -> list[Path]:
    """Copy every trained run of ``out`` to its shipped folder; the files shipped."""
    checkpoints = out / "checkpoints"
    if not checkpoints.is_dir():
        raise ConfigError(f"{out}: no checkpoints folder (not a reproduce --out folder?)")
    shipped: list[Path] = []
    for source in sorted(checkpoints.rglob("*.source.json")):
        if json.loads(source.read_text()).get("source") != "trained":
            continue
        stem = source.name.removesuffix(".source.json")
        folder = destination(checkpoints, source)
        pairs = [(source.parent / f"{stem}{x}", folder / f"{stem}{x}") for x in SUFFIXES]
        missing = [src.relative_to(out).as_posix() for src, _ in pairs if not src.exists()]
        if missing:
            raise ConfigError(f"{', '.join(missing)}: missing (is the run finished?)")
        todo = []
        for src, dst in pairs:
            if not dst.exists():
                todo.append((src, dst))
            elif not filecmp.cmp(src, dst, shallow=False):
                raise ConfigError(f"{dst.relative_to(ROOT)} is shipped with other contents; "
                                  "nothing shipped is overwritten")
        folder.mkdir(parents=True, exist_ok=True)
        with StagedFiles() as staged:  # a run's files land together, or none (interrupted)
            for src, dst in todo:
                staged.write_with(dst, functools.partial(shutil.copyfile, src))
            staged.commit()
        shipped += [dst for _, dst in todo]
    return shipped


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m studies.ship_reproduction OUT")
    try:
        for path in ship(Path(sys.argv[1])):
            print(path.relative_to(ROOT))
    except ConfigError as err:
        sys.exit(str(err))
