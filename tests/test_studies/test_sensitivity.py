"""``cacc-bench sensitivity``: the variants it trains, the table it writes, the knob reading."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from run_marks import FULL

from commands.cli import main as cli
from commands.sensitivity import KNOBS, variants
from studies.sensitivity import SENSITIVITY_COLUMNS, knob_effects, training_bits

TUNED = {"consensus_eps": 2e-4, "qsgd_levels": 1, "share_whole_critic": False, "gamma": 0.99}


def test_variants_change_one_knob_each_around_the_tuned_config() -> None:
    vs = variants(list(KNOBS), TUNED)
    assert vs[0]["name"] == "base" and vs[0]["overrides"] == {}
    assert [(v["name"], v["value"]) for v in vs[1:]] == [
        ("eps_x0.01", 2e-6), ("eps_x0.1", 2e-5), ("eps_x10", 2e-3),
        ("qsgd_s2", 2), ("qsgd_s4", 4), ("qsgd_off", "off"),
        ("share_whole_critic", "whole critic"), ("gamma_0.995", 0.995)]
    assert all(len(v["overrides"]) == 1 for v in vs[1:])
    assert variants(["gamma"], {**TUNED, "gamma": 0.995})[1]["overrides"] == {"gamma": 0.99}


def test_training_bits_add_step_messages_and_consensus() -> None:
    assert training_bits({"training_step_bits_per_agent_step": 162.0, "total_steps": 1000.0,
                          "training_consensus_bits_per_agent": 500.0,
                          "local_qsgd_payload_bits_per_agent": 70.0}) == (162_500.0, 70.0)


def test_knob_effects_on_a_hand_made_table() -> None:
    rows = [("eps", 1, True, -500, -520, -480, 0), ("eps", 2, False, -700, -760, -650, 3),
            ("eps", 3, False, -510, -540, -470, 0), ("gamma", 1, True, -500, -520, -480, 0),
            ("gamma", 2, False, -490, -515, -470, 0), ("reference", "", False, -600, -610, -590, 0)]
    df = pd.DataFrame([{"scenario": "s", "knob": k, "knob_value": v, "is_base": b,
                        "reward_mean": m, "reward_ci_low": lo, "reward_ci_high": hi,
                        "collisions": c} for k, v, b, m, lo, hi, c in rows])
    eff = knob_effects(df).set_index("knob")
    assert list(eff.index) == ["eps", "gamma"]
    assert eff.loc["eps", "reward_spread"] == 200 and eff.loc["eps", "worst_value"] == 2
    assert eff.loc["eps", "differs_from_base"] and not eff.loc["gamma", "differs_from_base"]
    assert eff.loc["gamma", "best_value"] == 2 and eff.loc["eps", "collisions"] == 3


def _study(out: Path, resume: bool = False) -> pd.DataFrame:
    argv = ["sensitivity", "--scenarios", "catchup-v1", "--knobs", "qsgd_levels,v2v",
            "--steps", "1800", "--validation-episodes", "2", "--episodes", "2",
            "--out", str(out)] + (["--resume"] if resume else [])
    assert cli(argv) == 0
    return pd.read_csv(out / "sensitivity.csv")


@FULL
def test_a_tiny_study_trains_evaluates_and_reports(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    df = _study(tmp_path / "a")
    assert list(df.columns) == list(SENSITIVITY_COLUMNS)
    assert set(df["knob"]) == {"qsgd_levels", "v2v_delay_s", "v2v_packet_loss", "reference"}
    assert (df["n_episodes"] == 2).all()
    q = df[df["knob"] == "qsgd_levels"].set_index("knob_value")
    assert list(q.index) == ["1", "2", "4", "off"]
    # QSGD's payload grows with its levels and vanishes when off; nothing of it is sent
    payload = q["qsgd_payload_bits_per_agent"]
    assert payload["1"] < payload["2"] < payload["4"] and payload["off"] == 0
    ckpt = torch.load(tmp_path / "a" / "checkpoints" / "qsgd_s2" / "bdc__catchup-v1__n8__s0.pt",
                      weights_only=True)["curve_summary"]
    assert q.loc["2", "training_bits_sent_per_agent"] == pytest.approx(training_bits(ckpt)[0])
    # the unchanged policy is the zero point of each V2V sweep, and only it is marked base
    base = df[df["is_base"]]
    assert set(base["knob"]) == {"qsgd_levels", "v2v_delay_s", "v2v_packet_loss"}
    assert np.allclose(base["reward_mean"], base["reward_mean"].iloc[0])
    assert df[df["knob"] == "reference"]["variant"].tolist() == ["ovm"]
    report = (tmp_path / "a" / "report.md").read_text()
    assert "## Which knob matters" in report
    assert (tmp_path / "a" / "figures" / "bits_against_reward.png").stat().st_size > 0
    # a rerun trains and runs nothing new and gives the same table
    pd.testing.assert_frame_equal(_study(tmp_path / "a", resume=True), df)
    capsys.readouterr()
    assert cli(["sensitivity", "--knobs", "gamma", "--out", str(tmp_path / "a"), "--resume"]) == 2
    assert "other settings" in capsys.readouterr().err
    assert json.loads((tmp_path / "a" / "sensitivity.json").read_text())["steps"] == 1800


@pytest.mark.parametrize("argv, message", [
    (["--knobs", "eps"], "unknown knob 'eps'"),
    (["--seeds", "a"], "--seeds must be a comma list of integers"),
    (["--steps", "0"], "--steps must be >= 1"),
    (["--scenarios", "nope-v1"], "nope-v1"),
])
def test_bad_input_exits_2(argv: list[str], message: str, tmp_path: Path,
                           capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(["sensitivity", *argv, "--out", str(tmp_path / "x")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_the_readme_quotes_the_committed_study() -> None:
    """The README's and the report's reading of the committed study (docs/sensitivity) use the
    numbers its sensitivity.csv holds."""
    root = Path(__file__).resolve().parents[2]
    table = pd.read_csv(root / "docs" / "sensitivity" / "sensitivity.csv")
    readme = " ".join((root / "docs" / "results.md").read_text().split())  # was the README's
    report = " ".join((root / "docs" / "sensitivity" / "report.md").read_text().split())

    def reward(scenario: str, knob: str, value: str) -> float:
        row = table[(table["scenario"] == scenario) & (table["knob"] == knob)
                    & (table["knob_value"].astype(str) == value)]
        assert len(row) == 1
        return float(row["reward_mean"].iloc[0])

    whole, base = reward("catchup-v1", "shared", "whole critic"), reward("catchup-v1", "gamma", "0.99")
    quote = f"{whole:.1f} against {base:.1f}"
    assert quote in readme and quote in report
    slow_base = reward("slowdown-v1", "gamma", "0.99")
    assert f"crawls, {slow_base:,.0f}" in readme and f"crawls ({slow_base:,.0f}" in report
    retrained = table[(table["scenario"] == "slowdown-v1") & ~table["is_base"]
                      & table["knob"].isin(["consensus_eps", "qsgd_levels", "shared", "gamma"])]
    assert (retrained["reward_mean"] > slow_base).all()  # "every retrained variant beats it"
    faults = table[(table["scenario"] == "catchup-v1")
                   & table["knob"].isin(["v2v_delay_s", "v2v_packet_loss"])]
    assert (faults["reward_mean"] - base).abs().max() <= 1.0  # "at most 1 point on catchup-v1"
    slow_faults = table[(table["scenario"] == "slowdown-v1")
                        & table["knob"].isin(["v2v_delay_s", "v2v_packet_loss"])]
    assert ((slow_faults["reward_mean"] - slow_base).abs() / abs(slow_base)).max() <= 0.05
