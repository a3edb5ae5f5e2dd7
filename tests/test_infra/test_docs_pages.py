"""The documentation pages a new user starts from: the Python guide runs as written, every
command has a guide page, the home page's figure has a command that makes it, and wide tables
stay readable."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

yaml = pytest.importorskip("yaml")

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def _python_blocks(page: Path) -> list[str]:
    """The ```python blocks of a Markdown page, in order."""
    return re.findall(r"^```python\n(.*?)^```", page.read_text(), flags=re.MULTILINE | re.DOTALL)


def test_the_python_guide_runs_as_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Every code block of docs/guide/python.md, in order, in one namespace, from an empty
    working directory (as a notebook runs them)."""
    pytest.importorskip("gymnasium")
    pytest.importorskip("pettingzoo")
    blocks = _python_blocks(DOCS / "guide" / "python.md")
    assert len(blocks) >= 6
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {"__name__": "__guide__"}
    for i, code in enumerate(blocks):
        try:
            exec(compile(code, f"python.md block {i + 1}", "exec"), namespace)  # noqa: S102
        except Exception as exc:  # name the block that broke
            raise AssertionError(f"docs/guide/python.md block {i + 1} fails: {exc!r}") from exc
    said = capsys.readouterr().out
    # what the page says the blocks show
    assert "MultiDiscrete([4 4 4 4 4 4 4 4]) (8, 15)" in said
    assert "['follower_1', 'follower_2', 'follower_3', 'follower_4']" in said
    assert "11 m + 0.6 s x v" in said  # cacc's own policy: r = 20 m - 0.6 s x 15 m/s
    figures = tmp_path / "results" / "python-guide" / "figures"
    assert (figures / "per_vehicle__slowdown-v1__n4.png").is_file()
    assert len(list(figures.glob("timespace__*s2001.png"))) == 2  # the second seed, both laws


def _nav_pages() -> set[str]:
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())

    def walk(node: object) -> list[str]:
        if isinstance(node, str):
            return [node]
        if isinstance(node, list):
            return [p for item in node for p in walk(item)]
        if isinstance(node, dict):
            return [p for v in node.values() for p in walk(v)]
        return []

    return set(walk(config["nav"]))


def test_every_command_has_a_guide_page_in_the_nav_and_the_guide_table() -> None:
    from commands.cli import SUBCOMMANDS

    nav = _nav_pages()
    table = (DOCS / "guide" / "index.md").read_text()
    for command in SUBCOMMANDS:
        page = DOCS / "guide" / f"{command}.md"
        assert page.is_file(), f"no guide page docs/guide/{command}.md for `{command}`"
        assert f"cacc-bench {command}" in page.read_text(), f"{page.name} never shows the command"
        assert f"guide/{command}.md" in nav, f"docs/guide/{command}.md is not in mkdocs.yml's nav"
        assert f"]({command}.md)" in table, f"the guide's command table has no row for {command}"


def test_the_guide_links_the_python_page_and_the_safety_filter() -> None:
    table = (DOCS / "guide" / "index.md").read_text()
    assert "](python.md)" in table
    assert "](../safety-filter.md)" in table
    assert (DOCS / "safety-filter.md").is_file()


def _home_head() -> str:
    """The home page before its table of links."""
    return (DOCS / "index.md").read_text().split("## Where to go")[0]


def test_the_home_page_opens_with_install_and_run() -> None:
    head = _home_head()
    assert "pip install -e ." in head
    assert "cacc-bench run" in head and "cacc-bench plot" in head


def test_the_home_pages_result_is_what_the_controllers_score() -> None:
    """The one result: the mean reward of `cacc` and `ovm` on the first 50 test seeds of
    catchup-v1, recomputed (and the same as the README's main table)."""
    import numpy as np

    from benchmark.rollout import rollout_batch
    from controllers.registry import make_controller
    from envs.params import TEST_SEEDS
    from envs.scenarios import make_scenario

    result = _home_head().split("## One result")[1].split("##")[0]
    quoted: dict[str, str] = {}
    for name, value in re.findall(r"\(`(\w+)`\) scores (?:a mean reward of )?(-?\d+\.\d\d)",
                                  result):
        quoted[name] = value
    assert set(quoted) == {"cacc", "ovm"}
    sc = make_scenario("catchup-v1")
    readme = (ROOT / "README.md").read_text()
    for name, value in quoted.items():
        trajs = rollout_batch(make_controller(name), sc, 8, list(TEST_SEEDS[:50]))
        assert not any(t.collided for t in trajs)
        assert f"{np.mean([t.reward.mean() for t in trajs]):.2f}" == value
        assert re.search(rf"^\| catchup-v1 \| \d+ \| `{name}` \| 0/50 \| {value} ", readme,
                         flags=re.MULTILINE), f"the README's row of {name} says otherwise"


def test_the_home_pages_figure_is_what_its_command_draws(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The figure is committed, and the commands the page names draw a figure of that name."""
    import analysis.plots as plots
    from commands.cli import main

    section = _home_head().split("## One figure")[1]
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", section)
    assert len(figures) == 1 and (DOCS / figures[0]).is_file()
    run = re.search(r"`cacc-bench (run [^`]+)`", section)
    assert run is not None and "`cacc-bench plot`" in section
    args = run.group(1).split()
    out = tmp_path / "ring"
    args[args.index("--out") + 1] = str(out)
    assert main([*args, "--quiet"]) == 0
    stems: list[str] = []
    monkeypatch.setattr(plots, "_save", lambda fig, d, stem: stems.append(stem) or [])
    assert main(["plot", str(out), "--no-energy-map"]) == 0
    assert Path(figures[0]).stem in stems


def test_wide_tables_scroll_instead_of_wrapping_labels() -> None:
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    sheets = config.get("extra_css", [])
    assert sheets, "mkdocs.yml names no extra_css"
    css = "".join((DOCS / s).read_text() for s in sheets)
    assert re.search(r"white-space:\s*nowrap", css)
    assert re.search(r"overflow-x:\s*auto", css)


def test_the_home_page_counts_the_packages_it_lists() -> None:
    home = (DOCS / "index.md").read_text()
    words = {"six": 6, "seven": 7, "eight": 8, "nine": 9}
    said = re.search(r"The code is (\w+) top-level packages", home)
    assert said is not None
    listed = re.findall(r"^- `(\w+)`:", home.split("## The packages")[1], flags=re.MULTILINE)
    layers = ROOT / "pyproject.toml"
    contract = re.search(r"layers\s*=\s*\[(.*?)\]", layers.read_text(), flags=re.DOTALL)
    assert contract is not None
    in_contract = re.findall(r'"(\w+)"', contract.group(1))
    assert words[said.group(1)] == len(listed) == len(in_contract)
    assert sorted(listed) == sorted(in_contract)  # every layer of the import contract


def test_the_python_notebook_holds_the_guides_code() -> None:
    """docs/guide/python-notebook.ipynb (rendered by the site) has the page's Python blocks as its code
    cells, in order, so the notebook runs what the test above runs (the install cell aside)."""
    import json

    nb = json.loads((DOCS / "guide" / "python-notebook.ipynb").read_text())
    cells = ["".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"]
    python = [c for c in cells if not c.startswith("%%bash")]
    blocks = _python_blocks(DOCS / "guide" / "python.md")
    assert [c.strip() for c in python] == [b.strip() for b in blocks]
    assert nb["metadata"]["kernelspec"]["name"] == "python3"
