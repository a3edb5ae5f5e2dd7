"""Executors of a sweep: ``serial``, ``process`` (a local pool) and ``ray`` (a cluster).

Every executor runs :func:`benchmark.suite.execute_batch` on the same batches of keys and yields
the records as batches finish; the caller (one process) writes them to the store, so there is a single writer.
Each run depends only on its key, so all executors give identical numbers.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from benchmark.reaper import hand_over
from benchmark.suite import RunKey, batch_keys, execute_batch
from infra.errors import ConfigError

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


def _worker_main(conn: Any, parent_pid: int, env: dict[str, str] | None = None) -> None:
    """A process-executor worker: apply the jobs it receives on ``conn`` until told to stop,
    with ``env`` added to its environment before anything else runs.

    It started with SIGINT and SIGTERM blocked (the parent's mask while it starts workers), so a
    Ctrl-C sent to the whole process group during its start-up prints nothing. From here SIGINT
    is ignored (the parent decides and stops the workers) and SIGTERM ends it at once, silently;
    it dies with the parent, whatever kills it (SIGKILL included).
    """
    import signal

    os.environ.update(env or {})  # before any library reads it (MKL at its first product)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _SIGNALS)
    _worker_env()
    die_with_parent(parent_pid)
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        fn, item = job
        try:
            reply: tuple[str, Any] = ("ok", fn(item))
        except BaseException as exc:  # sent to the parent, which raises it
            reply = ("error", _portable(exc))
        try:
            conn.send(reply)
        except (OSError, ValueError):  # the parent went away
            return
        except Exception as exc:  # the result does not pickle: say so instead of dying
            conn.send(("error", _portable(exc)))


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it pickles, else a RuntimeError with its text; the worker's traceback is
    attached as ``__notes__`` (shown by the parent's traceback)."""
    import pickle
    import traceback

    text = "".join(traceback.format_exception(exc))
    try:
        pickle.dumps(exc)
    except Exception:
        exc = RuntimeError(f"{type(exc).__name__}: {exc}")
    exc.__notes__ = [f"in the worker process:\n{text}"]
    exc.__traceback__ = None
    return exc


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
    env: dict[str, str] | None = None,
) -> Iterator[list[dict]]:
    """Yield the records of each batch of :func:`batch_keys` as it finishes (any order), run in
    processes holding ``env`` from their start (:func:`map_jobs`)."""
    batches = [(b, keep_trajectory) for b in batch_keys(keys, workers)]
    yield from map_jobs(_run, batches, executor, workers, ray_address, env)


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
    env: dict[str, str] | None = None,
) -> Iterator[Any]:
    """Apply a top-level (picklable) function to every item on an executor; yield the results
    as they finish (any order). Sweeps and multi-seed training both run through here.

    ``env``: environment variables the function's processes hold from their start (process
    workers, Ray workers); ``serial`` with an ``env`` this process lacks runs the items in one
    worker process started with it (a library may have read the variable here already).
    """
    if executor not in EXECUTORS:
        raise ConfigError(f"unknown executor {executor!r}; valid executors are: {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    if not items:
        return
    env = dict(env or {})
    if executor == "serial" and any(os.environ.get(k) != v for k, v in env.items()):
        yield from _process(fn, items, 1, env)
    elif executor == "serial":
        for item in items:
            yield fn(item)
    elif executor == "process":
        yield from _process(fn, items, workers, env)
    else:
        yield from _ray(fn, items, workers, ray_address, env)


_SIGNALS = frozenset({2, 15})  # SIGINT, SIGTERM (numbers: the same on every POSIX system)

#: Seconds a worker told to stop may take before it is killed.
STOP_GRACE_S = 2.0


class WorkerDied(RuntimeError):
    """A worker of the process executor ended without answering (killed from outside)."""


class _Pool:
    """Spawned worker processes, each fed one job at a time through its own pipe.

    No threads and no queues shared between processes: the parent waits on the pipes and the
    processes' sentinels, so stopping is killing the processes and reaping them, and nothing can
    wait on a worker that is blocked (``concurrent.futures`` joined its manager thread at exit
    and hung after a second Ctrl-C).
    """

    def __init__(self, workers: int, env: dict[str, str] | None = None) -> None:
        self.procs: list[Any] = []
        self.conns: list[Any] = []
        _LIVE.add(self)
        import multiprocessing as mp
        import signal

        from infra.interrupt import held, raise_if_interrupted

        ctx = mp.get_context("spawn")
        # the workers inherit the blocked mask, so a Ctrl-C to the process group reaches none
        # of them before they ignore it; here a signal is recorded and raised after the start
        with held():
            from multiprocessing import resource_tracker

            # started first: starting it unblocks SIGINT and SIGTERM in this thread
            resource_tracker.ensure_running()
            block = hasattr(signal, "pthread_sigmask")
            old = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS) if block else None
            try:
                for _ in range(workers):
                    parent_end, child_end = ctx.Pipe()
                    proc = ctx.Process(target=_worker_main, args=(child_end, os.getpid(), env),
                                       daemon=True)
                    self.procs.append(proc)
                    self.conns.append(parent_end)
                    if block:
                        signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
                    proc.start()
                    child_end.close()
            finally:
                if block:
                    signal.pthread_sigmask(signal.SIG_SETMASK, old)  # type: ignore[arg-type]
        raise_if_interrupted()

    def imap_unordered(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]:
        """Yield ``fn(item)`` for every item as the workers finish them (any order)."""
        from multiprocessing.connection import wait

        from infra.interrupt import raise_if_interrupted

        todo = list(items)[::-1]
        busy: dict[int, bool] = {}
        for i, conn in enumerate(self.conns):
            if todo:
                conn.send((fn, todo.pop()))
                busy[i] = True
        while busy:
            ready = wait([self.conns[i] for i in busy] + [self.procs[i].sentinel for i in busy])
            for i in list(busy):
                conn = self.conns[i]
                if conn in ready or conn.poll():
                    try:
                        kind, value = conn.recv()
                    except (EOFError, OSError):
                        kind, value = "died", None
                elif self.procs[i].sentinel in ready:
                    kind, value = "died", None
                else:
                    continue
                if kind == "died":
                    self._died(i)
                del busy[i]
                if kind == "error":
                    raise value
                if todo:
                    conn.send((fn, todo.pop()))
                    busy[i] = True
                raise_if_interrupted()
                yield value

    def _died(self, i: int) -> None:
        from infra.interrupt import Interrupted, raise_if_interrupted

        proc = self.procs[i]
        proc.join(1.0)
        raise_if_interrupted()  # killed with the parent's own signal: that is an interrupt
        code = proc.exitcode
        if code is not None and -code in _SIGNALS:
            raise Interrupted(-code)
        raise WorkerDied(f"a worker process of the process executor ended without answering "
                         f"(exit status {code}); its run was not stored")

    def stop(self, graceful: bool) -> None:
        """End every worker: asked to stop (``graceful``, after the last result), else killed at
        once; reaped either way, so none is left behind. Signals only recorded meanwhile."""
        from infra.interrupt import held

        with held():
            _LIVE.discard(self)
            if graceful:
                for conn in self.conns:
                    try:
                        conn.send(None)
                    except (OSError, ValueError):
                        pass
                for proc in self.procs:
                    if proc.pid is not None:
                        proc.join(STOP_GRACE_S)
            for proc in self.procs:
                if proc.pid is not None and proc.exitcode is None:
                    proc.kill()
            for proc in self.procs:
                if proc.pid is not None:
                    proc.join(STOP_GRACE_S)
            for conn in self.conns:
                conn.close()
            _stop_resource_tracker()


