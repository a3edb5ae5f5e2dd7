"""Executors of a sweep: ``serial``, ``process`` (a local pool) and ``ray`` (a cluster).

Every executor runs :func:`benchmark.suite.execute_batch` on the same batches of keys and yields
the records as batches finish; the caller (one process) writes them to the store, so there is a single writer.
Each run depends only on its key, so all executors give identical numbers.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from benchmark.suite import RunKey, batch_keys, execute_batch
from envs.errors import ConfigError

EXECUTORS = ("serial", "process", "ray")


def add_executor_options(parser: Any, default: str = "serial") -> None:
    """``--executor``, ``--workers`` and ``--ray-address``, the same on every command."""
    parser.add_argument("--executor", choices=EXECUTORS, default=default,
                        help="serial, process or ray (default: %(default)s)")
    parser.add_argument("--workers", type=int, default=2,
                        help="processes or Ray CPUs (default 2)")
    parser.add_argument("--ray-address", default=None, help="attach to this Ray cluster")


#: ``--executor auto`` (the default of ``cacc-bench run``): see :func:`resolve_executor`.
AUTO = "auto"


#: Learned-policy episodes from which ``auto`` runs a sweep's policies on a process pool: they
#: run batched, so fewer cost less than the workers' start (see :func:`resolve_executor`).
POOL_POLICY_EPISODES = 400


def resolve_executor(keys: Sequence[RunKey], executor: str, workers: int) -> str:
    """The executor ``auto`` stands for: ``process`` when more than one worker is allowed, the
    sweep holds more than one batch, and it holds an optimiser run (family ``mpc``, worth a
    worker's start-up of a few seconds) or at least :data:`POOL_POLICY_EPISODES` learned-policy
    episodes; else ``serial``. Any other executor is returned as given. The choice never
    changes a number, only the wall time (every executor gives identical records)."""
    if executor != AUTO:
        return executor
    from controllers.registry import resolve

    family = {name: resolve(name).family for name in {k.name for k in keys}}
    policy_runs = sum(family[k.name] == "marl" for k in keys)
    heavy = "mpc" in family.values() or policy_runs >= POOL_POLICY_EPISODES
    if workers > 1 and heavy and len(batch_keys(keys, workers)) > 1:
        return "process"
    return "serial"


def _worker_env() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")


def _worker_init(parent_pid: int) -> None:
    """Start of a process-executor worker: one thread per library, interrupts that no solver
    swallows, and death with the parent (whatever kills it, SIGKILL included)."""
    _worker_env()
    from envs.interrupt import install

    install()
    die_with_parent(parent_pid)


def die_with_parent(parent_pid: int) -> None:
    """End this process when ``parent_pid`` ends: the kernel's parent-death signal on Linux,
    a watchdog thread elsewhere; at once if the parent is already gone."""
    import sys
    import threading
    import time

    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    else:
        def watch() -> None:
            while os.getppid() == parent_pid:
                time.sleep(0.5)
            os._exit(1)

        threading.Thread(target=watch, daemon=True).start()
    if os.getppid() != parent_pid:
        os._exit(1)


def _run(args: tuple[list[RunKey], bool]) -> list[dict]:
    _worker_env()
    return execute_batch(*args)


def run_batches(
    keys: Sequence[RunKey],
    executor: str = "serial",
    workers: int = 1,
    ray_address: str | None = None,
    keep_trajectory: bool = False,
) -> Iterator[list[dict]]:
    """Yield the records of each batch of :func:`batch_keys` as it finishes (any order)."""
    batches = [(b, keep_trajectory) for b in batch_keys(keys, workers)]
    yield from map_jobs(_run, batches, executor, workers, ray_address)


def run_keys(
    keys: Sequence[RunKey],
    executor: str = "serial",
    workers: int = 1,
    ray_address: str | None = None,
    keep_trajectory: bool = False,
) -> Iterator[dict]:
    """Yield the record of every key as its batch finishes (any order; :func:`batch_keys`)."""
    for records in run_batches(keys, executor, workers, ray_address, keep_trajectory):
        yield from records


def map_jobs(
    fn: Callable[[Any], Any],
    items: Sequence[Any],
    executor: str = "serial",
    workers: int = 1,
    ray_address: str | None = None,
) -> Iterator[Any]:
    """Apply a top-level (picklable) function to every item on an executor; yield the results
    as they finish (any order). Sweeps and multi-seed training both run through here."""
    if executor not in EXECUTORS:
        raise ConfigError(f"unknown executor {executor!r}; valid executors are: {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    if not items:
        return
    if executor == "serial":
        for item in items:
            yield fn(item)
    elif executor == "process":
        yield from _process(fn, items, workers)
    else:
        yield from _ray(fn, items, workers, ray_address)


def _process(fn: Callable[[Any], Any], items: Sequence[Any], workers: int) -> Iterator[Any]:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    ctx = mp.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                               initargs=(os.getpid(),))
    try:
        futures = [pool.submit(fn, item) for item in items]
        for fut in as_completed(futures):
            yield fut.result()
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def ensure_ray(workers: int, address: str | None = None) -> object:
    """Attach to ``address`` / ``RAY_ADDRESS`` if given, else start a local instance on loopback.

    The local instance has no dashboard, no usage statistics and token authentication off (it
    only listens on 127.0.0.1).
    """
    try:
        import ray
    except ImportError:
        raise ConfigError(
            "the ray executor needs Ray: install with `pip install -e '.[ray]'`"
        ) from None
    if ray.is_initialized():
        return ray
    address = address or os.environ.get("RAY_ADDRESS")
    if address:
        ray.init(address=address, log_to_driver=False)
    else:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")
        ray.init(
            num_cpus=workers,
            include_dashboard=False,
            _node_ip_address="127.0.0.1",
            log_to_driver=False,
            configure_logging=False,
        )
    return ray


def _ray(fn: Callable[[Any], Any], items: Sequence[Any], workers: int,
         address: str | None) -> Iterator[Any]:
    ray = ensure_ray(workers, address)
    remote = ray.remote(num_cpus=1)(fn)  # type: ignore[attr-defined]
    pending = [remote.remote(item) for item in items]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)  # type: ignore[attr-defined]
            for ref in done:
                yield ray.get(ref)  # type: ignore[attr-defined]
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)  # type: ignore[attr-defined]
