"""The shared training stage: when a shipped checkpoint stands in for a training run."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

import controllers.policy as policy
from commands.policy_training import copy_shipped, is_done, shipped_checkpoint
from envs.scenarios import make_scenario
from infra.errors import ConfigError
from marl.checkpoint import energy_model_id, save_checkpoint
from marl.training import PolicyJob, learner_config


def _zero_weights(config: dict) -> dict[str, torch.Tensor]:
    """Every acting weight of the N = 8 bdc network (zeros): a checkpoint must hold them all."""
    from marl.checkpoint import acting_weight_shapes

    return {k: torch.zeros(v) for k, v in acting_weight_shapes("bdc", config, 8).items()}


def _ship(folder: Path, job: PolicyJob, total_steps: int, energy_model: str | None = None,
          **config_changes: object) -> Path:
    config = {**job.key().stored_config(), **config_changes}
    path = folder / "bdc__catchup-v1__n8__s0.pt"
    save_checkpoint(path, algo="bdc", config=config, scenario="catchup-v1", n_vehicles=8, seed=0,
                    steps=total_steps // 2, energy_model=energy_model or energy_model_id(),
                    curve_summary={"total_steps": total_steps, "wall_s": 12.5},
                    weights=_zero_weights(config))
    path.with_suffix("").with_suffix(".curve.csv").write_text("episode,steps\n1,720\n")
    return path


@pytest.fixture
def job(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> PolicyJob:
    monkeypatch.setattr(policy, "CHECKPOINT_DIR", tmp_path / "shipped")
    monkeypatch.setattr(policy, "VARIANT_DIR", tmp_path / "shipped" / "variants")
    (tmp_path / "shipped").mkdir()
    return PolicyJob("bdc", make_scenario("catchup-v1"), 8, (0,), 600_000,
                     learner_config("bdc", {"gamma": 0.995}), tmp_path / "out",
                     validation_episodes=32, name="bdc",
                     study="main")


def test_a_shipped_run_stands_in_only_with_the_same_config_and_budget(
        tmp_path: Path, job: PolicyJob) -> None:
    shipped = tmp_path / "shipped"
    assert shipped_checkpoint(job) is None  # nothing shipped
    path = _ship(shipped, job, 602_340)  # stops at the first update past the budget
    assert shipped_checkpoint(job) == path
    _ship(shipped, job, 1_000_000)  # a longer run is another budget
    assert shipped_checkpoint(job) is None
    _ship(shipped, job, 590_000)
    assert shipped_checkpoint(job) is None
    _ship(shipped, job, 600_000, gamma=0.99)
    assert shipped_checkpoint(job) is None
    _ship(shipped, job, 600_000, energy_model="0123456789ab")  # trained under another reward
    assert shipped_checkpoint(job) is None


def test_a_run_trained_under_another_energy_model_is_not_done(tmp_path: Path, job: PolicyJob) -> None:
    """A copied or finished run made under another energy model (its reward differed) is not
    this job: the copy is redone, a finished run in the folder is refused, naming the model."""
    import json

    path = _ship(tmp_path / "shipped", job, 600_720)
    copy_shipped(job, path)
    assert is_done(job)
    info = json.loads(job.file(".source.json").read_text())
    assert info["energy_model"] == energy_model_id()
    job.file(".source.json").write_text(json.dumps({**info, "energy_model": "0123456789ab"}))
    assert not is_done(job)
    job.file(".source.json").unlink()
    final = job.out / "bdc__catchup-v1__n8__s0.final.pt"
    save_checkpoint(final, algo="bdc", config=job.key().stored_config(), scenario="catchup-v1",
                    n_vehicles=8, seed=0, steps=600_720, energy_model="0123456789ab",
                    curve_summary={}, weights=_zero_weights(job.key().stored_config()))
    with pytest.raises(ConfigError, match="another energy model"):
        is_done(job)


def test_a_copied_run_is_done_and_records_where_it_came_from(tmp_path: Path, job: PolicyJob) -> None:
    import json

    path = _ship(tmp_path / "shipped", job, 600_720)
    assert not is_done(job)
    copy_shipped(job, path)
    assert is_done(job)
    info = json.loads(job.file(".source.json").read_text())
    assert info["source"] == "shipped" and info["steps"] == 600_720 and info["wall_s"] == 12.5
    assert info["arithmetic"] == "native"  # the shipped run's own (no portable key)
    assert (job.out / "bdc__catchup-v1__n8__s0.curve.csv").exists()
    longer = replace(job, steps=700_000)
    assert not is_done(longer)


def test_a_shipped_run_is_found_in_a_variant_folder_by_its_config(tmp_path: Path,
                                                                  job: PolicyJob) -> None:
    """The shipped folder first, then each variant folder: the first with the job's config
    stands in; an ablation only in the variant folder of its own name."""
    variants = tmp_path / "shipped" / "variants"
    (variants / "other").mkdir(parents=True)
    (variants / "paper").mkdir()
    _ship(tmp_path / "shipped", job, 600_000, gamma=0.99)  # the leaderboard's: another config
    _ship(variants / "other", job, 2_000_000)  # another budget
    assert shipped_checkpoint(job) is None
    found = _ship(variants / "paper", job, 600_000)
    assert shipped_checkpoint(job) == found
    ablation = replace(job, name="bdc-noqsgd")
    assert shipped_checkpoint(ablation) is None  # not in another variant's folder
    (variants / "bdc-noqsgd").mkdir()
    own = _ship(variants / "bdc-noqsgd", job, 600_000)
    assert shipped_checkpoint(ablation) == own