def _stop_resource_tracker() -> None:
    """Stop (and reap) multiprocessing's resource tracker, which spawning a worker started: it
    would otherwise outlive the command by a moment. It restarts when needed."""
    from multiprocessing import resource_tracker

    stop = getattr(resource_tracker._resource_tracker, "_stop", None)
    if stop is not None:
        try:
            stop()
        except Exception:
            pass


#: Pools not yet stopped (the command line stops them on every exit path).
_LIVE: set[_Pool] = set()


def stop_all() -> None:
    """Kill the workers of every pool still running (a command that ends with an error or an
    interrupt while a sweep's generator is left suspended)."""
    for pool in list(_LIVE):
        pool.stop(graceful=False)


def _process(fn: Callable[[Any], Any], items: Sequence[Any], workers: int,
             env: dict[str, str] | None = None) -> Iterator[Any]:
    pool = None
    finished = False
    try:
        pool = _Pool(min(workers, len(items)), env)
        yield from pool.imap_unordered(fn, items)
        finished = True
    finally:
        if pool is not None:
            pool.stop(graceful=finished)
        else:
            stop_all()


#: Seconds a Ray address has to accept a connection before the command is refused.
RAY_CONNECT_TIMEOUT_S = 5.0
#: Attempts (about one a second) to attach to a Ray cluster that accepts connections.
RAY_ATTACH_ATTEMPTS = 5


