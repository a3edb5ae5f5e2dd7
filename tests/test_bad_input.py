"""Bad input, every subcommand: exit 2 and one clear message, no traceback, nothing stored."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from commands.cli import main as cli

#: command -> argument lists that must be refused before any work. ``{FILE}`` is an existing
#: plain file (where a folder or checkpoint is expected), ``{EMPTY}`` an empty folder.
CASES: dict[str, list[list[str]]] = {
    "run": [
        ["--controllers", "nope"],
        ["--controllers", ""],
        ["--controllers", "ovm:alpha=abc"],
        ["--controllers", "ovm:alpha=nan"],
        ["--controllers", "ovm:alpha=inf"],
        ["--controllers", "ovm:alpha=1e400"],
        ["--controllers", "ovm:gamma=1"],
        ["--controllers", "mpc:horizon=1.5"],
        ["--controllers", "mpc:horizon=0"],
        ["--controllers", "mpc:horizon=-3"],
        ["--controllers", "mpc:horizon=99999999999999999999999"],
        ["--controllers", "mpc:smooth_max_kw=0"],
        ["--controllers", "cacc:feedforward=maybe"],
        ["--controllers", "cacc:feedforward=2"],
        ["--controllers", "cacc:time_gap_s=-1"],
        ["--controllers", "bdc:seed=-1"],
        ["--controllers", "bdc:seed=x"],
        ["--controllers", "bdc:seed=7"],
        ["--controllers", "bdc:mode=argmax"],
        ["--controllers", "bdc:checkpoint=/nope.pt"],
        ["--controllers", "bdc:checkpoint={FILE}"],
        ["--controllers", "bdc:variant=zzz"],
        ["--controllers", "bdc:untrained=maybe"],
        ["--controllers", "duty:k=0"],
        ["--controllers", "duty:k=-2"],
        ["--controllers", "duty:k_max=0"],
        ["--controllers", "openacc-real", "--scenarios", "catchup-v1"],
        ["--controllers", "=1"],
        ["--controllers", "alpha=1,ovm"],
        ["--scenarios", "nope"],
        ["--scenarios", ""],
        ["--scenarios", "sine-v1:amplitude_mps=-1"],
        ["--scenarios", "sine-v1:amplitude_mps=nan"],
        ["--scenarios", "sine-v1:frequency_hz=10"],
        ["--scenarios", "sine-v1:nope=1"],
        ["--scenarios", "catchup-v1:window=x"],
        ["--scenarios", "sine-v1:amplitude_mps"],
        # arrangements that make no sense (mixed traffic)
        ["--controllers", "cacc", "--scenarios", "catchup-v1:humans=9"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:humans=2+2"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:cav_fraction=1.5"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:cav_fraction=-0.1"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:cavs=9"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:cav_fraction=0.5,humans=2"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:placement=middle"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:human_model=krauss"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:cavs=0"],
        ["--controllers", "bdc", "--scenarios", "catchup-v1:humans=2"],
        ["--controllers", "cmpc", "--scenarios", "ring-v1"],
        ["--controllers", "cacc", "--scenarios", "ring-v1", "--vehicles", "10"],
        ["--controllers", "cacc", "--scenarios", "ring-v1:length_m=50"],
        ["--vehicles", "1"],
        ["--vehicles", "0"],
        ["--vehicles", "-4"],
        ["--vehicles", "x"],
        ["--vehicles", "99"],
        ["--vehicles", "1e3"],
        ["--vehicles", ""],
        ["--episodes", "0"],
        ["--episodes", "-1"],
        ["--episodes", "x"],
        ["--episodes", "1e9"],
        ["--episodes", "99999999999999999999"],
        ["--seeds", "-1"],
        ["--seeds", "x"],
        ["--seeds", ""],
        ["--seeds", "1.5"],
        ["--seeds", "99999999999999999999999"],
        ["--comm-delay", "-0.1"],
        ["--comm-delay", "nan"],
        ["--comm-delay", "inf"],
        ["--comm-delay", "x"],
        ["--comm-delay", "1e400"],
        ["--packet-loss", "-0.1"],
        ["--packet-loss", "1.5"],
        ["--packet-loss", "nan"],
        ["--lag", "-1"],
        ["--lag", "inf"],
        ["--lag", "1000"],
        ["--workers", "0"],
        ["--workers", "-1"],
        ["--executor", "gpu"],
        ["--out", "{FILE}"],
        ["--out", "/proc/cacc"],
        ["--out", "/sys/x/y"],
        ["--episodes", "2", "--seeds", "1"],
        ["--bogus"],
    ],
    "leaderboard": [[], ["/nonexistent"], ["{FILE}"], ["{EMPTY}"], ["--pool-seeds"]],
    "plot": [[], ["/nonexistent"], ["{FILE}"], ["{EMPTY}"]],
    "stability": [
        ["--controllers", "nope"],
        ["--time-gap", "-1"],
        ["--time-gap", "nan"],
        ["--delay", "-1"],
        ["--lag", "-1"],
        ["--n-vehicles", "1"],
        ["--amplitude", "-1"],
        ["--omega-min", "0"],
        ["--omega-min", "10", "--omega-max", "1"],
        ["--n-omega", "0"],
        ["--controllers", "bdc"],
        ["--out", "{FILE}"],
        ["--controllers", "cacc:kp=x"],
        ["--omega-max", "inf"],
    ],
    "train": [
        [],
        ["--algo", "ia2c", "--scenario", "catchup-v1", "--device", "tpu"],
        ["--algo", "ia2c", "--scenario", "catchup-v1", "--device", "cuda:x"],
        ["--algo", "ia2c", "--scenario", "catchup-v1", "--device", "mps"],
        ["--algo", "nope", "--scenario", "catchup-v1"],
        ["--algo", "bdc", "--scenario", "nope"],
        ["--algo", "bdc", "--scenario", "sine-v1:amplitude_mps=2"],
        ["--algo", "bdc", "--scenario", "sine-v1[amplitude_mps=2]"],
        ["--algo", "bdc", "--scenario", ","],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--steps", "0"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--steps", "-5"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--seed", "-1"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--seeds", "a"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--seeds", "0,1", "--population", "0"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--vehicles", "1"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "gamma=2"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "gamma"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "nope=1"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "gamma=nan"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "hidden=0"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "advantage_norm=maybe"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--episodes-parallel", "0"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--workers", "0"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--out", "{FILE}"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "consensus_eps=-1"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "qsgd_levels=-1"],
        ["--algo", "bdc", "--scenario", "catchup-v1", "--set", "lr_scale=0"],
    ],
    "tune": [
        ["--algos", "nope"],
        ["--scenarios", "nope"],
        ["--trials", "0"],
        ["--steps", "0"],
        ["--vehicles", "1"],
        ["--workers", "0"],
        ["--seed", "-1"],
        ["--out", "{FILE}"],
    ],
    "reproduce": [
        ["--budget", "huge"],
        ["--device", "gpu"],
        ["--algos", "nope"],
        ["--scenarios", "nope"],
        ["--skip", "nope"],
        ["--workers", "0"],
        ["--out", "{FILE}"],
        ["--algos", ""],
    ],
    "pareto": [
        ["--scenarios", "nope"],
        ["--episodes", "0"],
        ["--families", "nope"],
        ["--vehicles", "1"],
        ["--families", ""],
        ["--out", "{FILE}"],
        ["--workers", "0"],
    ],
    "sensitivity": [
        ["--device", "tpu"],
        ["--knobs", "x"],
        ["--seeds", "-1"],
        ["--steps", "0"],
        ["--episodes", "0"],
        ["--scenarios", "nope"],
        ["--out", "{FILE}"],
        ["--validation-episodes", "0"],
    ],
    "fit-power": [["--write", "--figure"], ["--figure", "/proc/x.png"]],
    "perf": [
        ["--only", "nope"],
        ["--only", "train", "--device", "tpu"],
        ["--controllers", "nope"],
        ["--algos", "nope"],
        ["--controllers", "ovm:alpha=x"],
        ["--controllers", "cacc:nope=1"],
        ["--controllers", ","],
        ["--population", "-1"],
    ],
    "help": [["nope"]],
    "list": [["--bogus"]],
}

#: Commands whose bad input is checked with an output folder of their own.
WITH_OUT = ("run", "pareto", "sensitivity", "reproduce", "tune")
MATRIX = [(cmd, args) for cmd, cases in CASES.items() for args in cases]


def _exit_code(argv: list[str]) -> int:
    """The command's exit status in this process (argparse's own errors exit 2 themselves)."""
    try:
        return cli(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def test_the_matrix_is_large() -> None:
    assert len(MATRIX) >= 100 and len(CASES) >= 12


@pytest.mark.parametrize("cmd, args", MATRIX, ids=[" ".join([c, *a])[:60] for c, a in MATRIX])
def test_bad_input_exits_2_with_a_message(
    cmd: str,
    args: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("x")
    (tmp_path / "empty").mkdir()
    argv = [
        cmd,
        *(
            a.replace("{FILE}", str(tmp_path / "file")).replace("{EMPTY}", str(tmp_path / "empty"))
            for a in args
        ),
    ]
    out = tmp_path / "out"
    if cmd in WITH_OUT and "--out" not in args:
        argv += ["--out", str(out)]
    assert _exit_code(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip(), err
    # nothing stored, nothing trained
    assert not list(tmp_path.rglob("store.sqlite")) and not list(tmp_path.rglob("*.pt"))


def _digest(folder: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.iterdir())
        if p.is_file() and p.suffix in (".csv", ".sqlite")
    }


@pytest.mark.parametrize(
    "args",
    [
        ["--controllers", "ovm:alpha=nan"],
        ["--vehicles", "1"],
        ["--scenarios", "sine-v1:nope=1"],
        ["--lag", "1000"],
        ["--controllers", "bdc:seed=7"],
        ["--seeds", "-1"],
    ],
)
def test_bad_input_on_a_finished_folder_loses_nothing(args: list[str], tmp_path: Path) -> None:
    out = tmp_path / "done"
    base = [
        "run",
        "--controllers",
        "ovm,acc",
        "--scenarios",
        "catchup-v1",
        "--vehicles",
        "2",
        "--episodes",
        "1",
        "--out",
        str(out),
        "--quiet",
    ]
    assert cli(base) == 0
    before = _digest(out)
    extra = dict(zip(args[::2], args[1::2], strict=True))
    argv = list(base)
    for flag, value in extra.items():
        if flag in argv:
            argv[argv.index(flag) + 1] = value
        else:
            argv += [flag, value]
    assert _exit_code([*argv, "--resume"]) == 2
    assert _digest(out) == before
