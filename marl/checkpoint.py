"""Checkpoint I/O of the MARL policies (small, safe to load, versioned).

A checkpoint is one ``torch.save`` file holding only tensors, strings, numbers, lists and dicts,
loaded with ``torch.load(weights_only=True)`` (no pickled code). It stores the acting weights of
every agent (stacked ``(N, ...)`` tensors, float16: the policy controller evaluates exactly these
weights, cast back to float32), the algorithm, its config, the scenario, N, the seed, the number of
training steps, the training curve summary, the fingerprint of the energy model its reward used
(:func:`energy_model_id`) and a format version. Loading a checkpoint of another
format version, algorithm or N fails with a :class:`envs.errors.ConfigError` naming the file and
the command that makes the right one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from envs.errors import ConfigError

FORMAT_VERSION = 1
WEIGHT_DTYPE = torch.float16


def train_command(algo: str, scenario: str, n_vehicles: int, seed: int = 0, out: str = "") -> str:
    """The ``cacc-bench train`` command that makes a checkpoint."""
    cmd = f"cacc-bench train --algo {algo} --scenario {scenario} --vehicles {n_vehicles} --seed {seed}"
    return cmd + (f" --out {out}" if out else "")


def energy_model_id() -> str:
    """Fingerprint of the shipped energy model (the reward's power term): a checkpoint records
    it, and a shipped or finished run counts as the same run only under the same model."""
    from envs.energy.power import _default_polynomial

    return _default_polynomial().fingerprint


def same_energy_model(record: dict[str, Any]) -> bool:
    """Whether a checkpoint (or a record copied from one) was trained under the shipped model."""
    return record.get("energy_model") == energy_model_id()


def save_checkpoint(
    path: str | Path,
    *,
    algo: str,
    config: dict[str, Any],
    scenario: str,
    n_vehicles: int,
    seed: int,
    steps: int,
    curve_summary: dict[str, float],
    weights: dict[str, torch.Tensor],
) -> Path:
    """Write a checkpoint; returns its path."""
    path = Path(path)
    payload = {
        "format_version": FORMAT_VERSION,
        "algo": algo,
        "config": dict(config),
        "scenario": scenario,
        "n_vehicles": int(n_vehicles),
        "seed": int(seed),
        "steps": int(steps),
        "curve_summary": {k: float(v) for k, v in curve_summary.items()},
        "energy_model": energy_model_id(),
        "weights": {k: v.detach().to(WEIGHT_DTYPE).contiguous() for k, v in weights.items()},
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)
    return path


def load_checkpoint(
    path: str | Path,
    *,
    algo: str | None = None,
    n_vehicles: int | None = None,
    scenario: str | None = None,
) -> dict[str, Any]:
    """Read a checkpoint and check it (weights come back as float32 tensors).

    Raises
    ------
    ConfigError
        Missing or unreadable file, other format version, other algorithm or N, or NaN or
        infinite weights (the message names the file and the train command).
    """
    path = Path(path)
    want_algo = algo or "ALGO"
    want_scenario = scenario or "SCENARIO"
    want_n = n_vehicles or 8

    def fix() -> str:
        return f"make it with `{train_command(want_algo, want_scenario, want_n)}`"

    if not path.exists():
        raise ConfigError(f"checkpoint {path} does not exist; {fix()}")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure means an unusable file
        raise ConfigError(f"checkpoint {path} cannot be read ({exc}); {fix()}") from None
    if not isinstance(data, dict) or data.get("format_version") != FORMAT_VERSION:
        got = data.get("format_version") if isinstance(data, dict) else None
        raise ConfigError(
            f"checkpoint {path} has format version {got}, this cacc-bench reads version "
            f"{FORMAT_VERSION}; re-train: `{train_command(want_algo, want_scenario, want_n)}`"
        )
    if scenario is None:
        want_scenario = data.get("scenario", want_scenario)
    if algo is not None and data["algo"] != algo:
        raise ConfigError(
            f"checkpoint {path} holds algorithm {data['algo']!r}, not {algo!r}; {fix()}"
        )
    if n_vehicles is not None and data["n_vehicles"] != n_vehicles:
        raise ConfigError(
            f"checkpoint {path} was trained for N = {data['n_vehicles']} followers, not "
            f"{n_vehicles}; {fix()}"
        )
    data["weights"] = {k: v.to(torch.float32) for k, v in data["weights"].items()}
    bad = [k for k, v in data["weights"].items() if not bool(torch.isfinite(v).all())]
    if bad:
        raise ConfigError(
            f"checkpoint {path} has non-finite weights ({', '.join(bad)}): its training "
            f"diverged; {fix()}"
        )
    return data