def check_ray_address(address: str | None) -> None:
    """Refuse (ConfigError, within :data:`RAY_CONNECT_TIMEOUT_S`) a Ray address that does not
    accept a TCP connection: ``ray.init`` retries such an address for minutes. ``None``,
    ``auto`` and ``local`` are left to Ray. Call it before anything is created."""
    import socket

    if not address or address in ("auto", "local"):
        return
    hostport = address.split("://", 1)[-1].rstrip("/")
    host, sep, port_text = hostport.rpartition(":")
    if not sep or not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise ConfigError(f"--ray-address {address!r} is not HOST:PORT (or ray://HOST:PORT)")
    try:
        with socket.create_connection((host.strip("[]"), int(port_text)),
                                      timeout=RAY_CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise ConfigError(
            f"the Ray cluster at {address} does not answer ({reason}, waited at most "
            f"{RAY_CONNECT_TIMEOUT_S:g} s); start it (`ray start --head`) or fix --ray-address "
            "/ RAY_ADDRESS"
        ) from None


#: The watchdog of the local Ray instance (:mod:`benchmark.reaper`), while one runs.
_reaper: Any = None


def _start_reaper() -> None:
    """Start :mod:`benchmark.reaper` on this process (Linux): it ends every process the local
    Ray instance started once this command ends, even by SIGKILL."""
    global _reaper
    import subprocess
    import sys

    if _reaper is not None or not os.path.isdir("/proc/self"):
        return
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (root, os.environ.get("PYTHONPATH")) if p)}
    _reaper = subprocess.Popen([sys.executable, "-m", "benchmark.reaper", str(os.getpid())],
                               stdin=subprocess.PIPE, env=env, cwd=root)


def _hand_over_to_reaper() -> None:
    """Give the reaper this process's descendants now (a signal ends the process at once):
    the Ray agents it has not scanned yet would be orphans once Ray's raylet dies with us."""
    if _reaper is not None and _reaper.stdin is not None:
        hand_over(_reaper.stdin.fileno(), os.getpid())


def shutdown_ray() -> None:
    """Stop the Ray instance this process started or attached to, then let the reaper end what
    Ray's shutdown missed, and wait for it (signals only recorded meanwhile)."""
    import sys

    global _reaper
    from infra.interrupt import held

    with held():
        ray = sys.modules.get("ray")
        if ray is not None and getattr(ray, "is_initialized", lambda: False)():
            ray.shutdown()
        if _reaper is not None:
            reaper, _reaper = _reaper, None
            try:
                reaper.stdin.close()
                reaper.wait(timeout=10)
            except Exception:
                reaper.kill()


