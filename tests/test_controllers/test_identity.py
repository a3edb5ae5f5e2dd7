"""One policy, one identity (issue 53, point 2): a checkpoint is loaded only as what it records;
a label holds canonical values (one spelling per number, a folder by its resolved path); a
setting named twice runs once; a store reached through a link is not written without its own
folder's lock."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pandas as pd
import pytest
import torch

from benchmark.store import ResultStore
from commands.cli import main as cli
from controllers.policy import CHECKPOINT_DIR, VARIANT_DIR, PolicyController, checkpoint_path
from controllers.registry import CONTROLLERS, controller_label
from infra.errors import ConfigError
from infra.naming import canonical_value, merge_repeats, parse_label

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted(CHECKPOINT_DIR.rglob("*.pt"))
NAME = re.compile(r"(.+?)__(.+?)__n(\d+)__s(\d+)\.pt")


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    capsys.readouterr()
    rc = cli(["run", "--quiet", "--episodes", "1", *argv])
    return rc, capsys.readouterr().err


# ------------------------------------------------------------------ what a checkpoint records
def test_every_shipped_checkpoint_records_what_the_controller_loads_it_as() -> None:
    """Loaded as the controller loads it (its folder: the leaderboard's or a variant; its name:
    algorithm, scenario, N and seed), each shipped file records exactly that."""
    assert len(SHIPPED) > 100
    for path in SHIPPED:
        algo, scenario, n, seed = NAME.fullmatch(path.name).groups()  # type: ignore[union-attr]
        options: dict[str, object] = {"seed": int(seed)}
        if path.parent != CHECKPOINT_DIR:
            assert path.parent.parent == VARIANT_DIR
            options["variant"] = path.parent.name
        if "vehicles" in PolicyController.options_of(algo):
            options["vehicles"] = int(n)
        ctrl = PolicyController(algo, **options)  # type: ignore[arg-type]
        source, n_run = ctrl._source(scenario, int(n))
        folder = VARIANT_DIR / ctrl.variant if ctrl.variant else None
        assert checkpoint_path(algo, source, n_run, ctrl.seed, folder) == path
        data = torch.load(path, map_location="cpu", weights_only=True)
        assert {k: data[k] for k in ("algo", "scenario", "n_vehicles", "seed")} == \
            ctrl._identity(source, n_run), path


@pytest.fixture
def copied(tmp_path: Path) -> Path:
    """A folder where a seed-2 bdc file sits under the seed-0 name, and an ippo catchup-v1 file
    under the slowdown-v1 name."""
    folder = tmp_path / "ck"
    folder.mkdir()
    shutil.copy(CHECKPOINT_DIR / "bdc__catchup-v1__n8__s2.pt", folder / "bdc__catchup-v1__n8__s0.pt")
    shutil.copy(CHECKPOINT_DIR / "ippo__catchup-v1__n8__s0.pt",
                folder / "ippo__slowdown-v1__n8__s0.pt")
    return folder


@pytest.mark.parametrize("controller, scenario, says", [
    ("bdc", "catchup-v1", "was trained with seed 2, not 0"),
    ("ippo", "slowdown-v1", "was trained on catchup-v1, not slowdown-v1"),
])
def test_a_copied_or_renamed_checkpoint_is_refused_naming_both(
        copied: Path, tmp_path: Path, controller: str, scenario: str, says: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    rc, err = _run(capsys, "--controllers", f"{controller}:checkpoint_dir={copied}",
                   "--scenarios", scenario, "--out", str(tmp_path / "out"))
    assert rc == 2 and says in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out" / "store.sqlite").exists()


def test_an_explicit_file_is_what_it_records(capsys: pytest.CaptureFixture[str],
                                            tmp_path: Path) -> None:
    """checkpoint=FILE takes no option that picks a file by name (seed, scenario)."""
    path = CHECKPOINT_DIR / "bdc__catchup-v1__n2__s0.pt"
    for extra in ("seed=1", "scenario=slowdown-v1"):
        rc, err = _run(capsys, "--controllers", f"bdc:checkpoint={path},{extra}", "--vehicles",
                       "2", "--out", str(tmp_path / extra))
        assert rc == 2 and "checkpoint=FILE names one policy" in err, err
    with pytest.raises(ConfigError, match="names no path"):
        PolicyController("ippo", checkpoint="")


# ------------------------------------------------------------------ canonical labels
def test_one_number_is_one_label() -> None:
    spellings = ("2", "2.0", "2e0", "+2", " 2.00")
    assert {controller_label("cacc", {"kp": s}) for s in spellings} == {"cacc[kp=2]"}
    assert controller_label("cacc", {"kp": 2.0}) == controller_label("cacc", {"kp": "2"})
    assert controller_label("bdc", {"seed": "+1"}) == "bdc[seed=1]"
    assert controller_label("wac", {"untrained": "yes"}) == "wac[untrained=true]"
    assert controller_label("safe:cacc", {"safe_pred_brake_mps2": "4.0"}) == \
        "safe:cacc[safe_pred_brake_mps2=4]"
    assert [canonical_value(v) for v in (0.1, -0.0, 1e-5, 1e16, True, 3)] == \
        ["0.1", "0", "1e-05", "1e+16", "true", "3"]


def _committed_labels() -> set[str]:
    """Controller labels of the committed results: the CSV tables' label columns and the
    labels the documents quote."""
    labels: set[str] = set()
    for path in [*ROOT.glob("docs/**/*.csv"), *ROOT.glob("tests/golden/*.csv")]:
        table = pd.read_csv(path)
        for column in ("controller", "label"):
            if column in table and table[column].dtype == object:
                labels |= {v for v in table[column] if "[" in v}
    for path in [ROOT / "README.md", *ROOT.glob("docs/**/*.md")]:
        labels |= set(re.findall(r"`([a-z0-9:-]+\[[^]`\s]*\])`", path.read_text()))
    return labels


def test_committed_labels_are_canonical(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Every controller label in the committed results reads back as itself (reproduce's
    folders are relative to its output, its working folder)."""
    monkeypatch.chdir(tmp_path)
    labels = _committed_labels()
    checked = []
    for label in labels:
        try:
            name, options = parse_label(label)
        except ConfigError:  # an abbreviation (``bdc[mode=greedy,...]``)
            continue
        if name in CONTROLLERS or name.removeprefix("safe:") in CONTROLLERS:
            assert controller_label(name, options) == label
            checked.append(label)
    assert len(checked) > 30


