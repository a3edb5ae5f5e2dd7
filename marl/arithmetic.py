"""Float32 training and float64 evaluation arithmetic that give a seed the same numbers on
every processor measured: an AMD EPYC (AVX2) and an Intel Xeon with AVX-512.

PyTorch's CPU kernels pick their instructions by processor: MKL's float32 products, PyTorch's
own AVX-512 or AVX2 loops, numpy's OpenBLAS and its elementwise loops, and PyTorch's float32
square root, which rounds about a fifth of its results to a neighbour, otherwise on an Intel
and an AMD processor. A sampled training run carries any last bit into other weights
(``tests/test_marl/test_marl_losses.py`` pins one hash per processor family in the default, ``native``,
mode).

``portable`` starts a process with :func:`portable_env`: MKL's conditional numerical
reproducibility branch ``COMPATIBLE`` (``MKL_CBWR``) and, on a processor with AVX2 and FMA, the
AVX2 kernels of PyTorch (``ATEN_CPU_CAPABILITY``), of numpy's OpenBLAS
(``OPENBLAS_CORETYPE=Haswell``) and of numpy's own loops (its AVX-512 targets disabled); in such
a process the learners take a correctly rounded square root (:func:`marl.layers.sqrt`). The
short trainings then give one hash on both processors (``tests/test_marl/test_arithmetic.py``), and so do
numpy's linear algebra, which the MPC controllers use, and its elementwise functions
(:mod:`marl.arithmetic_fingerprint`). MKL's branch alone held the weights across
instruction sets on one processor, but not from the Xeon to the EPYC.

Each library reads its setting once, when the process starts or at its first use, so it must be
in a process's environment from its start: the executors start such processes with it
(:func:`benchmark.executors.map_jobs`'s ``env``), and a training job checks it
(:func:`require`). ``reproduce`` and ``sensitivity`` evaluate in it too: MKL's kernels also
round the sampled policies' actions. It costs training time (``cacc-bench perf`` with
:func:`portable_env` in the environment, ``docs/reproduction.md``).
"""

from __future__ import annotations

import functools
import os

from infra.errors import ConfigError

#: ``native``: the fastest kernels for this processor; ``portable``: :func:`portable_env`.
ARITHMETIC_MODES: tuple[str, ...] = ("native", "portable")

#: What a process's environment holds from its start for ``portable`` arithmetic, on every
#: processor (:func:`portable_env` adds the AVX2 kernels where the processor has them).
PORTABLE_ENV: dict[str, str] = {"MKL_CBWR": "COMPATIBLE"}

#: The AVX2 kernels ``portable`` asks for on a processor with AVX2 and FMA (numpy's AVX-512
#: targets, which differ between numpy versions, are added by :func:`portable_env`).
AVX2_ENV: dict[str, str] = {"ATEN_CPU_CAPABILITY": "avx2", "OPENBLAS_CORETYPE": "Haswell"}


@functools.cache
def portable_env() -> dict[str, str]:
    """The environment of a ``portable`` process on this processor: :data:`PORTABLE_ENV`, and
    with AVX2 and FMA, :data:`AVX2_ENV` plus ``NPY_DISABLE_CPU_FEATURES`` naming numpy's
    AVX-512 targets (on a processor without AVX2, forcing these kernels would fault)."""
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:  # another numpy layout: no AVX2 pins, only MKL's branch
        return dict(PORTABLE_ENV)
    if not (__cpu_features__.get("AVX2") and __cpu_features__.get("FMA3")):
        return dict(PORTABLE_ENV)
    avx512 = [t for t in __cpu_dispatch__ if t.startswith(("AVX512", "X86_V4"))]
    extra = {"NPY_DISABLE_CPU_FEATURES": " ".join(avx512)} if avx512 else {}
    return {**PORTABLE_ENV, **AVX2_ENV, **extra}


#: The key a checkpoint's ``curve_summary`` holds (1.0) when its run trained portably; absent
#: for native runs, so checkpoints trained before the mode existed read as native.
SUMMARY_KEY = "portable_arithmetic"


def check_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`ARITHMETIC_MODES`, else a ConfigError."""
    if mode not in ARITHMETIC_MODES:
        raise ConfigError(f"--arithmetic {mode!r}: expected one of {', '.join(ARITHMETIC_MODES)}")
    return mode


def process_env(mode: str) -> dict[str, str]:
    """The environment variables a process of ``mode`` is started with."""
    return dict(portable_env()) if check_mode(mode) == "portable" else {}


def current() -> str:
    """The mode this process's environment says (``portable`` when it holds
    :func:`portable_env`)."""
    portable = all(os.environ.get(k) == v for k, v in portable_env().items())
    return "portable" if portable else "native"


def require(mode: str) -> None:
    """Refuse (ConfigError) to train ``mode`` in a process whose environment says otherwise: a
    portable run in a process started without all of :func:`portable_env` (the libraries have
    already chosen their kernels), or a native run in a process started with all of it (its
    checkpoint would say native of portable numbers). A process holding only part of it (a
    machine that sets ``OPENBLAS_CORETYPE`` for every process, say) trains natively: native
    arithmetic is whatever kernels the process's own environment selects."""
    env = portable_env()
    held = [k for k, v in env.items() if os.environ.get(k) == v]
    if current() != check_mode(mode):
        shown = " ".join(f"{k}={v!r}" if " " in v else f"{k}={v}" for k, v in env.items())
        state = "portable" if len(held) == len(env) else "partly portable" if held else "native"
        raise ConfigError(
            f"a {mode} training run in a {state} process: the libraries read {shown} when a "
            "process starts; run it through the executors (cacc-bench train/reproduce "
            f"--arithmetic), or start the process with{'' if mode == 'portable' else 'out'} "
            "those variables")


def summary(mode: str) -> dict[str, float]:
    """The checkpoint's ``curve_summary`` entry that records ``mode``."""
    return {SUMMARY_KEY: 1.0} if check_mode(mode) == "portable" else {}


def of_summary(curve_summary: dict[str, float]) -> str:
    """The mode a checkpoint's ``curve_summary`` records."""
    return "portable" if curve_summary.get(SUMMARY_KEY, 0.0) == 1.0 else "native"