def ensure_ray(workers: int, address: str | None = None) -> object:
    """Attach to ``address`` / ``RAY_ADDRESS`` if given, else start a local instance on loopback.

    The local instance has no dashboard, no usage statistics and token authentication off (it
    only listens on 127.0.0.1); :mod:`benchmark.reaper` ends its processes when the command
    ends. Our SIGINT/SIGTERM handlers are put back after ``ray.init`` (Ray's SIGTERM handler
    prints a native stack dump and exits 1).
    """
    # read by Ray: attach attempts (about one a second); no native handler that turns SIGTERM
    # into a stack dump and exit status 1
    os.environ.setdefault("RAY_NUM_REDIS_GET_RETRIES", str(RAY_ATTACH_ATTEMPTS))
    os.environ.setdefault("RAY_DISABLE_FAILURE_SIGNAL_HANDLER", "1")
    try:
        import ray
    except ImportError:
        raise ConfigError(
            "the ray executor needs Ray: install with `pip install -e '.[ray]'`"
        ) from None
    import signal

    from infra.interrupt import Interrupted, exit_at_once, held, raise_if_interrupted, reinstall

    if ray.is_initialized():
        return ray
    address = address or os.environ.get("RAY_ADDRESS")
    if address:
        check_ray_address(address)
        try:
            ray.init(address=address, log_to_driver=False)
        except (ConnectionError, RuntimeError) as exc:
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ConfigError(
                f"cannot attach to the Ray cluster at {address} ({reason}; gave up after "
                f"{RAY_ATTACH_ATTEMPTS} attempts); start it (`ray start --head`) or fix "
                "--ray-address / RAY_ADDRESS"
            ) from None
    else:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")
        _start_reaper()
        # not interrupted half-way (a half-made core worker crashed the process at exit,
        # SIGSEGV) nor waited for (seconds): a signal ends the command's process at once (the
        # reaper ends Ray's), or, called from Python, is held and raised after; Ray's own
        # SIGTERM handler (sys.exit(15) from anywhere inside its start) not installed
        utils = getattr(getattr(ray, "_private", None), "utils", None)
        own_handler = getattr(utils, "set_sigterm_handler", None)
        try:
            with exit_at_once(_hand_over_to_reaper):
                if own_handler is not None:
                    utils.set_sigterm_handler = lambda handler: None  # type: ignore[union-attr]
                ray.init(
                    num_cpus=workers,
                    include_dashboard=False,
                    _node_ip_address="127.0.0.1",
                    log_to_driver=False,
                    configure_logging=False,
                )
        except BaseException as exc:
            with held():
                try:
                    ray.shutdown()  # whatever was made of it
                except Exception:
                    pass
            if isinstance(exc, SystemExit) and exc.code == signal.SIGTERM:
                raise Interrupted(signal.SIGTERM) from None
            raise
        finally:
            if own_handler is not None:
                utils.set_sigterm_handler = own_handler  # type: ignore[union-attr]
    reinstall()
    raise_if_interrupted()
    return ray


def _ray(fn: Callable[[Any], Any], items: Sequence[Any], workers: int,
         address: str | None, env: dict[str, str] | None = None) -> Iterator[Any]:
    ray = ensure_ray(workers, address)
    remote = ray.remote(num_cpus=1)(fn)  # type: ignore[attr-defined]
    if env:  # Ray starts workers of their own for a runtime environment
        remote = remote.options(runtime_env={"env_vars": env})
    pending = [remote.remote(item) for item in items]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)  # type: ignore[attr-defined]
            for ref in done:
                yield ray.get(ref)  # type: ignore[attr-defined]
    finally:
        from infra.interrupt import held

        # only while Ray runs: a generator finalised after ray.shutdown() (the interrupt came
        # while its consumer stored a batch) crashed the process (SIGSEGV) by cancelling then
        with held():
            if ray.is_initialized():  # type: ignore[attr-defined]
                for ref in pending:
                    try:
                        ray.cancel(ref, force=True)  # type: ignore[attr-defined]
                    except Exception:
                        pass
