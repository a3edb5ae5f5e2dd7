"""``cacc-bench reproduce`` and the analysis behind its report."""

from __future__ import annotations

import json
import math
import os
import re
import shlex
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from run_marks import FULL

from analysis.tables import format_table
from commands.cli import main as cli
from studies import reproduction as rp
from studies.paper import TABLE_I_REWARD, TABLE_II, TABLE_III

VERDICTS = {"holds", "does not hold", "inconclusive", "not testable here"}


def _curve(steps: list[float], values: list[float], train: list[float] | None = None) -> pd.DataFrame:
    train = train if train is not None else [0.0] * len(steps)
    return pd.DataFrame({"episode": range(1, len(steps) + 1), "steps": steps,
                         "train_reward": train, "eval_reward_sampled": values,
                         "eval_collisions_sampled": 0.0, "eval_reward_greedy": values,
                         "eval_collisions_greedy": 0.0})


def test_convergence_step_is_first_step_within_the_band_of_the_plateau_for_good() -> None:
    """The rule of docs/claim-rules.md (its own tests: tests/test_studies/test_claim_rules.py). Formerly a
    curve that did not rise "converged at its first point"; now it has not converged (NaN)."""
    steps = np.array([1.0, 2, 3, 4, 5, 6, 7])
    # rises from -100 to a plateau of 0 (last three); band 10 % of the rise: |value| <= 10
    values = np.array([-100.0, -50, -5, -20, 0, 0, 0])
    assert rp.convergence_step(steps, values) == 5.0  # -20 at step 4 breaks the run from 3
    assert rp.convergence_step(steps, np.array([-100.0, -9, -5, 0, 0, 0, 0])) == 2.0
    assert math.isnan(rp.convergence_step(steps, -np.arange(7.0)))  # ends below its start
    assert math.isnan(rp.convergence_step(np.array([]), np.array([])))


def test_table_one_means_and_stds_over_seeds() -> None:
    curves = {("bdc", "catchup-v1", s): _curve([1, 2], [-10.0 * (s + 1), -5.0 * (s + 1)],
                                               train=[-100.0, -10.0 * s])
              for s in range(3)}
    t1 = rp.table_one(curves, ["bdc"])
    row = t1.iloc[0]
    assert row["n_seeds"] == 3
    # last 10 % of 2 episodes is the last one: 0, -10, -20
    assert row["train_reward_mean"] == pytest.approx(-10.0)
    assert row["train_reward_std"] == pytest.approx(10.0)
    # final validation: -5, -10, -15
    assert row["validation_reward_mean"] == pytest.approx(-10.0)
    assert row["paper_reward"] == TABLE_I_REWARD["bdc"]


def _runs(power: dict[str, list[float]], scenario: str = "catchup-v1") -> pd.DataFrame:
    rows = []
    for name, values in power.items():
        for k, p in enumerate(values):
            rows.append({"controller": name, "scenario": scenario, "seed": 2000 + 10 * k,
                         "power_mean_kw": p, "gap_mean_m": 20.0, "gap_std_m": 1.0,
                         "speed_mean_mps": 15.0, "speed_std_mps": 0.1, "accel_mean_mps2": 0.0,
                         "accel_std_mps2": 0.1, "collision": False, "reward": -p})
    return pd.DataFrame(rows)


def test_energy_claim_verdicts_follow_the_paired_intervals() -> None:
    names = {n: n for n in ("bdc", "ia2c", "commnet")}
    rng = np.random.default_rng(0)
    base = 18.0 + rng.normal(0, 0.2, 20)
    holds = rp.energy_claim(_runs({"bdc": base, "ia2c": base + 1.0, "commnet": base + 0.5}),
                            names, "catchup-v1")
    assert holds.verdict == "holds"
    assert "vs ia2c" in holds.measured and "largest" in holds.measured
    fails = rp.energy_claim(_runs({"bdc": base + 1.0, "ia2c": base, "commnet": base + 2.0}),
                            names, "catchup-v1")
    assert fails.verdict == "does not hold"
    missing = rp.energy_claim(_runs({"ia2c": base}), names, "catchup-v1")
    assert missing.verdict == "not testable here"


