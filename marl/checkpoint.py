"""Checkpoint I/O of the MARL policies (small, safe to load, versioned).

A checkpoint is one ``torch.save`` file holding only tensors, strings, numbers, lists and dicts,
loaded with ``torch.load(weights_only=True)`` (no pickled code). It stores the acting weights of
every agent (stacked ``(N, ...)`` tensors, float16: the policy controller evaluates exactly these
weights, cast back to float32), the algorithm, its config, the scenario, N, the seed, the number of
training steps, the training curve summary, the fingerprint of the energy model its reward used
(:func:`energy_model_id`) and a format version. Loading a checkpoint of another
format version, algorithm or N fails with a :class:`infra.errors.ConfigError` naming the file and
the command that makes the right one.

Format 2 adds ``sha256``, a content hash over the canonical JSON of every other field and the
weight tensors in key order (:func:`content_hash`); loading recomputes it and refuses a file
whose hash, weight dtypes or shapes, or config field types do not match (a damaged, truncated
or altered file is a :class:`ConfigError` saying what to do, never a traceback). The shipped
format-1 files (no hash) load only when the whole file's SHA-256 is a shipped one
(:data:`marl.shipped_digests.FORMAT_1_SHA256`). A checkpoint is written atomically
(:mod:`infra.atomic`): a reader sees the old file or the new one, never part of one.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import hashlib
import io
import json
import math
import random
import re
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from envs.params import EVAL_MODES
from infra.atomic import StagedFiles, write_with
from infra.errors import ConfigError

FORMAT_VERSION = 2
#: Format 1: no content hash; read only for the shipped files (by their file digest).
SHIPPED_FORMAT = 1
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


def save_checkpoint(path: str | Path, **fields: Any) -> Path:
    """Write the checkpoint of :func:`checkpoint_payload`'s keyword ``fields`` atomically;
    returns its path."""
    path, payload = Path(path), checkpoint_payload(**fields)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_payload(path, payload)
    return path


def checkpoint_payload(
    *,
    algo: str,
    config: dict[str, Any],
    scenario: str,
    n_vehicles: int,
    seed: int,
    steps: int,
    curve_summary: dict[str, float],
    weights: dict[str, torch.Tensor],
    energy_model: str | None = None,
) -> dict[str, Any]:
    """The dict a checkpoint file holds (weights copied to the CPU as float16), hashed."""
    payload = {
        "format_version": FORMAT_VERSION,
        "algo": algo,
        "config": dict(config),
        "scenario": scenario,
        "n_vehicles": int(n_vehicles),
        "seed": int(seed),
        "steps": int(steps),
        "curve_summary": {k: float(v) for k, v in curve_summary.items()},
        "energy_model": energy_model if energy_model is not None else energy_model_id(),
        "weights": {k: v.detach().to("cpu", WEIGHT_DTYPE).clone().contiguous()
                    for k, v in weights.items()},
    }
    payload["sha256"] = content_hash(payload)
    return payload


def write_payload(path: str | Path, payload: dict[str, Any], atomic: bool = True) -> None:
    """Write a checkpoint dict (its hash recomputed: fields may have changed); atomically
    unless ``atomic`` is False (``path`` is then itself a temporary file)."""
    payload = {**payload, "sha256": content_hash(payload)}
    if atomic:
        write_with(path, lambda tmp: save_to_file(payload, tmp))
    else:
        save_to_file(payload, path)


#: Validation numbers a learning curve records per evaluation mode (``eval_<key>_<mode>``).
CURVE_EVAL_KEYS: tuple[str, ...] = ("reward", "collisions")
#: The columns of a learning curve (``<stem>.curve.csv``), every learner's: the episodes and
#: environment steps so far, the learner's own (possibly shaped) training reward, and per
#: evaluation mode the validation reward and collisions; a cell is empty where not measured (a
#: shared-policy learner records no episode or training reward, and validates sampled actions
#: only). Curves written before hold ``steps,validation_reward,validation_collisions``.
CURVE_COLUMNS: tuple[str, ...] = ("episode", "steps", "train_reward", *(
    f"eval_{k}_{m}" for m in EVAL_MODES for k in CURVE_EVAL_KEYS))


def write_run(out: Path, stem: str, curve: Sequence[dict[str, float]],
              checkpoints: dict[str, dict[str, Any]]) -> None:
    """Write a finished run's files together: ``<stem>.curve.csv`` (:data:`CURVE_COLUMNS`) and
    each checkpoint (``suffix -> payload``: ``.final.pt``, ``.pt``), each to a temporary file,
    then all renamed (:class:`infra.atomic.StagedFiles`): an interrupted or failed run leaves the
    files of an earlier run byte for byte as they were."""
    def write_curve(path: Path) -> None:
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(CURVE_COLUMNS)
            for row in curve:
                cells = [row.get(k, math.nan) for k in CURVE_COLUMNS]
                w.writerow(["" if math.isnan(v) else f"{v:.0f}" if k < 2 else f"{v:.4f}"
                            for k, v in enumerate(cells)])

    out.mkdir(parents=True, exist_ok=True)
    with StagedFiles() as staged:
        staged.write_with(out / f"{stem}.curve.csv", write_curve)
        for suffix, payload in checkpoints.items():
            staged.write_with(out / f"{stem}{suffix}",
                              functools.partial(write_payload, payload=payload, atomic=False))
        staged.commit()


# ---------------------------------------------------------------------------- resumable snapshots
#: Seconds of training between two resumable snapshots of a run (``<stem>.snapshot.pt``): the
#: most work, beside the batch or update in flight, that an interruption loses.
SNAPSHOT_EVERY_S = 60.0
#: The format of a snapshot file.
SNAPSHOT_FORMAT = 1
SNAPSHOT_SUFFIX = ".snapshot.pt"


class Snapshots:
    """The resumable snapshot of one training run, written every :data:`SNAPSHOT_EVERY_S`.

    The file (``<stem>.snapshot.pt`` beside the run's files) holds everything the run continues
    from bit for bit at a boundary of its loop (a batch of the paper's learners, an update of
    the shared ones, a round of the distiller): weights, optimiser state, random streams,
    counters, the curve so far and the kept snapshot, as the trainer's state dict (tensors,
    numbers, strings; read with ``torch.load(weights_only=True)``, no pickled code) with its
    SHA-256 and the run it belongs to (``identity``: learner, scenario, N, seed, budget, config,
    arithmetic, energy model). Each write is atomic (:mod:`infra.atomic`): an interruption
    leaves the last snapshot whole. The run removes the file when its own files are written.

    Parameters
    ----------
    path : path
        The snapshot file.
    identity : dict
        What the run is; a file recording another is refused (:meth:`read`).
    every_s : float, optional
        Seconds between writes (default :data:`SNAPSHOT_EVERY_S`; 0: at every boundary).
    """

    def __init__(self, path: str | Path, identity: dict[str, Any],
                 every_s: float | None = None) -> None:
        self.path = Path(path)
        self.identity = dict(identity)
        self.every_s = SNAPSHOT_EVERY_S if every_s is None else float(every_s)
        self._clock = time.monotonic
        self._last = self._clock()

    def due(self) -> bool:
        """Whether :attr:`every_s` passed since the last write (or since the run started)."""
        return self._clock() - self._last >= self.every_s

    def write(self, steps: int, state: dict[str, Any]) -> None:
        """Replace the file with ``state`` (the trainer's, after ``steps`` environment steps)."""
        buffer = io.BytesIO()
        torch.save(state, buffer)
        blob = buffer.getvalue()
        payload = {"format_version": SNAPSHOT_FORMAT, "identity": self.identity,
                   "steps": int(steps), "sha256": hashlib.sha256(blob).hexdigest(),
                   "state": blob}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_with(self.path, lambda tmp: save_to_file(payload, tmp))
        self._last = self._clock()

    def steps(self) -> int | None:
        """The environment steps the file's run had taken (None without a file); verified as
        :meth:`read` does."""
        header = self._header()
        return None if header is None else int(header["steps"])

    def read(self) -> dict[str, Any] | None:
        """The state the file holds, or None without a file.

        Raises
        ------
        ConfigError
            A damaged file (unreadable, another format, a hash that does not match), or one of
            another run (learner, scenario, N, seed, budget, config, arithmetic or energy
            model differ); the one line names the file and what to do.
        """
        header = self._header()
        if header is None:
            return None
        state = torch.load(io.BytesIO(header["state"]), map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise self._damaged("its state is not a dict")
        return state

    def remove(self) -> None:
        """Remove the file (the run finished: its checkpoint is the product)."""
        self.path.unlink(missing_ok=True)

    def _damaged(self, what: str) -> ConfigError:
        return ConfigError(f"snapshot {self.path} is damaged ({what}); remove it to train this "
                           "run from the start")

    def _header(self) -> dict[str, Any] | None:
        if not self.path.exists():
            return None
        try:
            data = torch.load(io.BytesIO(self.path.read_bytes()), map_location="cpu",
                              weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any failure means an unusable file
            reason = " ".join(str(exc).split()).split(". ")[0][:160] or type(exc).__name__
            raise self._damaged(f"it cannot be read: {reason}") from None
        if not isinstance(data, dict) or data.get("format_version") != SNAPSHOT_FORMAT:
            got = data.get("format_version") if isinstance(data, dict) else None
            raise self._damaged(f"format {got}, this cacc-bench reads {SNAPSHOT_FORMAT}")
        blob = data.get("state")
        if not isinstance(blob, bytes) or hashlib.sha256(blob).hexdigest() != data.get("sha256"):
            raise self._damaged("its content hash does not match")
        got = data.get("identity")
        if not isinstance(got, dict) or not isinstance(data.get("steps"), int):
            raise self._damaged("no identity or steps")
        if got != self.identity:
            raise ConfigError(
                f"snapshot {self.path} is of another run ({', '.join(_differ(got, self.identity))}"
                " differ); resume with the options it was made with, or remove it to train this "
                "run from the start")
        return data


def _differ(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """The keys where ``a`` and ``b`` differ (``config fields x, y`` inside a dict)."""
    out = []
    for k in sorted({*a, *b}):
        x, y = a.get(k), b.get(k)
        if x == y:
            continue
        if isinstance(x, dict) and isinstance(y, dict):
            fields = sorted(f for f in {*x, *y} if x.get(f) != y.get(f))
            out.append(f"{k} fields {', '.join(fields)}")
        else:
            out.append(k)
    return out


def plain_state(value: Any, shared: Sequence[torch.Generator] = ()) -> Any:
    """``value`` as the plain data a snapshot holds: tensors and arrays copied to CPU tensors,
    numbers, strings, lists, dicts with string keys, an object's attributes by name, and a
    generator of ``shared`` by its place (restored as the trainer's own,
    :func:`restore_state`).

    Raises
    ------
    TypeError
        For anything else (a learner keeping such state cannot be snapshotted: say how).
    """
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, torch.Tensor):
        return value.detach().to("cpu", copy=True)
    if isinstance(value, np.ndarray):
        return {"__array__": torch.from_numpy(np.array(value, copy=True))}
    if isinstance(value, torch.Generator):
        for i, g in enumerate(shared):
            if value is g:
                return {"__generator__": i}
        raise TypeError("a snapshot holds the trainer's own generators only")
    if isinstance(value, list | tuple):
        return [plain_state(v, shared) for v in value]
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return {k: plain_state(v, shared) for k, v in value.items()}
    if hasattr(value, "__dict__") and not callable(value):
        return {"__object__": type(value).__qualname__,
                "attributes": {k: plain_state(v, shared) for k, v in vars(value).items()}}
    raise TypeError(f"a snapshot cannot hold a {type(value).__name__}")


def restore_state(current: Any, state: Any, shared: Sequence[torch.Generator] = (),
                  device: torch.device | str = "cpu") -> Any:
    """The value :func:`plain_state` made ``state`` of, rebuilt on ``current`` (the value of a
    freshly made trainer it replaces): an object is filled in place, a tuple stays a tuple,
    tensors go to ``current``'s device (``device`` where it has none)."""
    if isinstance(state, dict) and "__object__" in state:
        if current is None or type(current).__qualname__ != state["__object__"]:
            raise ConfigError(f"a snapshot holds a {state['__object__']} where this trainer "
                              f"has {type(current).__name__}: remove it to train from the start")
        for k, v in state["attributes"].items():
            setattr(current, k, restore_state(getattr(current, k, None), v, shared, device))
        return current
    if isinstance(state, dict) and "__generator__" in state:
        return shared[state["__generator__"]]
    if isinstance(state, dict) and "__array__" in state:
        return state["__array__"].numpy().copy()
    if isinstance(state, torch.Tensor):
        return state.to(current.device if isinstance(current, torch.Tensor) else device)
    if isinstance(state, list):
        items = list(current) if isinstance(current, list | tuple) else []
        out = [restore_state(items[i] if i < len(items) else None, v, shared, device)
               for i, v in enumerate(state)]
        return tuple(out) if isinstance(current, tuple) else out
    if isinstance(state, dict):
        named = current if isinstance(current, dict) else {}
        return {k: restore_state(named.get(k), v, shared, device) for k, v in state.items()}
    return state


def process_rng_state() -> dict[str, Any]:
    """The process-wide random streams (torch's, numpy's, Python's) as plain data."""
    # numpy's global stream: training draws none, kept so that nothing can differ
    kind, keys, pos, has_gauss, cached = np.random.get_state()  # noqa: NPY002
    version, internal, gauss = random.getstate()
    return {"torch": torch.get_rng_state(),
            "numpy": [kind, torch.from_numpy(np.array(keys, dtype=np.int64)), int(pos),
                      int(has_gauss), float(cached)],
            "python": [int(version), list(internal), gauss]}


def set_process_rng_state(state: dict[str, Any]) -> None:
    """Put back :func:`process_rng_state`'s streams."""
    torch.set_rng_state(state["torch"])
    kind, keys, pos, has_gauss, cached = state["numpy"]
    keys = keys.numpy().astype(np.uint32)
    np.random.set_state((kind, keys, pos, has_gauss, cached))  # noqa: NPY002
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))


def save_to_file(payload: dict[str, Any], path: str | Path) -> None:
    """``torch.save`` into memory, then one plain write of the bytes to ``path``: a full disk
    is then an ``OSError`` (``ENOSPC``) naming the file, where torch's zip writer raised a
    ``RuntimeError`` (``unexpected pos``) that no caller could tell from a bug."""
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    with open(path, "wb") as fh:
        fh.write(buffer.getbuffer())


def content_hash(data: dict[str, Any]) -> str:
    """SHA-256 over the canonical JSON of every field but ``weights`` and ``sha256``, then each
    weight's name, dtype, shape and bytes in key order."""
    return _hash({k: v for k, v in data.items() if k not in ("weights", "sha256")},
                 data.get("weights", {}))


def _hash(meta: dict[str, Any], weights: dict[str, Any]) -> str:
    h = hashlib.sha256(json.dumps(meta, sort_keys=True, separators=(",", ":"),
                                  default=repr).encode())
    for key in sorted(weights):
        t = weights[key].detach().to("cpu").contiguous()
        h.update(f"\0{key}\0{t.dtype}\0{list(t.shape)}\0".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


#: The fields that, with the weights, decide how a checkpoint's policy acts.
ACTING_FIELDS: tuple[str, ...] = ("algo", "n_vehicles", "config")


def policy_id(data: dict[str, Any]) -> str:
    """SHA-256 of what a loaded checkpoint's policy acts with: :data:`ACTING_FIELDS` and the
    weights (hashed as :func:`content_hash` does). A run retrained to the same weights has the
    same id whatever its timings or commit; empty without weights."""
    if "weights" not in data:
        return ""
    return _hash({k: data.get(k) for k in ACTING_FIELDS}, data["weights"])


def load_checkpoint(
    path: str | Path,
    *,
    algo: str | None = None,
    n_vehicles: int | None = None,
    scenario: str | None = None,
    seed: int | None = None,
) -> dict[str, Any]:
    """Read a checkpoint and verify it (weights come back as float32 tensors); ``algo``,
    ``n_vehicles``, ``scenario`` and ``seed``, where given, are what it is loaded as, and must
    be what it records (a file copied or renamed keeps its own).

    Raises
    ------
    ConfigError
        Missing, unreadable, damaged or altered file (content hash, weight dtypes and shapes,
        config field types), other format version, a recorded algorithm, N, scenario or seed
        other than the one given, or NaN or infinite weights; the one-line message names the
        file and what to do.
    """
    path = Path(path)
    named = re.fullmatch(r"(.+?)__(.+?)__n(\d+)__s(\d+)(?:\.final)?\.pt", path.name)
    want_algo = algo or (named.group(1) if named else "ALGO")
    want_scenario = scenario or (named.group(2) if named else "SCENARIO")
    want_n = n_vehicles or (int(named.group(3)) if named else 8)
    want_seed = seed if seed is not None else int(named.group(4)) if named else 0

    def fix() -> str:
        cmd = train_command(want_algo, want_scenario, want_n, want_seed, str(path.parent))
        return f"make it with `{cmd}`"

    def damaged(what: str) -> ConfigError:
        return ConfigError(
            f"checkpoint {path} is damaged or was altered ({what}); restore the file (a shipped "
            f"one with `git checkout -- <file>`) or train it again: {fix()}")

    if not path.exists():
        raise ConfigError(f"checkpoint {path} does not exist; {fix()}")
    if not path.is_file():
        raise ConfigError(f"checkpoint {path} is not a file; {fix()}")
    try:
        blob = path.read_bytes()
        data = torch.load(io.BytesIO(blob), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure means an unusable file
        reason = " ".join(str(exc).split()).split(". ")[0][:160] or type(exc).__name__
        raise ConfigError(f"checkpoint {path} cannot be read ({reason}); {fix()}") from None
    got = data.get("format_version") if isinstance(data, dict) else None
    if got == SHIPPED_FORMAT:
        from marl.shipped_digests import FORMAT_1_SHA256

        if hashlib.sha256(blob).hexdigest() not in FORMAT_1_SHA256:
            shipped = {Path(v).name: v for v in reversed(list(FORMAT_1_SHA256.values()))}
            which = (f"differs from the shipped controllers/checkpoints/{shipped[path.name]} "
                     "(restore a damaged copy with `git checkout` or copy it again)"
                     if path.name in shipped else "is not one of the shipped files")
            raise ConfigError(
                f"checkpoint {path} has format version 1 (no content hash) and {which}, so it "
                f"cannot be verified; re-train ({fix()}), or, if you trust the file, add its "
                f"hash: `python -m marl.checkpoint {path}`")
    elif got != FORMAT_VERSION:
        raise ConfigError(
            f"checkpoint {path} has format version {got}, this cacc-bench reads version "
            f"{FORMAT_VERSION}; re-train: {fix()}"
        )
    assert isinstance(data, dict)
    if scenario is None and isinstance(data.get("scenario"), str):
        want_scenario = data["scenario"]
    if got == FORMAT_VERSION:
        try:
            ok = data.get("sha256") == content_hash(data)
        except Exception:  # noqa: BLE001 - weights that cannot even be hashed
            ok = False
        if not ok:
            raise damaged("its content hash does not match")
    _check_fields(data, damaged)
    for field, want in (("algo", algo), ("n_vehicles", n_vehicles), ("scenario", scenario),
                        ("seed", seed)):
        if want is not None and data[field] != want:
            raise ConfigError(f"checkpoint {path} {_RECORDS[field].format(data[field], want)} "
                              f"(a copied or renamed file keeps what it records); {fix()}")
    _check_config_and_shapes(data, damaged)
    data["weights"] = {k: v.to(torch.float32) for k, v in data["weights"].items()}
    bad = [k for k, v in data["weights"].items() if not bool(torch.isfinite(v).all())]
    if bad:
        raise ConfigError(
            f"checkpoint {path} has non-finite weights ({', '.join(bad)}): its training "
            f"diverged; {fix()}"
        )
    return data


#: What a checkpoint records, beside what it was loaded as (:func:`load_checkpoint`).
_RECORDS: dict[str, str] = {
    "algo": "holds algorithm {!r}, not {!r}", "n_vehicles": "was trained for N = {} followers, not {}",
    "scenario": "was trained on {}, not {}", "seed": "was trained with seed {}, not {}"}
#: Fields every checkpoint holds, with their types.
_FIELDS: dict[str, type] = {
    "algo": str, "config": dict, "scenario": str, "n_vehicles": int, "seed": int, "steps": int,
    "curve_summary": dict, "weights": dict,
}


def _check_fields(data: dict[str, Any], damaged: Any) -> None:
    """Every field present with its type; weights are named float16 tensors."""
    for name, kind in _FIELDS.items():
        value = data.get(name)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise damaged(f"field {name!r} is {type(value).__name__}, not {kind.__name__}")
    for key, value in data["curve_summary"].items():
        if not isinstance(key, str) or not isinstance(value, float):
            raise damaged(f"curve_summary entry {key!r} is not a number")
    for key, value in data["weights"].items():
        if not isinstance(key, str) or not isinstance(value, torch.Tensor):
            raise damaged(f"weight {key!r} is not a tensor")
        if value.dtype != WEIGHT_DTYPE:
            raise damaged(f"weight {key!r} is {value.dtype}, not {WEIGHT_DTYPE}")


#: Python types a config field's annotation admits (annotations are strings here).
_ANNOTATION_TYPES: dict[str, tuple[type, ...]] = {
    "int": (int,), "float": (int, float), "bool": (bool,), "str": (str,), "None": (type(None),),
}


def _check_config_and_shapes(data: dict[str, Any], damaged: Any) -> None:
    """For an algorithm of :mod:`marl.config`: the config's fields exist with the annotated
    types and build a valid config, and every stored weight is one of that network's acting
    weights with its shape (``(N, ...)``). Other algorithms are covered by the hash only."""
    from marl.config import algorithm, config_from_dict
    from marl.learners import PAPER_ALGORITHMS

    if data["algo"] not in PAPER_ALGORITHMS:
        return
    algo = algorithm(data["algo"])
    fields = {f.name: f for f in dataclasses.fields(algo.config_cls)}
    for key, value in data["config"].items():
        if key not in fields:
            raise damaged(f"config field {key!r} is not a {algo.name} field")
        kinds = [k.strip() for k in str(fields[key].type).split("|")]
        if all(k in _ANNOTATION_TYPES for k in kinds):
            allowed = tuple(t for k in kinds for t in _ANNOTATION_TYPES[k])
            if not isinstance(value, allowed) or (isinstance(value, bool) and "bool" not in kinds):
                raise damaged(f"config field {key!r} = {value!r} is not {fields[key].type}")
            if isinstance(value, float) and not math.isfinite(value):
                raise damaged(f"config field {key!r} = {value!r} is not finite")
    try:
        config = config_from_dict(algo, data["config"])
    except ConfigError as exc:
        raise damaged(f"config: {exc}") from None
    expected = acting_weight_shapes(algo.name, config, data["n_vehicles"])
    for key, value in data["weights"].items():
        if key not in expected:
            raise damaged(f"weight {key!r} is not a {algo.name} network weight")
        if tuple(value.shape) != expected[key]:
            raise damaged(f"weight {key!r} has shape {tuple(value.shape)}, the network's is "
                          f"{expected[key]}")
    missing = sorted(set(expected) - set(data["weights"]))
    if missing:
        raise damaged(f"weight {missing[0]!r} of the {algo.name} network is missing"
                      + (f", and {len(missing) - 1} more" if len(missing) > 1 else ""))


def acting_weight_shapes(algo_name: str, config: Any, n_vehicles: int) -> dict[str, tuple[int, ...]]:
    """The acting weights a checkpoint of ``algo_name`` (a :mod:`marl.config` algorithm) with
    ``config`` (its config object or dict) at N = ``n_vehicles`` holds, with their shapes:
    every one must be stored (:func:`load_checkpoint` refuses a file missing one)."""
    from marl.config import algorithm, config_from_dict

    algo = algorithm(algo_name)
    if isinstance(config, dict):
        config = config_from_dict(algo, config)
    with torch.device("meta"):  # shapes only: no memory, no initialisation, no random draw
        net = algo.build_net(config, n_vehicles, with_critic=False)
    return {k: tuple(v.shape) for k, v in net.acting_state_dict().items()}


def upgrade_checkpoint(path: str | Path) -> bool:
    """Rewrite a format-1 checkpoint (no hash) as format 2, the same weights with their content
    hash, after checking its fields, dtypes, shapes and config; True if it was rewritten (a
    format-2 file is verified and left as it is).

    Raises
    ------
    ConfigError
        The file cannot be read, or fails a check.
    """
    path = Path(path)
    try:
        data = torch.load(io.BytesIO(path.read_bytes()), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure means an unusable file
        raise ConfigError(f"checkpoint {path} cannot be read ({type(exc).__name__})") from None
    version = data.get("format_version") if isinstance(data, dict) else None
    if version == FORMAT_VERSION:
        load_checkpoint(path)
        return False
    if version != SHIPPED_FORMAT:
        raise ConfigError(f"checkpoint {path} has format version {version}, not 1")

    def damaged(what: str) -> ConfigError:
        return ConfigError(f"checkpoint {path} cannot be upgraded ({what}); re-train it")

    _check_fields(data, damaged)
    _check_config_and_shapes(data, damaged)
    write_payload(path, {**data, "format_version": FORMAT_VERSION})
    load_checkpoint(path)
    return True


if __name__ == "__main__":  # python -m marl.checkpoint FILE...: add the hash to format-1 files
    import sys

    try:
        for name in sys.argv[1:]:
            print(f"{name}: {'upgraded to format 2' if upgrade_checkpoint(name) else 'verified'}")
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
