"""The documentation site's navigation (``mkdocs.yml``), checked cheaply: no build, no network.

CI builds the site with ``mkdocs build --strict`` (``.ci/run``); these tests catch the commonest
breakages in the default run already: a nav entry whose file is gone, a new Markdown page that
nobody put in the nav, an API page naming a module that moved.
"""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

import pytest

yaml = pytest.importorskip("yaml")

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"


def _config() -> dict:
    return yaml.safe_load((ROOT / "mkdocs.yml").read_text())


def _nav_files(node: object) -> list[str]:
    """Every page path in a nav tree (strings and the values of one-key mappings)."""
    if isinstance(node, str):
        return [] if re.match(r"^[a-z]+://", node) else [node]
    if isinstance(node, list):
        return [p for item in node for p in _nav_files(item)]
    if isinstance(node, dict):
        return [p for value in node.values() for p in _nav_files(value)]
    return []


def _patterns(text: str | None) -> list[str]:
    lines = (text or "").splitlines()
    return [s.strip() for s in lines if s.strip() and not s.strip().startswith("#")]


def _matches(rel: str, pattern: str) -> bool:
    """The gitignore-style patterns this site uses: ``/dir/``, ``/file.md``, ``*.md`` globs."""
    anchored = pattern.startswith("/")
    pattern = pattern.lstrip("/")
    if pattern.endswith("/"):
        folder = pattern.rstrip("/")
        parents = [str(Path(*Path(rel).parts[:i])) for i in range(1, len(Path(rel).parts))]
        return any(fnmatch.fnmatch(p, folder) for p in parents) if anchored else any(
            fnmatch.fnmatch(Path(p).name, folder) for p in parents)
    if anchored or "/" in pattern:
        return fnmatch.fnmatch(rel, pattern)
    return fnmatch.fnmatch(Path(rel).name, pattern)


def test_every_nav_entry_is_an_existing_page() -> None:
    config = _config()
    assert config.get("docs_dir", "docs") == "docs"
    pages = _nav_files(config["nav"])
    assert pages, "mkdocs.yml has an empty nav"
    missing = [p for p in pages if not (DOCS / p).is_file()]
    assert not missing, f"nav entries without a file under docs/: {missing}"
    twice = sorted({p for p in pages if pages.count(p) > 1})
    assert not twice, f"pages listed twice in nav: {twice}"


def test_every_markdown_page_is_in_the_nav_or_deliberately_left_out() -> None:
    config = _config()
    in_nav = set(_nav_files(config["nav"]))
    left_out = _patterns(config.get("not_in_nav")) + _patterns(config.get("exclude_docs"))
    forgotten = []
    for path in sorted(DOCS.rglob("*.md")):
        rel = path.relative_to(DOCS).as_posix()
        if rel not in in_nav and not any(_matches(rel, p) for p in left_out):
            forgotten.append(rel)
    assert not forgotten, (
        f"Markdown pages in neither the nav of mkdocs.yml nor not_in_nav/exclude_docs: "
        f"{forgotten}")


def test_the_pattern_matching_reads_the_config_as_mkdocs_does() -> None:
    assert _matches("scripts/x.md", "/scripts/")
    assert not _matches("a/scripts/x.md", "/scripts/")
    assert _matches("a/scripts/x.md", "scripts/")
    assert _matches("paper-reproduction/sources/a.md", "/paper-reproduction/sources/")
    assert _matches("notes/draft.md", "/notes/draft.md")
    assert _matches("notes/draft.md", "*.md")
    assert not _matches("notes/draft.md", "/draft.md")


def test_every_module_on_the_api_pages_exists() -> None:
    """A ``::: package.module`` line must name a module of this repository, so a renamed or
    moved module fails here rather than only in CI's strict build."""
    missing = []
    named = 0
    for page in sorted((DOCS / "api").glob("*.md")):
        for module in re.findall(r"^:::\s*([\w.]+)\s*$", page.read_text(), flags=re.MULTILINE):
            named += 1
            base = ROOT.joinpath(*module.split("."))
            if not (base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()):
                missing.append(f"{page.name}: {module}")
    assert named > 0
    assert not missing, f"API pages name modules that do not exist: {missing}"


def test_ci_builds_the_site_in_strict_mode() -> None:
    ci = (ROOT / ".ci" / "run").read_text()
    assert "pip install -e '.[docs]'" in ci
    assert re.search(r"mkdocs build --strict", ci)
