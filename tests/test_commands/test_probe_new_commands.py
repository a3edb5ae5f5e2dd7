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
    # a V2V delay beyond an episode: a MemoryError allocating its buffer (infra.limits.check_delay)
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
    # a network or rollout within the old 1..1e7 ranges that cannot be allocated (a
    # RuntimeError traceback), or one rollout far beyond --steps (a run of minutes for 64 steps)
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "64", "--vehicles", "2",
     "--out", "{OUT}", "--set", "hidden=10000000"],
    ["train", "--algo", "mappo", "--scenario", "catchup-v1", "--steps", "64", "--vehicles", "2",
     "--out", "{OUT}", "--set", "hidden=2048"],
    ["train", "--algo", "distill", "--scenario", "catchup-v1", "--vehicles", "2",
     "--out", "{OUT}", "--set", "hidden=1000000"],
    ["tune", "--algos", "ippo", "--scenarios", "catchup-v1", "--vehicles", "2", "--trials", "1",
     "--steps", "100", "--out", "{OUT}", "--set", "hidden=10000000"],
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "64", "--vehicles", "2",
     "--out", "{OUT}", "--set", "n_envs=10000000", "--set", "rollout_steps=8"],
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "64", "--vehicles", "2",
     "--out", "{OUT}", "--set", "n_envs=2", "--set", "rollout_steps=10000000"],
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "64", "--vehicles", "2",
     "--out", "{OUT}", "--set", "n_envs=2", "--set", "rollout_steps=1000"],
    ["tune", "--algos", "ippo", "--scenarios", "catchup-v1", "--vehicles", "2", "--trials", "1",
     "--steps", "1000", "--out", "{OUT}"],
    # a V2V delay between simulation steps ran as the nearest step and was stored as typed
    ["run", "--controllers", "cacc", "--scenarios", "catchup-v1", "--vehicles", "2",
     "--episodes", "1", "--comm-delay", "0,0.05", "--out", "{OUT}"],
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "64", "--vehicles", "2",
     "--out", "{OUT}", "--set", "comm_delay_s=0.15"],
    ["stability", "--controllers", "cacc", "--empirical", "--delay", "0.25", "--out", "{OUT}"],
    # a policy option that names nothing trainable: the advice was to train it
    ["run", "--controllers", "ippo:scenario=nope-v9", "--scenarios", "catchup-v1",
     "--episodes", "1", "--out", "{OUT}"],
    ["run", "--controllers", "ippo:seed=99999999999999999999", "--scenarios", "catchup-v1",
     "--episodes", "1", "--out", "{OUT}"],
    ["run", "--controllers", "bdc:seed=419", "--scenarios", "catchup-v1", "--episodes", "1",
     "--out", "{OUT}"],
    ["run", "--controllers", "ippo:variant=w5_0", "--scenarios", "catchup-v1",
     "--episodes", "1", "--out", "{OUT}"],
    ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "6.5", "--out", "{OUT}"],
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
    ["--algo", "ippo", "--steps", "200", "--set", "n_envs=2", "--set", "rollout_steps=8"],
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


def test_a_step_budget_may_be_written_as_a_float() -> None:
    """``--help`` says "(default 6e5)": ``--steps 6e5`` was refused as an invalid int."""
    from infra.limits import step_count

    assert [step_count(t) for t in ("600000", "6e5", "2e3", "1_000")] == [600000, 600000, 2000,
                                                                           1000]


def test_resume_never_trains_over_a_finished_run_of_another_setting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    """``train --resume`` of a shared learner retrained a finished run of another config over
    it, silently (the paper's learners refused). Now refused before any training, files
    byte-identical; the same setting is skipped; a copy renamed to another N is refused by
    ``run``."""
    import hashlib

    base = ["train", "--algo", "ippo", "--scenario", "catchup-v1", "--vehicles", "2",
            "--steps", "64", "--set", "rollout_steps=8", "--set", "eval_every_steps=32",
            "--out", str(tmp_path)]
    assert _exit_code([*base, "--set", "n_envs=4"]) == 0

    def digests() -> dict[str, str]:
        return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in tmp_path.iterdir()
                if p.is_file()}

    before = digests()
    capsys.readouterr()
    assert _exit_code([*base, "--set", "n_envs=8", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "config fields n_envs differ" in err and "Traceback" not in err, err
    assert _exit_code([*base, "--set", "n_envs=4", "--steps", "128", "--resume"]) == 2
    assert "budget 64 steps, not 128" in capsys.readouterr().err
    assert digests() == before
    assert _exit_code([*base, "--set", "n_envs=4", "--resume"]) == 0
    assert "finished before, skipped" in capsys.readouterr().err and digests() == before
    (tmp_path / "ippo__catchup-v1__n2__s0.pt").rename(tmp_path / "ippo__catchup-v1__n3__s0.pt")
    assert _exit_code(["run", "--controllers", f"ippo:checkpoint_dir={tmp_path},vehicles=3",
                       "--scenarios", "catchup-v1", "--vehicles", "3", "--episodes", "1",
                       "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "was trained for N = 2 followers, not 3" in err, err
    assert f"--vehicles 3 --seed 0 --out {tmp_path}" in err  # the file's own name and folder


def test_paths_in_messages_are_as_the_user_wrote_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    assert _exit_code(["train", "--algo", "ippo", "--scenario", "catchup-v1", "--steps", "64",
                       "--out", "afile/sub"]) == 2
    assert "--out afile/sub: afile is a file" in capsys.readouterr().err
    assert _exit_code(["train", "--algo", "ippo", "--scenario", "sine-v1", "--tuned",
                       "--steps", "64", "--out", "o"]) == 2
    err = capsys.readouterr().err
    assert "in the package's marl/tuned_configs.json" in err and str(Path.cwd()) not in err
