"""The short training whose weights the tests pin (native and portable arithmetic)."""

from __future__ import annotations

import torch

from marl import arithmetic
from marl.arithmetic_fingerprint import weights_hash

#: Weights after three batches of 4 followers on slowdown-v1, seed 3, advantage_norm (torch
#: 2.13 CPU, one thread; :func:`weights_hash`) with native arithmetic: one hash per family of
#: CPU kernels measured, since MKL rounds float32 products differently between processors and
#: sampled training turns the last bit into other weights. Measured on AMD EPYCs with and
#: without AVX-512 (first; the same hash) and on an Intel Xeon with AVX-512 and AMX (second).
#: On another CPU, add its hash after checking the rest of the suite passes there. A change in
#: the learner's arithmetic changes every hash: if it is intended, say why in the commit and
#: update the pins.
NATIVE_PINNED = {
    "ia2c": ("49697009249f3d40", "3a9844e581e84a20"),
    "bdc": ("0f5895d5a28a7600", "7e66330e3087ec38"),
    "dial": ("b6fe515744bb9855", "b38960411574c8a0"),
}

#: The same trainings with portable arithmetic (:func:`marl.arithmetic.portable_env`: MKL's
#: ``COMPATIBLE`` branch, PyTorch's and numpy's AVX2 kernels, the learners' correctly rounded
#: square root): one hash per algorithm on every processor with AVX2 and FMA. Measured equal on
#: an AMD EPYC (AVX2) and an Intel Xeon with AVX-512 and AMX (``python -m
#: marl.arithmetic_fingerprint --portable-training``,
#: docs/notes/portable-training-intel-xeon-avx512.json), with PyTorch 2.13 and 2.11. With MKL's branch alone they differed between the two vendors: PyTorch's
#: float32 square root rounds otherwise on each.
PORTABLE_PINNED: dict[str, str] = {"ia2c": "ca472a608caa50da", "bdc": "432410e073a6866a",
                                   "dial": "8c47229e1d724cda"}


def portable_pins() -> dict[str, str]:
    """The portable hashes (a skip on a processor without AVX2 and FMA, where portable
    arithmetic pins only MKL's branch and PyTorch runs its scalar kernels)."""
    import pytest

    if "ATEN_CPU_CAPABILITY" not in arithmetic.portable_env():
        pytest.skip("no AVX2 and FMA: no portable weights hashes pinned for such a processor")
    return PORTABLE_PINNED


def weights_hash_and_kernels(name: str) -> tuple[str, str, str]:
    """:func:`weights_hash` and the instruction set PyTorch's own kernels used in this process."""
    digest, mode = weights_hash(name)
    return digest, mode, torch.backends.cpu.get_cpu_capability()
