"""Float32 training arithmetic that gives a seed the same weights whatever instruction sets the
libraries use, on the processors measured (not between an Intel and an AMD one).

PyTorch's CPU products go through Intel MKL, which picks its kernels by processor: an Intel
Xeon and an AMD EPYC round some float32 products differently, and a sampled training run
carries that last bit into other weights (``tests/test_marl_losses.py`` pins one hash per
processor family in the default, ``native``, mode).

``portable`` sets MKL's conditional numerical reproducibility branch ``COMPATIBLE`` (the
environment variable ``MKL_CBWR``). Intel documents it as giving the same results on Intel and
Intel-compatible processors. Measured, it gives one processor the same weights whatever
instruction sets MKL and PyTorch use (an Intel Xeon with AVX-512, or with both limited to AVX2,
AVX or SSE4.2 kernels; an AMD EPYC without AVX-512, with MKL limited to SSE4.2), but the Xeon's
and the EPYC's weights differ, and PyTorch's scalar kernels (no AVX2) give others again
(``tests/test_arithmetic.py`` pins one hash per vendor;
``docs/scripts/arithmetic_fingerprint.py`` compares operations between processors). MKL reads it
once, at its first product, so it must be in a process's environment before that: the executors
start such processes with it (:func:`benchmark.executors.map_jobs`'s ``env``), and a training
job checks it (:func:`require`). ``reproduce`` and ``sensitivity`` evaluate in it too: MKL's
kernels also round the sampled policies' actions. It costs time: 1.2 to 2.3 times the native
training time on the two processors measured (``cacc-bench perf`` with ``MKL_CBWR=COMPATIBLE``
in the environment, ``docs/reproduction.md``).
"""

from __future__ import annotations

import os

from envs.errors import ConfigError

#: ``native``: MKL's fastest kernels for this processor; ``portable``: :data:`PORTABLE_ENV`.
ARITHMETIC_MODES: tuple[str, ...] = ("native", "portable")

#: What a process's environment holds from its start for ``portable`` arithmetic.
PORTABLE_ENV: dict[str, str] = {"MKL_CBWR": "COMPATIBLE"}

#: The key a checkpoint's ``curve_summary`` holds (1.0) when its run trained portably; absent
#: for native runs, so checkpoints trained before the mode existed read as native.
SUMMARY_KEY = "portable_arithmetic"


def check_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`ARITHMETIC_MODES`, else a ConfigError."""
    if mode not in ARITHMETIC_MODES:
        raise ConfigError(f"--arithmetic {mode!r}: expected one of {', '.join(ARITHMETIC_MODES)}")
    return mode


def process_env(mode: str) -> dict[str, str]:
    """The environment variables a training process of ``mode`` is started with."""
    return dict(PORTABLE_ENV) if check_mode(mode) == "portable" else {}


def current() -> str:
    """The mode this process's environment says (``portable`` when it holds
    :data:`PORTABLE_ENV`)."""
    portable = all(os.environ.get(k) == v for k, v in PORTABLE_ENV.items())
    return "portable" if portable else "native"


def require(mode: str) -> None:
    """Refuse (ConfigError) to train ``mode`` in a process whose environment says otherwise: a
    portable run in a process started without :data:`PORTABLE_ENV` (MKL has already chosen its
    kernels), or a native run in a portable process."""
    if current() != check_mode(mode):
        env = " ".join(f"{k}={v}" for k, v in PORTABLE_ENV.items())
        raise ConfigError(
            f"a {mode} training run in a {current()} process: MKL reads {env} when a process "
            "starts; run it through the executors (cacc-bench train/reproduce --arithmetic), "
            f"or start the process with{'' if mode == 'portable' else 'out'} {env}")


def summary(mode: str) -> dict[str, float]:
    """The checkpoint's ``curve_summary`` entry that records ``mode``."""
    return {SUMMARY_KEY: 1.0} if check_mode(mode) == "portable" else {}


def of_summary(curve_summary: dict[str, float]) -> str:
    """The mode a checkpoint's ``curve_summary`` records."""
    return "portable" if curve_summary.get(SUMMARY_KEY, 0.0) == 1.0 else "native"