def test_energy_claim_counts_the_variation_between_training_seeds() -> None:
    """Three BDC training seeds, one costlier than IA2C: pooled per episode BDC saves about 5 %
    on every episode, but the training seeds' spread makes the verdict inconclusive."""
    rng = np.random.default_rng(0)
    base = 18.0 + rng.normal(0, 0.2, 20)
    power = {f"bdc-s{k}": base * f for k, f in enumerate((0.85, 0.95, 1.05))}
    power.update({f"ia2c-s{k}": base * f for k, f in enumerate((1.0, 1.005, 0.995))})
    labels = {name: name.split("-")[0] for name in power}
    verdict = rp.energy_claim(_runs(power), labels, "catchup-v1")
    assert "vs ia2c +5.0" in verdict.measured
    assert verdict.verdict == "inconclusive"


def test_reward_claim_verdicts_follow_the_two_stage_intervals() -> None:
    """BDC above both rivals on every training seed: holds; one BDC seed far below: the margin's
    interval covers 0, inconclusive; a rival above on every seed: does not hold."""
    rng = np.random.default_rng(1)
    base = 18.0 + rng.normal(0, 0.5, 20)

    def claim(power: dict[str, np.ndarray]) -> rp.Verdict:
        runs = _runs(power)  # reward = -power
        labels = {name: name.split("-")[0] for name in power}
        return rp.reward_claim(runs, labels, rp.table_two(runs, labels), "catchup-v1")

    rivals = {f"{a}-s{k}": base + 1.0 for a in ("ia2c", "dial") for k in range(3)}
    steady = claim({**{f"bdc-s{k}": base for k in range(3)}, **rivals})
    assert steady.verdict == "holds" and "BDC minus ia2c +1.0 [+1.0, +1.0]" in steady.measured
    spread = claim({**{f"bdc-s{k}": base + d for k, d in enumerate((-2.0, -2.0, 4.0))}, **rivals})
    assert spread.verdict == "inconclusive"
    worse = claim({**{f"bdc-s{k}": base + 2.0 for k in range(3)}, **rivals})
    assert worse.verdict == "does not hold" and worse.reason == "ia2c, dial scores higher"


def test_table_two_puts_the_paper_values_beside_ours() -> None:
    runs = _runs({"lab-bdc-0": [17.0, 19.0], "lab-bdc-1": [18.0, 18.0], "ovm": [30.0, 30.0]})
    t2 = rp.table_two(runs, {"lab-bdc-0": "bdc", "lab-bdc-1": "bdc", "ovm": "ovm"})
    bdc = t2.set_index("name").loc["bdc"]
    assert bdc["n_episodes"] == 4 and bdc["power_kw_avg"] == pytest.approx(18.0)
    assert bdc["paper_power_kw_avg"] == TABLE_II["bdc"]["power_kw"][0]
    assert math.isnan(t2.set_index("name").loc["ovm", "paper_ivs_m_avg"])


def test_format_table_shows_nan_as_dash() -> None:
    df = pd.DataFrame({"a": ["x"], "b": [math.nan], "c": [1.234]})
    text = format_table(df, [("a", "A"), ("b", "B"), ("c", "C")])
    assert text.splitlines()[2] == "| x | - | 1.23 |"


def test_plot_of_a_training_folder_draws_learning_curves(tmp_path: Path) -> None:
    for seed in (0, 1):
        _curve([100, 200], [-50.0, -40.0 - seed]).to_csv(
            tmp_path / f"bdc__catchup-v1__n8__s{seed}.curve.csv", index=False)
    assert cli(["plot", str(tmp_path)]) == 0
    assert (tmp_path / "figures" / "curves__catchup-v1__n8.png").stat().st_size > 0


def test_policy_checkpoint_dir_names_the_train_command(tmp_path: Path) -> None:
    from controllers.policy import PolicyController
    from envs.scenarios import make_scenario
    from infra.errors import ConfigError

    ctrl = PolicyController("bdc", checkpoint_dir=str(tmp_path), seed=1)
    with pytest.raises(ConfigError, match=f"--out {tmp_path}"):
        ctrl.preflight(make_scenario("catchup-v1"), 8)


