"""Hashes of each float32 operation the learners use (and of the float64 linear algebra of
numpy's OpenBLAS, which the MPC controllers use) under each arithmetic setting, on this CPU.

Run it on two processors and compare the JSON files: an operation whose hash differs under the
same setting is one whose rounding depends on the processor (docs/notes/issue34-clean-clone.md,
"Portable arithmetic on an AMD EPYC"). From the repository root:

    .venv/bin/python -m marl.arithmetic_fingerprint > fingerprint-CPU.json
    .venv/bin/python -m marl.arithmetic_fingerprint --compare a.json b.json

``--portable-training`` prints the tests' short-training hashes (:func:`weights_hash`) in
portable processes; ``--ops`` leaves out the short training (any PyTorch, the project's other
dependencies not installed); ``--numpy`` hashes only numpy's operations, under
:data:`NUMPY_SETTINGS`, with no PyTorch (or another PyTorch) installed. The same library
versions give hashes comparable with a full run's.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from marl import arithmetic

if TYPE_CHECKING:
    import numpy as np

#: Settings, each read by MKL or PyTorch when a process starts (so each runs in its own).
SETTINGS: dict[str, dict[str, str]] = {
    "native": {},
    "mkl_compatible": {"MKL_CBWR": "COMPATIBLE"},
    "mkl_compatible+aten_avx2": {"MKL_CBWR": "COMPATIBLE", "ATEN_CPU_CAPABILITY": "avx2"},
    "mkl_compatible+aten_default": {"MKL_CBWR": "COMPATIBLE", "ATEN_CPU_CAPABILITY": "default"},
    "mkl_avx2": {"MKL_CBWR": "AVX2"},
    "mkl_avx2+aten_avx2": {"MKL_CBWR": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"},
    "mkl_sse4_2": {"MKL_CBWR": "SSE4_2"},
    "mkl_compatible+openblas_haswell": {"MKL_CBWR": "COMPATIBLE",
                                        "OPENBLAS_CORETYPE": "Haswell"},
}

#: Settings read by numpy and its OpenBLAS at import, for ``--numpy``.
NUMPY_SETTINGS: dict[str, dict[str, str]] = {
    "native": {},
    "openblas_haswell": {"OPENBLAS_CORETYPE": "Haswell"},
    "numpy_x86_v3": {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"},
    "openblas_haswell+numpy_x86_v3": {"OPENBLAS_CORETYPE": "Haswell",
                                      "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"},
}

#: Shapes of the float32 inputs, drawn in this order from the generator before numpy's own
#: operations' (``--numpy`` draws and drops them, so its numpy inputs are the full run's).
TORCH_INPUT_SHAPES: tuple[tuple[int, ...], ...] = (
    (64, 15), (15, 64), (8, 240, 32), (8, 32, 64), (8, 1, 64), (4096,), (64, 64),
    (64, 64), (64, 64), (64, 64))

#: The algorithms of the short training (:func:`weights_hash`).
PINNED_ALGOS: tuple[str, ...] = ("bdc", "dial", "ia2c")


def _hash(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


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


def weights_hash(name: str) -> tuple[str, str]:
    """The weights hash after the short training the tests pin (three batches of 4 followers
    on slowdown-v1, seed 3, ``advantage_norm``, one thread) of ``name`` in this process, and
    the process's arithmetic mode (top level: the executors' worker processes run it)."""
    import torch

    from marl.a2c import Trainer
    from marl.config import algorithm

    torch.set_num_threads(1)
    a = algorithm(name)
    trainer = Trainer(a, a.config_cls(advantage_norm=True), "slowdown-v1", 4, 3)
    trainer.runs[0].total_steps = 3000
    for _ in range(3):
        trainer.run_batch()
    blob = b"".join(p.detach().numpy().tobytes() for p in trainer.net.parameters())
    return _hash(blob), arithmetic.current()


def fingerprint(training: bool = True) -> dict[str, str]:
    """Hashes of fixed-input float32 operations in this process (one thread); with
    ``training``, also of the short training (:func:`weights_hash`, needs the project's
    dependencies)."""
    import numpy as np
    import torch

    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)  # only for the sampling operations themselves
    rng = np.random.default_rng(0)  # inputs from numpy: torch's own normal_ depends on its kernels
    a, b, x3, w3, bias3, big, p0, *grads = (
        torch.from_numpy(rng.standard_normal(s).astype(np.float32)) for s in TORCH_INPUT_SHAPES)
    big = big * 4
    out = {
        "mm_64x15x64": torch.mm(a, b),
        "addmm_240x32x64": torch.addmm(bias3[0, 0], x3[0], w3[0]),
        "bmm_8x240x32x64": torch.bmm(x3, w3),
        "baddbmm_8x240x32x64": torch.baddbmm(bias3, x3, w3),
        "linear_240x32x64": torch.nn.functional.linear(x3[0], w3[0].T, bias3[0, 0]),
        "qr_64x15": torch.linalg.qr(a)[0],
        "exp": torch.exp(big), "log": torch.log(big.abs() + 1e-3), "tanh": torch.tanh(big),
        "sigmoid": torch.sigmoid(big), "sqrt": torch.sqrt(big.abs()),
        "softmax": torch.softmax(big.view(-1, 4), -1),
        "log_softmax": torch.log_softmax(big.view(-1, 4), -1),
        "pow_1.5": big.abs().pow(1.5), "div": big / (big.abs() + 1.0),
        "sum_4096": big.sum().reshape(1), "mean_rows": big.view(64, 64).mean(1),
        "multinomial": torch.multinomial(torch.softmax(big.view(-1, 4), -1), 1, generator=g),
        "normal": torch.empty(4096).normal_(generator=g),
    }
    p = torch.nn.Parameter(p0)
    opt = torch.optim.RMSprop([p], lr=1e-3, alpha=0.99, eps=1e-5)
    for grad in grads:
        p.grad = grad
        opt.step()
    out["rmsprop_3_steps"] = p
    res = {k: _hash(v.detach().contiguous().numpy().tobytes()) for k, v in out.items()}
    res.update(numpy_hashes(rng))
    if training:
        res["short_training_bdc"] = weights_hash("bdc")[0]
    res["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    return res


def numpy_hashes(rng: np.random.Generator) -> dict[str, str]:
    """Hashes of numpy's float64 elementwise functions and linear algebra, inputs from ``rng``
    after the float32 inputs (:data:`TORCH_INPUT_SHAPES`)."""
    import numpy as np

    grid = np.linspace(-4, 4, 100_001)
    res = {"numpy_cos_sin_exp_f64": _hash(b"".join(f(grid).tobytes()
                                                   for f in (np.cos, np.sin, np.exp)))}
    # numpy's OpenBLAS picks its kernels by processor (OPENBLAS_CORETYPE): the MPC
    # controllers' float64 linear algebra goes through it
    m64 = rng.standard_normal((96, 96))
    spd = m64 @ m64.T + 96 * np.eye(96)
    blas = {"numpy_matmul_f64": m64 @ m64.T, "numpy_solve_f64": np.linalg.solve(spd, m64[:, :8]),
            "numpy_cholesky_f64": np.linalg.cholesky(spd)}
    res.update({k: _hash(v.tobytes()) for k, v in blas.items()})
    return res


def _openblas_core() -> str:
    """The kernel family numpy's OpenBLAS runs (``OPENBLAS_CORETYPE`` forces one)."""
    import ctypes
    import glob

    import numpy as np

    for lib in glob.glob(os.path.join(os.path.dirname(np.__file__), os.pardir, "numpy.libs",
                                      "libscipy_openblas*")):
        for name in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename"):
            fn = getattr(ctypes.CDLL(lib), name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                return str(fn().decode())
    return "unknown"


def numpy_fingerprint() -> dict[str, str]:
    """:func:`numpy_hashes` with its inputs drawn as :func:`fingerprint` draws them."""
    import numpy as np

    rng = np.random.default_rng(0)
    for shape in TORCH_INPUT_SHAPES:
        rng.standard_normal(shape).astype(np.float32)
    res = numpy_hashes(rng)
    res["numpy"] = np.__version__
    res["openblas_core"] = _openblas_core()
    return res


#: Modes of a run: what each process computes, under which settings.
MODES: dict[str, tuple[str, dict[str, dict[str, str]]]] = {
    "all": ("--one", SETTINGS),
    "ops": ("--ops-one", SETTINGS),  # no short training: any PyTorch, project not installed
    "numpy": ("--numpy-one", NUMPY_SETTINGS),  # no PyTorch
}


def _in_process(args: list[str], env: dict[str, str]) -> object:
    """What this module prints with ``args`` in a fresh process started with ``env`` added."""
    proc = subprocess.run([sys.executable, "-m", __spec__.name, *args],
                          env={**os.environ, **env}, capture_output=True, text=True, check=True,
                          cwd=Path(__file__).resolve().parents[1])
    return json.loads(proc.stdout)


def _machine() -> dict[str, object]:
    return {"cpu": cpuinfo("model name") or platform.processor(), "vendor": cpuinfo("vendor_id")}


def run_all(mode: str = "all") -> dict[str, object]:
    """Every setting of ``mode`` (:data:`MODES`), each in a fresh process."""
    flag, settings = MODES[mode]
    results = _machine()
    if mode != "numpy":
        import torch

        results["torch"] = torch.__version__
    for name, extra in settings.items():
        results[name] = _in_process([flag], extra)
    return results


def portable_training() -> dict[str, object]:
    """The short trainings (:data:`PINNED_ALGOS`), each in a fresh portable process
    (:func:`marl.arithmetic.portable_env`): the hashes the tests' ``PORTABLE_PINNED`` holds."""
    env = arithmetic.portable_env()
    results = {**_machine(), "env": env}
    for algo in PINNED_ALGOS:
        results[algo] = _in_process(["--training-one", algo], env)
    return results


def compare(first: str, second: str) -> int:
    """Print the operations whose hash differs between two fingerprint files, per setting."""
    with open(first) as f1, open(second) as f2:
        a, b = json.load(f1), json.load(f2)
    print(f"{first}: {a['cpu']}\n{second}: {b['cpu']}")
    for name in {**SETTINGS, **NUMPY_SETTINGS}:
        if name not in a or name not in b:
            continue
        diff = [op for op in a[name] if op in b[name] and a[name][op] != b[name][op]]
        print(f"{name:30s} {'same' if not diff else 'differ: ' + ', '.join(diff)}")
    return 0


if __name__ == "__main__":
    args = sys.argv[1:]
    if args in (["--one"], ["--ops-one"]):
        print(json.dumps(fingerprint(training=args == ["--one"])))
    elif args[:1] == ["--training-one"] and len(args) == 2:
        import torch

        print(json.dumps([*weights_hash(args[1]), torch.__version__]))
    elif args == ["--numpy-one"]:
        print(json.dumps(numpy_fingerprint()))
    elif args == ["--portable-training"]:
        print(json.dumps(portable_training(), indent=1))
    elif args in ([], ["--ops"], ["--numpy"]):
        print(json.dumps(run_all(args[0][2:] if args else "all"), indent=1))
    elif args[:1] == ["--compare"] and len(args) == 3:
        sys.exit(compare(args[1], args[2]))
    else:
        sys.exit("usage: python -m marl.arithmetic_fingerprint [--ops | --numpy | "
                 "--portable-training | --compare FIRST SECOND]")
