"""Command-line conventions: a command is required, ``help CMD``, ``python -m commands``."""

from __future__ import annotations

import subprocess
import sys

import pytest

from commands.cli import SUBCOMMANDS, main


def test_bare_command_prints_usage_and_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    err = capsys.readouterr().err
    assert "usage: cacc-bench <command>" in err and "reproduce" in err


def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in SUBCOMMANDS:
        assert f"  {name} " in out


@pytest.mark.parametrize("cmd", ["run", "train", "reproduce", "pareto"])
def test_help_cmd_is_the_commands_help(cmd: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["help", cmd])
    assert exc.value.code == 0
    assert f"usage: cacc-bench {cmd}" in capsys.readouterr().out


def test_python_dash_m_benchmark() -> None:
    res = subprocess.run([sys.executable, "-m", "commands", "--version"], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.startswith("cacc-bench ")
    res = subprocess.run([sys.executable, "-m", "commands", "nope"], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2 and "unknown command 'nope'" in res.stderr


@pytest.mark.parametrize("cmd", sorted(SUBCOMMANDS))
def test_help_texts_have_no_markup(cmd: str, capsys: pytest.CaptureFixture[str]) -> None:
    try:
        code = main([cmd, "--help"])
    except SystemExit as exc:
        code = exc.code
    assert code == 0
    out = capsys.readouterr().out
    assert "``" not in out and ":func:" not in out and ":class:" not in out


def test_missing_policy_checkpoint_fails_before_any_run(tmp_path, capsys) -> None:
    """A policy without a checkpoint for the asked N stops the sweep before it starts: exit 2,
    the train command to make it, and no results folder."""
    out = tmp_path / "r"
    # N = 2, 4, 6 and 8 ship for catchup-v1 (the reproduction's size study); 3 does not
    assert main(["run", "--controllers", "ovm,bdc", "--scenarios", "catchup-v1", "--vehicles", "3",
                 "--episodes", "1", "--out", str(out)]) == 2
    assert "cacc-bench train --algo bdc --scenario catchup-v1 --vehicles 3" in capsys.readouterr().err
    assert not out.exists()


def test_a_signal_that_breaks_an_import_ends_as_the_signal(monkeypatch, capsys) -> None:
    """A SIGINT while a C extension starts (numpy's) surfaces as an ImportError from that import:
    with a signal received, the command ends as interrupted (130, one line), not a traceback;
    without one, the ImportError stays an error."""
    import signal

    import pytest

    from commands import cli
    from infra import interrupt

    def broken(name: str) -> None:
        interrupt._received = signal.SIGINT
        raise ImportError("PyCapsule_Import could not import module \"datetime\"")

    monkeypatch.setattr(interrupt, "_holding", interrupt._holding)  # restored after the test
    monkeypatch.setattr(interrupt, "_received", None)
    monkeypatch.setattr(cli.importlib, "import_module", broken)
    assert cli.main(["leaderboard", "x"]) == 130
    assert capsys.readouterr().err.strip() == cli.interrupted_line(signal.SIGINT, "leaderboard")

    def missing(name: str) -> None:
        raise ImportError("no module")

    monkeypatch.setattr(interrupt, "_received", None)
    monkeypatch.setattr(cli.importlib, "import_module", missing)
    with pytest.raises(ImportError):
        cli.main(["leaderboard", "x"])
