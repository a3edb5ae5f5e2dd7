"""The short training whose weights the tests pin (native and portable arithmetic)."""

from __future__ import annotations

import hashlib

import torch

from marl import arithmetic

#: Weights after three batches of 4 followers on slowdown-v1, seed 3, advantage_norm (torch
#: 2.13 CPU, one thread; :func:`weights_hash`) with native arithmetic: one hash per family of
#: CPU kernels measured, since MKL rounds float32 products differently between processors and
#: sampled training turns the last bit into other weights. Measured on an AMD EPYC with AVX-512
#: (first) and on an Intel Xeon with AVX-512 and AMX (second; both say AVX512 to
#: `torch.backends.cpu.get_cpu_capability()`). On another CPU, add its hash after checking the
#: rest of the suite passes there. A change in the learner's arithmetic changes every hash: if
#: it is intended, say why in the commit and update the pins.
NATIVE_PINNED = {
    "ia2c": ("49697009249f3d40", "3a9844e581e84a20"),
    "bdc": ("0f5895d5a28a7600", "7e66330e3087ec38"),
    "dial": ("b6fe515744bb9855", "b38960411574c8a0"),
}

#: The same trainings with portable arithmetic: one hash per algorithm. Measured on the Intel
#: Xeon; Intel documents MKL's COMPATIBLE branch as giving the same results on its and
#: compatible processors, so an AMD processor must give the same hashes. They hold with MKL
#: limited to AVX2, AVX or SSE4.2 and PyTorch's kernels to AVX2 (what a processor without
#: AVX-512 runs), not with PyTorch's scalar kernels (``ATEN_CPU_CAPABILITY=default``).
PORTABLE_PINNED = {
    "ia2c": "685e471a8fcad903",
    "bdc": "8da992d5bd3cac4f",
    "dial": "0cab3ab54c7d5b11",
}


def weights_hash(name: str) -> tuple[str, str]:
    """The short-training weights hash of ``name`` in this process, and the process's mode
    (top level: the executors' worker processes run it)."""
    from marl.a2c import Trainer
    from marl.config import algorithm

    torch.set_num_threads(1)
    a = algorithm(name)
    trainer = Trainer(a, a.config_cls(advantage_norm=True), "slowdown-v1", 4, 3)
    trainer.runs[0].total_steps = 3000
    for _ in range(3):
        trainer.run_batch()
    blob = b"".join(p.detach().numpy().tobytes() for p in trainer.net.parameters())
    return hashlib.sha256(blob).hexdigest()[:16], arithmetic.current()


def weights_hash_and_kernels(name: str) -> tuple[str, str, str]:
    """:func:`weights_hash` and the instruction set PyTorch's own kernels used in this process."""
    digest, mode = weights_hash(name)
    return digest, mode, torch.backends.cpu.get_cpu_capability()