def _readme_reproduce_command() -> list[str]:
    text = (Path(__file__).resolve().parents[2] / "docs" / "reproduction.md").read_text()
    section = re.search(r"^## The command\n(.*?)(?=^## )", text, re.S | re.M)
    assert section, "docs/reproduction.md has no section 'The command'"
    block = re.search(r"```bash\n(.*?)```", section.group(1), re.S)
    assert block
    (line,) = [ln for ln in block.group(1).strip().splitlines() if ln.strip()]
    argv = shlex.split(line)
    assert argv[:2] == [".venv/bin/cacc-bench", "reproduce"]
    return argv[1:]


def _replace(argv: list[str], flag: str, value: str) -> list[str]:
    i = argv.index(flag)
    return [*argv[:i + 1], value, *argv[i + 2:]]


@pytest.fixture(scope="module")
def tiny_reproduction(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The README's reproduction command in small form: quick budget, one algorithm, one
    scenario (the README never lies)."""
    out = tmp_path_factory.mktemp("rep") / "rep"
    argv = _replace(_replace(_readme_reproduce_command(), "--budget", "quick"), "--out", str(out))
    assert cli([*argv, "--algos", "bdc", "--scenarios", "catchup-v1"]) == 0
    return out


#: Both tests of the tiny reproduction run on one pytest-xdist worker (``--dist loadgroup``), so
#: its module fixture is built once, not once per worker (about 95 s each); both are full checks
#: (CI runs them).
_ONE_WORKER = pytest.mark.xdist_group("tiny_reproduction")


@FULL
@_ONE_WORKER
def test_reproduce_writes_the_report_tables_and_claims(tiny_reproduction: Path) -> None:
    out = tiny_reproduction
    report = (out / "report.md").read_text()
    for section in ("## Table I", "## Table II", "## Learning curves", "## The paper's claims"):
        assert section in report
    t1 = pd.read_csv(out / "table1.csv")
    assert set(t1["algo"]) == {"bdc", "bdc-noqsgd"} and set(t1["n_seeds"]) == {2}
    t2 = pd.read_csv(out / "table2.csv")
    assert {"ovm", "duty", "cacc", "mpc", "mpc-qp", "cmpc", "bdc", "bdc-noqsgd"} <= set(t2["name"])
    bdc = t2.set_index("name").loc["bdc"]
    assert bdc["n_episodes"] == 4  # 2 training seeds x 2 episodes
    assert bdc["paper_ivs_m_avg"] == TABLE_II["bdc"]["ivs_m"][0]
    claims = pd.read_csv(out / "claims.csv")
    assert set(claims["verdict"]) <= VERDICTS and len(claims) >= 6
    for fig in ("curves_marl__catchup-v1.png", "radar__catchup-v1.png",
                "timeseries__bdc__catchup-v1.png"):
        assert (out / "figures" / fig).stat().st_size > 0
    # main 2 + ablation 2 + sizes 3 x 2 + OpenACC 3 x 2, every one trained portably (the default)
    sources = [json.loads(p.read_text()) for p in (out / "checkpoints").rglob("*.source.json")]
    assert len(sources) == 16 and {s["arithmetic"] for s in sources} == {"portable"}
    assert "Training arithmetic **portable**" in report
    assert "Policies: 16 trained here (trained with portable arithmetic)." in report
    sizes = pd.read_csv(out / "sizes.csv")
    assert set(sizes["n_vehicles"]) == {2, 4, 6, 8} and set(sizes["name"]) == {"bdc", "ovm"}
    t3 = pd.read_csv(out / "table3.csv")
    assert set(t3["group"]) == {"S", "M", "L"}
    assert set(t3["name"]) == {"openacc-real", "cacc", "mpc", "bdc"}
    real_s = t3[(t3["group"] == "S") & (t3["name"] == "openacc-real")].iloc[0]
    assert real_s["paper_ivs_m_std"] == TABLE_III["S"]["openacc"]["ivs_m"][1]
    assert "## Platoon size" in report and "## OpenACC (Table III)" in report
    assert (out / "figures" / "curves_sizes__bdc.png").stat().st_size > 0
    # never trained on a test window
    assert not list((out / "checkpoints").rglob("*__openacc-[sml]-v1__*"))


@FULL
@_ONE_WORKER
def test_reproduce_refuses_a_used_folder_and_resumes_without_redoing(
        tiny_reproduction: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tiny_reproduction
    argv = ["reproduce", "--budget", "quick", "--algos", "bdc", "--scenarios", "catchup-v1",
            "--out", str(out)]
    assert cli(argv) == 2
    assert "--resume" in capsys.readouterr().err
    stamps = {p: os.stat(p).st_mtime_ns for p in (out / "checkpoints").rglob("*.pt")}
    before = pd.read_csv(out / "table2.csv")
    assert cli([*argv, "--resume"]) == 0
    assert {p: os.stat(p).st_mtime_ns for p in (out / "checkpoints").rglob("*.pt")} == stamps
    err = capsys.readouterr().err
    assert "0 to train" in err and "0 to run" in err
    pd.testing.assert_frame_equal(pd.read_csv(out / "table2.csv"), before)
    assert cli(["reproduce", "--budget", "paper", "--algos", "bdc", "--scenarios", "catchup-v1",
                "--out", str(out), "--resume"]) == 2  # other settings: refused


@FULL
@_ONE_WORKER
def test_resume_refuses_to_report_a_replaced_policy_with_its_old_runs(
        tiny_reproduction: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A trained checkpoint replaced by other weights after its evaluation: the resumed command
    refuses (exit 2) before reporting, and leaves the report as it was."""
    import shutil

    out = tmp_path / "rep"
    shutil.copytree(tiny_reproduction, out)
    ckpt = out / "checkpoints"
    import torch

    from marl.checkpoint import write_payload

    other = torch.load(ckpt / "bdc__catchup-v1__n8__s1.pt", weights_only=True)
    write_payload(ckpt / "bdc__catchup-v1__n8__s0.pt", {**other, "seed": 0})  # retrained
    report = (out / "report.md").read_bytes()
    capsys.readouterr()
    assert cli(["reproduce", "--budget", "quick", "--algos", "bdc", "--scenarios", "catchup-v1",
                "--out", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "that have changed since they ran" in err and "Traceback" not in err
    assert f"{out.resolve() / 'runs'} holds 2 runs" in err
    assert "bdc[checkpoint_dir=checkpoints] on catchup-v1, N = 8" in err
    assert (out / "report.md").read_bytes() == report


@pytest.mark.slow
def test_quick_budget_reproduces_everything_in_minutes(tmp_path: Path) -> None:
    """The whole quick reproduction (seven algorithms, the ablation, two scenarios)."""
    assert cli(["reproduce", "--budget", "quick", "--out", str(tmp_path / "q"),
                "--executor", "process", "--workers", "2"]) == 0
    assert len(list((tmp_path / "q" / "checkpoints").rglob("*.source.json"))) == 2 * (
        2 * 8 + 2 * 3 + 3)
    claims = pd.read_csv(tmp_path / "q" / "claims.csv")
    assert set(claims["verdict"]) <= VERDICTS
    assert "not testable here" != claims.set_index("claim").iloc[2]["verdict"]  # convergence ran


def test_the_readme_quotes_the_committed_paper_report() -> None:
    """The README's paper-budget verdicts are the committed report's (docs/paper-reproduction,
    copied from the run that made it): rewards, collisions, power and verdicts as the CSVs hold
    them, formatted from the CSVs and looked up in the README."""
    docs = Path(__file__).resolve().parents[2] / "docs" / "paper-reproduction"
    readme = (docs.parent / "reproduction.md").read_text()  # moved there from the README
    readme = " ".join(readme.split())  # line breaks aside
    t2 = pd.read_csv(docs / "table2.csv").set_index(["name", "scenario"])
    quoted = [f"{t2.loc[(name, 'catchup-v1'), 'reward_mean']:.1f}"
              for name in ("bdc", "dial", "commnet", "fprint", "ia2c")]
    assert (f"BDC has the best reward of the five ({quoted[0]}; DIAL {quoted[1]}, CommNet "
            f"{quoted[2]}, FPrint {quoted[3]}, IA2C {quoted[4]})") in readme
    slow, slow_ia2c = t2.loc[("bdc", "slowdown-v1")], t2.loc[("ia2c", "slowdown-v1")]
    assert (f"BDC {slow['reward_mean']:,.0f} with {slow['collisions']:.0f} collisions in 150 "
            f"episodes trails IA2C ({slow_ia2c['reward_mean']:,.0f}, "
            f"{slow_ia2c['collisions']:.0f} collisions)") in readme
    assert f"BDC {t2.loc[('bdc', 'catchup-v1'), 'power_kw_avg']:.1f} kW for 8 followers" in readme
    noqsgd = [f"{t2.loc[(name, 'catchup-v1'), 'reward_mean']:.1f}" for name in ("bdc", "bdc-noqsgd")]
    assert f"BDC scores {noqsgd[0]} and {noqsgd[1]} on catchup-v1" in readme
    claims = pd.read_csv(docs / "claims.csv")
    energy = claims["measured"][0]
    assert energy.startswith("catchup-v1:")
    vs_ia2c = energy.split("vs ia2c ")[1].split(";")[0]  # "+9.13 % [-7.13, +27.58]"
    assert f"against IA2C {vs_ia2c}" in readme
    reward_claim = claims["measured"][1]
    vs_dial = reward_claim.rsplit("; dial ", 1)[1]  # "+59.4 [+37.9, +86.0]", the smallest margin
    assert f"(smallest: DIAL, {vs_dial})" in readme
    magnitude = claims.set_index("claim").filter(like="up to 5.8", axis=0)["measured"].iloc[0]
    vs_commnet = magnitude.split("vs commnet ")[1].split(" (paper")[0]  # "+6.89 % [+1.13, +15.06]"
    assert f"BDC's saving against CommNet, {vs_commnet} of total power" in readme
    slow_rates = claims[claims["measured"].str.startswith("slowdown-v1: collision rate")]
    for algo, name in (("ia2c", "IA2C"), ("commnet", "CommNet"), ("dial", "DIAL")):
        rate = slow_rates["measured"].iloc[0].split(f"{algo} ")[1].split(" = ")[1].split(" %")[0]
        assert f"{name} {rate} %" in readme
    for name, label in (("commnet", "CommNet"), ("fprint", "FPrint"), ("dial", "DIAL"),
                        ("wac", "WAC")):
        row = t2.loc[(name, "slowdown-v1")]
        assert f"{label} ({row['reward_mean']:,.0f}, {row['collisions']:.0f}" in readme \
            or f"against {row['reward_mean']:,.0f}, {label} with fewer collisions, " \
               f"{row['collisions']:.0f} against {slow['collisions']:.0f}" in readme
    without = t2.loc[("bdc-noqsgd", "slowdown-v1")]
    assert (f"without it BDC scores {without['reward_mean']:,.0f} with {without['collisions']:.0f} "
            f"collisions, with it {slow['reward_mean']:,.0f} with {slow['collisions']:.0f}") in readme
    by_claim = claims.set_index("claim")["measured"]
    sizes = by_claim.filter(like="Larger platoons", axis=0).iloc[0]
    assert f"BDC's N = 8 against N = 2 is {sizes.split('N=8 minus N=2 ')[1].split(';')[0]}" in readme
    openacc = by_claim.filter(like="OpenACC", axis=0).iloc[0]
    for window in ("S", "M", "L"):
        part = openacc.split(f"{window}: IVS std BDC ")[1]
        bdc_std, real_std = part.split(" m")[0], part.split("vs real ")[1].split(" m")[0]
        assert f"{bdc_std} against {real_std} m" in readme
    slow_claims = claims[claims["measured"].str.startswith("slowdown-v1:")].set_index("claim")
    slow_energy = slow_claims.filter(like="saves the most energy", axis=0)["measured"].iloc[0]
    savings = [float(slow_energy.split(f"vs {a} ")[1].split(" %")[0]) for a in
               ("ia2c", "fprint", "commnet")]
    assert f"BDC uses {min(savings):.0f} to {max(savings):.0f} % less power" in readme
    stable = slow_claims.filter(like="more stable velocity", axis=0)["measured"].iloc[0]
    speed = stable.split("speed std (m/s): ")[1].split(";")[0]  # "bdc 3.930, wac 4.221, dcea 4.209"
    stds = [float(v.split(" ")[1]) for v in speed.split(", ")]
    assert f"({stds[0]:.2f} against {stds[1]:.2f} and {stds[2]:.2f} m/s)" in readme
    qsgd = slow_claims.filter(like="QSGD", axis=0)["measured"].iloc[0]
    diff = qsgd.split("with minus without ")[1].split(", margin")[0]  # "-1069.2 [-2375.5, -18.3]"
    low, high = (float(v) for v in diff.split("[")[1].rstrip("]").split(", "))
    assert f"the interval ({float(diff.split(' ')[0]):,.0f} [{low:,.0f}, {high:,.0f}])" in readme
    converge = slow_claims.filter(like="converges fastest", axis=0)["measured"].iloc[0]
    words = {0: "none", 1: "one of three"}
    converged = {algo: 3 - int(converge.split(f"; {algo} ")[1].split(" of 3 seeds not")[0][-1])
                 for algo in ("bdc", "dcea")}  # "... 2 of 3 seeds not converged)"
    assert (f"(BDC {words[converged['bdc']]}, DCEA {words[converged['dcea']]})") in readme
    # the page's bullets sort the claims by verdict; these are the verdicts it states
    by_verdict = claims["verdict"].value_counts().to_dict()
    assert by_verdict == {"holds": 3, "inconclusive": 11, "does not hold": 4, "not testable here": 1}
    for verdict in ("Holds on catchup-v1:",
                    "Inconclusive on slowdown-v1, where every learned policy collides:",
                    "Inconclusive elsewhere:", "Does not hold:", "Not testable here:"):
        assert verdict in readme


def test_the_default_command_copies_what_the_committed_report_ran() -> None:
    """The committed report (docs/paper-reproduction) ran the shipped policies, all 75 copied by
    the default command: the 48 it would otherwise train, shipped in ``variants/`` and trained
    in the command's default arithmetic, and the 27 of the shipped folder's own; each source
    names a shipped file, so a clean clone runs the same weights."""
    from commands.reproduce import _parser

    root = Path(__file__).resolve().parents[2]
    docs = root / "docs" / "paper-reproduction"
    default = _parser().parse_args([]).arithmetic
    manifest = json.loads((docs / "reproduce.json").read_text())
    assert manifest["settings"]["arithmetic"] == default
    assert manifest["settings"].get("retrain") is False
    sources = [json.loads(p.read_text()) for p in (docs / "sources").rglob("*.source.json")]
    assert len(sources) == 75 and {s["source"] for s in sources} == {"shipped"}
    assert all((root / s["path"]).is_file() for s in sources)
    variants = [s for s in sources if "/variants/" in s["path"]]
    assert len(variants) == 48
    assert {s["arithmetic"] for s in variants} == {default}


@pytest.mark.parametrize("retrain", [False, True])
def test_the_paper_budget_copies_shipped_policies_unless_told_to_retrain(
        monkeypatch, tmp_path: Path, retrain: bool) -> None:
    """``--budget paper`` hands the training stage the shipped checkpoints to copy; with
    ``--retrain`` it trains every policy, and a folder started one way is not resumed the
    other."""
    import commands.reproduce as reproduce

    seen: dict = {}

    class Trained(Exception):
        pass

    def stage(jobs, args, reuse_shipped):
        seen.update(reuse=reuse_shipped, n=len(jobs))
        raise Trained

    monkeypatch.setattr(reproduce, "train_stage", stage)
    argv = ["--budget", "paper", "--algos", "bdc", "--scenarios", "catchup-v1",
            "--skip", "ablations,sizes,openacc", "--out", str(tmp_path / "out")]
    with pytest.raises(Trained):
        reproduce.main([*argv, *(["--retrain"] if retrain else [])])
    assert seen == {"reuse": not retrain, "n": 3}
    manifest = json.loads((tmp_path / "out" / "reproduce.json").read_text())
    assert manifest["settings"]["retrain"] is retrain
    other = [*argv, "--resume", *([] if retrain else ["--retrain"])]
    assert cli(["reproduce", *other]) == 2  # other settings: refused
