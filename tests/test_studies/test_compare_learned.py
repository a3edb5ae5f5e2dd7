"""``cacc-bench compare-learned`` and :mod:`studies.learned_report`: the comparison rules on
hand-made episodes, the command in small form, and the committed report read back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from run_marks import FULL

from commands.cli import main
from studies.learned_report import (
    DEGRADED,
    HIGHER,
    IDEAL,
    INCONCLUSIVE,
    LOWER,
    comparisons_frame,
    policy_name,
    write_report,
)

DOCS = Path(__file__).resolve().parents[2] / "docs" / "compare-learned"


def _episodes(policy: str, rewards: np.ndarray, setting: tuple[float, float] = IDEAL,
              collisions: tuple[int, ...] = ()) -> list[dict]:
    """Rows of an episodes frame: ``rewards`` (training seeds, episodes)."""
    rows = []
    for s, row in enumerate(np.atleast_2d(rewards)):
        for k, r in enumerate(row):
            rows.append({"policy": policy, "train_seed": s, "scenario": "catchup-v1",
                         "n_vehicles": 8, "comm_delay_s": setting[0], "packet_loss": setting[1],
                         "seed": 2000 + 10 * k, "reward": float(r),
                         "collision": (s, k) in collisions, "energy_kwh_per_100km": 9.0,
                         "gap_rmse_m": 1.0, "compute_ms_p50": 0.01})
    return rows


def test_policy_names_drop_the_training_seed_and_keep_the_variant() -> None:
    assert policy_name("ippo", {"seed": "2"}) == "ippo"
    assert policy_name("ippo", {"seed": "1", "variant": "ovm-gain"}) == "ippo (OVM-gain)"
    assert policy_name("ippo", {"variant": "elsewhere"}) is None
    assert policy_name("cacc", {}) == "cacc"


def test_collisions_decide_first_then_the_interval() -> None:
    rng = np.random.default_rng(0)
    base = rng.normal(-400, 20, size=30)
    rows = (_episodes("mpc", base) + _episodes("distill", base - 5 + rng.normal(0, 0.1, 30))
            + _episodes("ippo", np.stack([base + 50, base + 60, base + 40]), collisions=((1, 3),))
            + _episodes("ippo (OVM-gain)", np.stack([base + rng.normal(0, 5, 30)] * 3)))
    comp = comparisons_frame(pd.DataFrame(rows)).set_index(["ours", "other"])
    # far higher reward, but one colliding episode: lower, decided on collisions
    assert comp.loc[("ippo", "mpc"), "verdict"] == LOWER
    assert comp.loc[("ippo", "mpc"), "basis"] == "collisions"
    # a clear paired difference of -5: lower, on the reward
    row = comp.loc[("distill", "mpc")]
    assert row["verdict"] == LOWER and row["basis"] == "reward"
    assert row["difference"] == pytest.approx(-5.0, abs=0.05) and row["ci_high"] < 0
    # noise around zero: inconclusive
    assert comp.loc[("ippo (OVM-gain)", "mpc"), "verdict"] == INCONCLUSIVE


def test_the_gap_is_the_sum_of_its_parts() -> None:
    """``OVM-gain - mpc = (OVM-gain - ippo) + (ippo - distill) + (distill - mpc)`` in the means."""
    rng = np.random.default_rng(1)
    rows = []
    for name, shift in (("mpc", 0), ("distill", -3), ("ippo", -20), ("ippo (OVM-gain)", -8)):
        rows += _episodes(name, rng.normal(-400 + shift, 15, size=(3 if name != "mpc" else 1, 20)))
    comp = comparisons_frame(pd.DataFrame(rows)).set_index(["ours", "other"])["difference"]
    parts = (comp[("ippo (OVM-gain)", "ippo")] + comp[("ippo", "distill")]
             + comp[("distill", "mpc")])
    assert comp[("ippo (OVM-gain)", "mpc")] == pytest.approx(parts, rel=1e-12)


def test_communication_pairs_each_training_seed_and_episode_with_itself() -> None:
    """A policy whose degraded runs are its ideal ones plus 0.5: the difference is 0.5 with a
    zero-width interval, however much the seeds and episodes differ among themselves."""
    rng = np.random.default_rng(2)
    ideal = rng.normal(-400, 50, size=(3, 25))
    rows = _episodes("ippo", ideal) + _episodes("ippo", ideal + 0.5, DEGRADED)
    comp = comparisons_frame(pd.DataFrame(rows))
    row = comp[comp["question"] == "communication"].iloc[0]
    assert row["difference"] == pytest.approx(0.5)
    assert row["ci_low"] == pytest.approx(0.5) and row["ci_high"] == pytest.approx(0.5)
    assert row["verdict"] == HIGHER


@FULL
def test_the_command_in_small_form(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cl"
    argv = ["compare-learned", "--scenarios", "catchup-v1", "--episodes", "1", "--vehicles",
            "4", "--executor", "serial", "--out", str(out)]
    assert main(argv) == 0
    report = (out / "report.md").read_text()
    assert str(tmp_path) not in report  # the report names no machine's path
    comp = pd.read_csv(out / "comparisons.csv")
    assert {"the gap", "learning", "communication"} <= set(comp["question"])
    policies = pd.read_csv(out / "policies.csv")
    assert {"cacc", "mpc", "ippo", "distill"} <= set(policies["policy"])
    assert main([*argv, "--resume"]) == 0
    capsys.readouterr()
    assert main(["compare-learned", "--scenarios", "nope-v1", "--out", str(tmp_path / "x")]) == 2
    assert main(["compare-learned", "--vehicles", "1", "--out", str(tmp_path / "x")]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_the_committed_report_is_its_episodes_read_again(tmp_path: Path) -> None:
    """``docs/compare-learned/report.md`` and ``comparisons.csv`` are what the report code makes
    of the committed ``episodes.csv`` (the runs themselves: ``cacc-bench compare-learned``)."""
    ep = pd.read_csv(DOCS / "episodes.csv")
    committed = (DOCS / "report.md").read_text()
    command = committed.split("Made by `", 1)[1].split(" --out FOLDER`", 1)[0]
    comp = comparisons_frame(ep)
    write_report(ep, comp, tmp_path, command, pd.read_csv(DOCS / "sweeps.csv"))
    assert (tmp_path / "report.md").read_text() == committed
    pd.testing.assert_frame_equal(comp, pd.read_csv(DOCS / "comparisons.csv"), check_dtype=False)


@pytest.mark.parametrize(("policy", "scenario", "delay", "loss"), [
    ("cacc", "catchup-v1", 0.2, 0.3),
    ("ippo (residual, time-aware critic)", "slowdown-v1", 0.0, 0.0)])
def test_the_committed_sweeps_are_the_shipped_policies(policy, scenario, delay, loss) -> None:
    """A committed sweep peak (``sweeps.csv``, :func:`studies.learned_report.policy_sweeps`)
    recomputed: the model-based law exactly, a sampled policy within 0.05 % (across CPUs)."""
    from studies.learned_report import policy_sweeps

    ep = pd.read_csv(DOCS / "episodes.csv")
    ep = ep[(ep["policy"] == policy) & (ep["scenario"] == scenario)
            & (ep["comm_delay_s"] == delay) & (ep["packet_loss"] == loss)]
    got = policy_sweeps(ep)
    want = pd.read_csv(DOCS / "sweeps.csv")
    want = want[(want["policy"] == policy) & (want["scenario"] == scenario)
                & (want["comm_delay_s"] == delay) & (want["packet_loss"] == loss)]
    assert len(got) == len(want) == 1
    assert got["sweep_peak_gain"].iloc[0] == pytest.approx(want["sweep_peak_gain"].iloc[0],
                                                           rel=5e-4)
    assert bool(got["sweep_string_stable"].iloc[0]) == bool(want["sweep_string_stable"].iloc[0])


@pytest.mark.parametrize(("policy", "scenario"), [
    ("ippo (residual on cacc)", "catchup-v1"), ("ippo-bdc", "slowdown-v1"), ("cacc", "catchup-v1")])
def test_the_committed_episodes_are_the_shipped_policies(policy: str, scenario: str) -> None:
    """A few committed episodes rerun from the shipped checkpoints give the same rewards."""
    from benchmark.rollout import rollout_batch
    from controllers.registry import make_controller
    from envs.scenarios import make_scenario
    from studies.learned_report import POLICIES

    ep = pd.read_csv(DOCS / "episodes.csv")
    ep = ep[(ep["policy"] == policy) & (ep["scenario"] == scenario) & (ep["comm_delay_s"] == 0)
            & (ep["packet_loss"] == 0) & (ep["train_seed"] == 0)].sort_values("seed").head(3)
    assert len(ep) == 3
    ctrl, opts = POLICIES[policy]
    opts = {**opts, "seed": "0"} if ctrl != "cacc" else opts
    trajs = rollout_batch(make_controller(ctrl, **opts), make_scenario(scenario), 8,
                          [int(s) for s in ep["seed"]])
    np.testing.assert_allclose([t.reward.mean() for t in trajs], ep["reward"], rtol=1e-8)  # CSV digits


def test_the_readme_answer_is_the_committed_report() -> None:
    """Every number of the README's answer is in the committed report; its compute and
    communication sentences hold on the committed tables."""
    import re

    readme = (DOCS.parents[1] / "README.md").read_text()
    # the answer's bullets up to the string-stability one (that one quotes its own report,
    # docs/string-stability, checked by tests/test_studies/test_string_stability_report.py)
    section = readme[readme.index("## Learned control"):readme.index("- **String stability.**")]
    report = (DOCS / "report.md").read_text()
    numbers = re.findall(r"(?<![\d.])-?\d+\.\d\d(?!\d)", section)
    assert len(numbers) >= 15
    for x in numbers:
        if x in ("1.64", "2.00"):
            continue
        assert x in report, x
    pol = pd.read_csv(DOCS / "policies.csv")
    ideal = pol[(pol["comm_delay_s"] == 0) & (pol["packet_loss"] == 0)].set_index(
        ["scenario", "policy"])["compute_ms_p50"]
    for sc in ("catchup-v1", "slowdown-v1"):
        assert round(ideal[(sc, "distill")], 4) == 0.0021
    assert (round(ideal[("catchup-v1", "mpc")], 2), round(ideal[("slowdown-v1", "mpc")], 2)) == (
        1.64, 2.00)
    comp = pd.read_csv(DOCS / "comparisons.csv")
    comm = comp[(comp["question"] == "communication")
                & comp["ours"].isin(["ippo", "ippo (OVM-gain)", "mappo", "ippo-bdc"])]
    assert round(-comm["difference"].min(), 2) == 2.15


def test_what_docs_learned_control_says_is_left_reads_the_report() -> None:
    import re

    text = (DOCS.parent / "learned-control.md").read_text()
    left = text[text.index("## Not done yet"):]
    report = (DOCS / "report.md").read_text()
    numbers = re.findall(r"(?<![\d.])-?\d+\.\d\d(?!\d)", left)
    assert all(x in report for x in numbers)