def test_a_folder_is_named_by_its_resolved_path(monkeypatch: pytest.MonkeyPatch,
                                                tmp_path: Path) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ck").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "ck")
    for key, leaf in (("checkpoint_dir", ""), ("checkpoint", "/f.pt")):
        spellings = [f"ck{leaf}", f"./ck/{leaf}", f"link{leaf}", f"{tmp_path}/ck{leaf}"]
        assert {controller_label("bdc", {key: s}) for s in spellings} == \
            {f"bdc[{key}=ck{leaf}]"}
    outside = tmp_path.parent / "elsewhere"
    assert controller_label("bdc", {"checkpoint_dir": "../elsewhere/"}) == \
        f"bdc[checkpoint_dir={outside.resolve().as_posix()}]"


# ------------------------------------------------------------------ a setting named twice
def test_merge_repeats_keeps_the_first_of_each() -> None:
    assert merge_repeats(["a", "b", "a2"], ["x", "y", "x"], "--opt") == \
        (["a", "b"], "--opt: x named more than once; each is used once")
    assert merge_repeats(["a"], ["x"], "--opt") == (["a"], "")


def test_run_merges_one_setting_named_twice(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    rc, err = _run(capsys, "--controllers", "cacc:kp=0.3,cacc:kp=0.30,cacc:kp=3e-1",
                   "--scenarios", "catchup-v1", "--vehicles", "2", "--out", str(tmp_path))
    assert rc == 0 and "--controllers: cacc[kp=0.3] named more than once" in err
    assert list(pd.read_csv(tmp_path / "runs.csv")["controller"]) == ["cacc[kp=0.3]"]


def test_generalise_lists_a_column_named_twice_once(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(["generalise", "--columns", "catchup,catchup", "--controllers", "cacc,cacc",
                "--episodes", "1", "--executor", "serial", "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "--columns: catchup named more than once" in err
    assert "--controllers: cacc named more than once" in err
    cells = pd.read_csv(tmp_path / "matrix.csv")
    assert list(zip(cells["row"], cells["column"], strict=True)) == [("cacc", "catchup")]


# ------------------------------------------------------------------ a store through a link
def test_a_store_that_links_into_another_folder_is_not_written(tmp_path: Path) -> None:
    ResultStore(tmp_path / "home", writer=True).close()
    store = tmp_path / "home" / "store.sqlite"
    before = store.read_bytes()
    (tmp_path / "here").mkdir()
    (tmp_path / "here" / "store.sqlite").symlink_to(store)
    with pytest.raises(ConfigError, match=f"is a link into {tmp_path / 'home'}"):
        ResultStore(tmp_path / "here", writer=True)
    ResultStore(tmp_path / "here").close()  # a reader is not refused
    assert store.read_bytes() == before
