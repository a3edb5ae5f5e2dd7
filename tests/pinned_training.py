"""The short training whose weights the tests pin (native and portable arithmetic)."""

from __future__ import annotations

import hashlib

import torch

from marl import arithmetic

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

#: The same trainings with portable arithmetic (``MKL_CBWR=COMPATIBLE``): one hash per algorithm
#: and processor vendor (``vendor_id`` in /proc/cpuinfo). Within a vendor they hold whatever
#: instruction sets MKL and PyTorch use (Intel Xeon: AVX-512 or forced AVX2, AVX, SSE4.2; AMD
#: EPYC: its AVX2 kernels, MKL forced to SSE4.2), but not between vendors, although Intel
#: documents the branch as giving the same results on its and compatible processors; not with
#: PyTorch's scalar kernels (``ATEN_CPU_CAPABILITY=default``) either.
PORTABLE_PINNED: dict[str, dict[str, str]] = {
    "GenuineIntel": {"ia2c": "685e471a8fcad903", "bdc": "8da992d5bd3cac4f",
                     "dial": "0cab3ab54c7d5b11"},
    "AuthenticAMD": {"ia2c": "28cda15b6b979309", "bdc": "8003453cd04d269f",
                     "dial": "1a146437cb072874"},
}

#: The algorithms of the short training.
PINNED_ALGOS: tuple[str, ...] = ("bdc", "dial", "ia2c")


def cpuinfo(field: str) -> str:
    """The first ``field`` of /proc/cpuinfo (``vendor_id``, ``model name``), or "" where the
    file does not say."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(field):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def cpu_vendor() -> str:
    """This processor's ``vendor_id``, or ""."""
    return cpuinfo("vendor_id")


def portable_pins() -> dict[str, str]:
    """The portable hashes pinned for this processor's vendor (a skip where none are: measure
    them with :func:`weights_hash` in a portable process, then add them)."""
    import pytest

    vendor = cpu_vendor()
    if vendor not in PORTABLE_PINNED:
        pytest.skip(f"no portable weights hashes pinned for processor vendor {vendor!r}")
    return PORTABLE_PINNED[vendor]


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
