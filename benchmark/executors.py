"""Executors of a sweep: ``serial``, ``process`` (a local pool) and ``ray`` (a cluster).

Every executor runs :func:`benchmark.suite.execute_run` on the same keys and yields the records
as runs finish; the caller (one process) writes them to the store, so there is a single writer.
Each run depends only on its key, so all executors give identical numbers.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence

from benchmark.suite import RunKey, execute_run
from envs.errors import ConfigError

EXECUTORS = ("serial", "process", "ray")


def _worker_init() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")


def _run(args: tuple[RunKey, bool]) -> dict:
    _worker_init()
    return execute_run(*args)


def run_keys(
    keys: Sequence[tuple[RunKey, bool]],
    executor: str = "serial",
    workers: int = 1,
    ray_address: str | None = None,
) -> Iterator[dict]:
    """Yield the record of every ``(key, keep_trajectory)`` as it finishes (any order)."""
    if executor not in EXECUTORS:
        raise ConfigError(f"unknown executor {executor!r}; valid executors are: {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    if not keys:
        return
    if executor == "serial":
        for item in keys:
            yield execute_run(*item)
    elif executor == "process":
        yield from _process(keys, workers)
    else:
        yield from _ray(keys, workers, ray_address)


def _process(keys: Sequence[tuple[RunKey, bool]], workers: int) -> Iterator[dict]:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    ctx = mp.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init)
    try:
        futures = [pool.submit(_run, item) for item in keys]
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


def _ray(keys: Sequence[tuple[RunKey, bool]], workers: int, address: str | None) -> Iterator[dict]:
    ray = ensure_ray(workers, address)
    remote = ray.remote(num_cpus=1)(_run)  # type: ignore[attr-defined]
    pending = [remote.remote(item) for item in keys]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)  # type: ignore[attr-defined]
            for ref in done:
                yield ray.get(ref)  # type: ignore[attr-defined]
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)  # type: ignore[attr-defined]
