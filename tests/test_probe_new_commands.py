"""Issue 32's second probe: bad input to the commands and options added since the first probe
(train/tune ``--set`` of the shared learners, ``run --controllers`` of the shared policies,
``perf --algos/--controllers``). Each case once gave a traceback or ran the default work; now:
exit 2 and one message, no traceback, nothing stored or trained."""

from __future__ import annotations

from pathlib import Path

import pytest

from commands.cli import main as cli

#: argument lists that must be refused before any work; ``{OUT}`` is a fresh output folder.
CASES: list[list[str]] = [
    # a V2V delay beyond an episode: a MemoryError allocating its buffer (envs.limits.check_delay)
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "200", "--vehicles", "2",
     "--out", "{OUT}", "--set", "comm_delay_max_s=1e9"],
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "200", "--vehicles", "2",
     "--out", "{OUT}", "--set", "comm_delay_s=1e9"],
    ["train", "--algo", "mappo", "--scenario", "catchup-v1", "--steps", "200", "--vehicles", "2",
     "--out", "{OUT}", "--set", "comm_delay_max_s=61"],
    ["tune", "--algos", "ippo", "--scenarios", "catchup-v1", "--vehicles", "2", "--trials", "1",
     "--steps", "200", "--out", "{OUT}", "--set", "comm_delay_max_s=1e9"],
    # an option a shared policy does not take: a TypeError from its constructor
    ["run", "--controllers", "ippo:untrained=maybe", "--episodes", "1", "--vehicles", "2",
     "--scenarios", "catchup-v1", "--out", "{OUT}"],
    ["run", "--controllers", "mappo:bogus=1", "--episodes", "1", "--out", "{OUT}"],
    ["run", "--controllers", "safe:ippo:untrained=true", "--episodes", "1", "--out", "{OUT}"],
    ["run", "--controllers", "distill:nope=1", "--episodes", "1", "--out", "{OUT}"],
    ["run", "--controllers", "ippo-bdc:nope=1", "--episodes", "1", "--out", "{OUT}"],
    ["perf", "--quick", "--controllers", "ippo:bogus=1"],
    # a field tune searches itself: the trial's value silently replaced the one given
    ["tune", "--algos", "ippo", "--scenarios", "catchup-v1", "--vehicles", "2", "--trials", "1",
     "--steps", "200", "--out", "{OUT}", "--set", "lr=1e308"],
    ["tune", "--algos", "ippo,mappo", "--out", "{OUT}", "--set", "gamma=0.9"],
    # a learning rate whose first update made the weights NaN (the NaN policy, collisions 0,
    # was kept as the best snapshot and written) or overflowed Adam's step (a traceback):
    # marl.ppo_nets.check_learning_rate, the one rule
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "200", "--vehicles", "2",
     "--out", "{OUT}", "--set", "lr=1e308"],
    ["train", "--algo", "distill", "--scenario", "catchup-v1", "--vehicles", "2", "--out",
     "{OUT}", "--set", "lr=1e308", "--set", "rounds=1", "--set", "episodes_per_round=1"],
    # --algos named an unknown learner and was ignored when the train part did not run
    ["perf", "--quick", "--only", "env", "--algos", "bogus"],
    # an empty selection ran every default instead of being refused like ","
    ["perf", "--quick", "--only", "train", "--algos", ""],
    ["perf", "--quick", "--only", "controllers", "--controllers", ""],
]


def _exit_code(argv: list[str]) -> int:
    try:
        return cli(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


@pytest.mark.parametrize("args", CASES, ids=[" ".join(a)[:70] for a in CASES])
def test_refused_with_one_message(
    args: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    argv = [a.replace("{OUT}", str(tmp_path / "out")) for a in args]
    assert _exit_code(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip(), err
    errors = [line for line in err.splitlines() if line.startswith("cacc-bench")]
    assert len(errors) == 1 and err.strip().splitlines()[-1] == errors[0], err  # progress before
    assert not list(tmp_path.rglob("store.sqlite")) and not list(tmp_path.rglob("*.pt"))


@pytest.mark.parametrize(("option", "message"), [
    ("ippo:untrained=maybe", "ippo has no option 'untrained'; its options are: checkpoint, "),
    ("safe:mappo:bogus=1", "safe:mappo has no option 'bogus'; its options are: "),
])
def test_an_unknown_shared_policy_option_names_the_valid_ones(
    option: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    assert _exit_code(["run", "--controllers", option, "--episodes", "1",
                       "--out", str(tmp_path / "out")]) == 2
    assert message in capsys.readouterr().err


def test_tune_refuses_to_fix_exactly_the_fields_it_searches() -> None:
    from commands.tune import SHARED_SEARCHED, SHARED_TUNED, default_params, search_space

    class FirstChoice:
        def suggest_float(self, name: str, low: float, high: float, log: bool = False) -> float:
            return low

        def suggest_categorical(self, name: str, choices: list[object]) -> object:
            return choices[0]

    spaces = {algo: set(search_space(FirstChoice(), algo)) for algo in SHARED_TUNED}
    assert set().union(*spaces.values()) == set(SHARED_SEARCHED)
    for algo, space in spaces.items():  # every study's first trial is the default config
        assert set(default_params(algo)) == space, algo
    assert spaces["ippo-bdc"] - spaces["ippo"] == {"consensus_eps"}


@pytest.mark.parametrize("algo_args", [
    ["--algo", "ippo", "--steps", "200"],
    ["--algo", "distill", "--set", "rounds=1", "--set", "episodes_per_round=1",
     "--set", "grad_steps=2"],
])
def test_weights_that_turn_non_finite_stop_the_training_and_write_nothing(
    algo_args: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Whatever makes the weights NaN (here every Adam step), the shared learner and the
    distiller stop with exit 2 and one line, before a NaN policy (which scores no collision)
    could be kept and written."""
    import torch

    def poisoned_step(self: torch.optim.Adam, closure: object = None) -> None:
        with torch.no_grad():
            for group in self.param_groups:
                for p in group["params"]:
                    p.fill_(float("nan"))

    monkeypatch.setattr(torch.optim.Adam, "step", poisoned_step)
    argv = ["train", *algo_args, "--scenario", "catchup-v1", "--vehicles", "2",
            "--out", str(tmp_path / "out")]
    assert _exit_code(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "the weights became non-finite" in err, err
    assert not list(tmp_path.rglob("*.pt"))
