"""marl/arithmetic_fingerprint.py: the per-operation hashes two processors compare."""

from __future__ import annotations

import json
from pathlib import Path

from marl import arithmetic_fingerprint as mod

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = ROOT / "docs" / "notes" / "arithmetic-fingerprint-amd-epyc.json"


def test_compare_names_the_operations_that_differ(tmp_path: Path, capsys) -> None:
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

    committed = json.loads(COMMITTED.read_text())
    assert set(mod.SETTINGS) <= set(committed)
    threads = torch.get_num_threads()
    try:
        assert set(mod.fingerprint()) == set(committed["native"])
    finally:
        torch.set_num_threads(threads)  # fingerprint() runs on one, as the short training


#: numpy's float64 hashes in a portable process (``--numpy-one`` under
#: :func:`marl.arithmetic.portable_env`), per numpy version: equal on an AMD EPYC (AVX2) and an
#: Intel Xeon with AVX-512 (natively, the Xeon's solve, Cholesky and elementwise hashes differ;
#: docs/notes/issue34-clean-clone.md).
PORTABLE_NUMPY_PINNED: dict[str, dict[str, str]] = {
    "2.4.6": {"numpy_cos_sin_exp_f64": "1efd5e363418e2e6", "numpy_matmul_f64": "c9bcb38000ec25a2",
              "numpy_solve_f64": "dec89aaf4f1ff9cb", "numpy_cholesky_f64": "4eca5d6d730d4552"},
}


def test_portable_numpy_arithmetic_is_pinned_across_processors() -> None:
    """The MPC controllers' float64 linear algebra (numpy's OpenBLAS) and numpy's elementwise
    functions give the pinned hashes in a portable process, on AVX2 kernels."""
    import os
    import subprocess
    import sys

    import numpy as np
    import pytest

    from marl.arithmetic import portable_env

    env = portable_env()
    if "OPENBLAS_CORETYPE" not in env:
        pytest.skip("no AVX2 and FMA: portable arithmetic pins no numpy kernels here")
    pins = PORTABLE_NUMPY_PINNED.get(np.__version__)
    if pins is None:
        pytest.skip(f"numpy {np.__version__}: no hashes pinned (run --numpy-one portably on two "
                    "processors and add them)")
    proc = subprocess.run([sys.executable, "-m", mod.__name__, "--numpy-one"],
                          capture_output=True, text=True, check=True, env={**os.environ, **env})
    got = json.loads(proc.stdout)
    assert got["openblas_core"] == "Haswell"
    assert {k: got[k] for k in pins} == pins
