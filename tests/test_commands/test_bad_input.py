"""Bad input, every subcommand: exit 2 and one clear message, no traceback, nothing stored."""

from __future__ import annotations

import hashlib
import json
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
        ["--controllers", "ippo:checkpoint="],  # not the shipped policy, silently
        ["--controllers", "ippo:checkpoint_dir="],
        ["--controllers", "safe:bdc:checkpoint= "],
        ["--controllers", "followerstopper:set_speed_mps="],  # not its default, silently
        ["--controllers", "cacc:kp=2,kp=3"],  # the last would win without a word
        ["--scenarios", "catchup-v1:cavs=2,cavs=3"],
        ["--scenarios", "sine-v1[amplitude_mps=2,amplitude_mps=3]"],
        ["--controllers", "idm:noise_mps2="],
        ["--controllers", "bdc:variant=zzz"],
        ["--controllers", "bdc:untrained=maybe"],
        ["--controllers", "duty:k=0"],
        ["--controllers", "duty:k=-2"],
        ["--controllers", "duty:k_max=0"],
        ["--controllers", "safe:cacc:safe_min_gap_m=1e308"],
        ["--controllers", "safe:cacc:safe_pred_brake_mps2=1e308"],
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
        # issue 53, mixed traffic: options that ran as something else, or as nothing
        ["--controllers", "cacc", "--scenarios", "catchup-v1:humans="],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:cavs=-1"],
        ["--controllers", "cacc", "--scenarios", "ring-v1:placement_seed=3"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:humans=2,placement=front"],
        ["--controllers", "cacc", "--scenarios", "catchup-v1:humans=2,reaction_delay_s=0.05"],
        ["--controllers", "idm:desired_speed_mps=1e-300", "--scenarios", "catchup-v1:cavs=1"],
        ["--controllers", "idm:accel_max_mps2=1e308", "--scenarios", "catchup-v1:cavs=1"],
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


# ------------------------------------------------------------------ damaged input files
SHIPPED = Path(__file__).resolve().parents[2] / "controllers" / "checkpoints"
STEM = "bdc__catchup-v1__n8__s0"
#: ``reproduce --resume`` of one policy, no extra study: refused (or not) before any work.
REPRODUCE = ["reproduce", "--budget", "quick", "--algos", "bdc", "--scenarios", "catchup-v1",
             "--skip", "ablations,sizes,openacc", "--resume"]
TRUNCATED, NOT_UTF8, GARBAGE = "truncated", "not UTF-8", "garbage"


def _damage(path: Path, how: str) -> None:
    """Damage ``path`` as a careless copy, a wrong encoding or a stray file would."""
    whole = path.read_bytes() if path.exists() else b'{"a": 1, "b": [1, 2, 3]}'
    path.write_bytes({TRUNCATED: whole[: len(whole) // 2], NOT_UTF8: b"\xff\xfe" + whole,
                      GARBAGE: b"garbage here\nand more\n"}[how])


def _reproduction(out: Path) -> None:
    """A started reproduction of :data:`REPRODUCE` holding the shipped seed-0 policy, copied."""
    (out / "checkpoints").mkdir(parents=True)
    for suffix in (".pt", ".curve.csv"):
        (out / "checkpoints" / f"{STEM}{suffix}").write_bytes((SHIPPED / f"{STEM}{suffix}")
                                                              .read_bytes())
    (out / "checkpoints" / f"{STEM}.source.json").write_text('{"source": "shipped"}')
    (out / "reproduce.json").write_text(json.dumps({"settings": {
        "budget": "quick", "algos": ["bdc"], "scenarios": ["catchup-v1"], "studies": [],
        "arithmetic": "portable", "retrain": False}, "status": "started"}))


def _flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 1
    path.write_bytes(bytes(data))


#: case -> (the damaged file, relative to the folder, and the command, ``{OUT}`` the folder)
DAMAGED: dict[str, tuple[str, list[str]]] = {
    "reproduce.json": ("reproduce.json", [*REPRODUCE, "--out", "{OUT}"]),
    "source record": (f"checkpoints/{STEM}.source.json", [*REPRODUCE, "--out", "{OUT}"]),
    "curve of a reproduction": (f"checkpoints/{STEM}.curve.csv", [*REPRODUCE, "--out", "{OUT}"]),
    "sensitivity.json": ("sensitivity.json", ["sensitivity", "--scenarios", "catchup-v1",
                                              "--knobs", "gamma", "--out", "{OUT}", "--resume"]),
    "curve of a training folder": (f"{STEM}.curve.csv", ["plot", "{OUT}"]),
    "runs.csv to leaderboard": ("runs.csv", ["leaderboard", "{OUT}", "--quiet"]),
    "runs.csv to run --resume": ("runs.csv", ["run", "--controllers", "ovm", "--scenarios",
                                              "catchup-v1", "--vehicles", "2", "--episodes",
                                              "1", "--out", "{OUT}", "--quiet", "--resume"]),
}


#: (case, damage) refused; a CSV cut short is a shorter table and a runs.csv of other text is
#: rebuilt from the store, so neither is damage a reader can tell.
REFUSED = [(case, how) for case, (name, _) in sorted(DAMAGED.items())
           for how in (TRUNCATED, NOT_UTF8, GARBAGE)
           if not (name.endswith(".csv") and how == TRUNCATED)
           and not (name == "runs.csv" and how == GARBAGE)]


@pytest.mark.parametrize("case, how", REFUSED, ids=[f"{c}-{h}" for c, h in REFUSED])
def test_a_damaged_input_file_is_refused_in_one_line_before_any_work(
        case: str, how: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 53: a truncated, non-UTF-8 or garbage JSON or CSV file a command reads gave a
    ``JSONDecodeError`` or ``UnicodeDecodeError`` traceback (a garbage curve was plotted empty):
    now exit 2 and one line naming the file, before any run, training or figure."""
    name, argv = DAMAGED[case]
    out = tmp_path / "out"
    if name.startswith("checkpoints/") or name == "reproduce.json":
        _reproduction(out)
    elif name == "runs.csv":
        assert cli(["run", "--controllers", "ovm", "--scenarios", "catchup-v1", "--vehicles",
                    "2", "--episodes", "1", "--out", str(out), "--quiet"]) == 0
    else:
        out.mkdir()
    _damage(out / name, how)
    damaged = (out / name).read_bytes()
    before = set(out.rglob("*"))
    code = _exit_code([a.replace("{OUT}", str(out)) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"{Path(name).name} is damaged" in err, err
    assert (out / name).read_bytes() == damaged  # left as it was
    new = set(out.rglob("*")) - before
    assert {p.name for p in new} <= {"store.lock"}, new  # no store, run, checkpoint or figure


def test_reproduce_resume_refuses_a_byte_flipped_copied_checkpoint_before_any_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 53: ``reproduce --resume`` evaluated a byte-flipped copied checkpoint and stored 50
    failed rows; now every checkpoint of the study is verified first (as ``run`` does)."""
    out = tmp_path / "rep"
    _reproduction(out)
    _flip(out / "checkpoints" / f"{STEM}.pt")
    assert _exit_code([*REPRODUCE, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{STEM}.pt" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (out / "runs").exists()  # nothing evaluated, nothing stored


def test_a_reader_that_goes_away_ends_the_command_quietly() -> None:
    """Issue 53: ``cacc-bench --help | head -1`` gave a ``BrokenPipeError`` traceback 6 times in
    10; the reader here is gone before the command writes, every time."""
    import os
    import subprocess
    import sys

    for argv in (["--help"], ["list"], ["--version"]):
        read, write = os.pipe()
        os.close(read)
        proc = subprocess.run([sys.executable, "-m", "commands", *argv], stdout=write,
                              stderr=subprocess.PIPE, text=True, timeout=60,
                              cwd=Path(__file__).resolve().parents[2])
        os.close(write)
        assert proc.returncode == 141 and proc.stderr == "", (argv, proc.stderr)


def test_leaderboard_on_a_read_only_folder_says_so_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 53: ``leaderboard`` on a read-only folder gave a ``filelock`` traceback (the lock
    refused as a non-root user is on a read-only folder: root writes everywhere)."""
    import errno

    from filelock import FileLock

    out = tmp_path / "done"
    assert cli(["run", "--controllers", "ovm", "--scenarios", "catchup-v1", "--vehicles", "2",
                "--episodes", "1", "--out", str(out), "--quiet"]) == 0
    before = _digest(out)

    def denied(self: object, *a: object, **k: object) -> None:
        raise PermissionError(errno.EACCES, "Permission denied", str(out / "store.lock"))

    monkeypatch.setattr(FileLock, "acquire", denied)
    capsys.readouterr()
    assert _exit_code(["leaderboard", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cannot be locked for writing (Permission denied); make it writable" in err
    assert len(err.strip().splitlines()) == 1 and _digest(out) == before


def test_a_new_store_on_a_full_disk_is_called_full_not_unreadable(tmp_path: Path) -> None:
    """Issue 53: on a full disk a command's new store was "not a readable results store" with
    the advice to move it away; now the full disk is named (RLIMIT_FSIZE stands in for it)."""
    import resource
    import signal
    import subprocess
    import sys

    def limited() -> None:  # files may not grow past 6 kB: the store cannot hold its tables
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (6_000, 6_000))

    out = tmp_path / "new"
    proc = subprocess.run([sys.executable, "-m", "commands", "run", "--controllers", "ovm",
                           "--scenarios", "catchup-v1", "--vehicles", "2", "--episodes", "1",
                           "--quiet", "--out", str(out)], capture_output=True, text=True,
                          timeout=120, cwd=Path(__file__).resolve().parents[2],
                          preexec_fn=limited)
    assert proc.returncode == 2, proc.stderr
    assert "results store could not grow" in proc.stderr, proc.stderr
    assert "not a readable" not in proc.stderr and "move" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (out / "store.sqlite").exists()  # no half-made store left


@pytest.mark.parametrize("target", ["link", "link/sub"])
def test_out_through_a_link_to_nothing_says_so(
        target: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 53: ``--out`` on a dangling symlink said "File exists"."""
    (tmp_path / "link").symlink_to(tmp_path / "gone")
    out = tmp_path / target
    assert _exit_code(["run", "--controllers", "ovm", "--scenarios", "catchup-v1",
                       "--vehicles", "2", "--episodes", "1", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "is a link to" in err and "which does not exist" in err and "File exists" not in err
    assert not (tmp_path / "gone").exists()


#: Issue 53: config values a float32 computation cannot survive (``--set init_log_std=1e308``
#: gave a RuntimeError traceback), and options that exclude each other.
CONFIG_RANGES = [
    (["--algo", "ippo", "--set", "init_log_std=1e308"], "init_log_std must lie in [-20, 2]"),
    (["--algo", "mappo", "--set", "init_log_std=-1e308"], "init_log_std must lie in [-20, 2]"),
    (["--algo", "ippo", "--set", "obs_clip=1e308"], "obs_clip must lie in (0, 3.4e+38]"),
    (["--algo", "ippo", "--set", "reward_clip=1e308"], "reward_clip must lie in (0, 3.4e+38]"),
    (["--algo", "bdc", "--set", "lr_scale=1e308"], "actor_lr x lr_scale is a learning rate"),
    (["--algo", "bdc", "--set", "rmsprop_alpha=1e308"], "rmsprop_alpha must lie in [0, 1)"),
    (["--algo", "bdc", "--set", "rmsprop_eps=-1"], "rmsprop_eps must be a finite number > 0"),
    (["--algo", "ia2c", "--set", "min_active_fraction=2"], "min_active_fraction must lie in"),
    (["--algo", "ippo", "--resume", "--overwrite"], "--resume and --overwrite exclude each other"),
]


@pytest.mark.parametrize("args, message", CONFIG_RANGES, ids=[a[3] for a, _ in CONFIG_RANGES])
def test_a_config_value_out_of_range_is_refused_in_one_line(
        args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert _exit_code(["train", "--scenario", "catchup-v1", "--vehicles", "2", "--steps", "64",
                       *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err, err
    assert not out.exists()


def test_tune_refuses_resume_with_overwrite(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(["tune", "--algos", "bdc", "--resume", "--overwrite",
                       "--out", str(tmp_path / "out")]) == 2
    assert "exclude each other" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
