"""docs/scripts/arithmetic_fingerprint.py: the per-operation hashes two processors compare."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "docs" / "scripts" / "arithmetic_fingerprint.py"
COMMITTED = ROOT / "docs" / "notes" / "arithmetic-fingerprint-amd-epyc.json"


def _module():
    spec = importlib.util.spec_from_file_location("arithmetic_fingerprint", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_compare_names_the_operations_that_differ(tmp_path: Path, capsys) -> None:
    mod = _module()
    ops = {"mm": "a", "exp": "b"}
    first = {"cpu": "one", "native": ops, "mkl_compatible": ops}
    second = {"cpu": "two", "native": ops, "mkl_compatible": {**ops, "mm": "c"}}
    for name, data in (("1.json", first), ("2.json", second)):
        (tmp_path / name).write_text(json.dumps(data))
    assert mod.compare(str(tmp_path / "1.json"), str(tmp_path / "2.json")) == 0
    out = capsys.readouterr().out
    assert "native                         same" in out
    assert "mkl_compatible                 differ: mm" in out


def test_the_committed_fingerprint_holds_every_operation_and_setting() -> None:
    """The AMD file a later run is compared with covers what the script now hashes."""
    import torch

    mod = _module()
    committed = json.loads(COMMITTED.read_text())
    assert set(mod.SETTINGS) <= set(committed)
    threads = torch.get_num_threads()
    try:
        assert set(mod.fingerprint()) == set(committed["native"])
    finally:
        torch.set_num_threads(threads)  # fingerprint() runs on one, as the short training
