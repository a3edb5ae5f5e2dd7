"""Training throughput of the MARL learners (called by ``cacc-bench perf``)."""

from __future__ import annotations

import time

import torch


def train_throughput(
    algo: str,
    steps: int = 20_000,
    n_vehicles: int = 8,
    scenario_id: str = "catchup-v1",
    episodes_parallel: int | None = None,
    cpu_time: bool = False,
    population: int = 1,
    device: str = "cpu",
) -> float:
    """Environment steps per second of training ``algo`` from scratch, one process, one thread.

    Steps are counted across the parallel episodes (an active episode's step is one environment
    step), as for the training budget. Nothing is written and no evaluation runs.

    Parameters
    ----------
    cpu_time : bool
        Divide by this process's CPU time instead of the wall clock (for busy shared machines).
    population : int
        Train this many seeds (0, 1, ...) at once as one population, ``steps`` each; the rate
        is the population's total.
    device : str
        Where the networks train (``cpu`` or ``cuda[:K]``; the environments stay on the CPU).
    """
    from marl.config import algorithm
    from marl.selection import run_population

    torch.set_num_threads(1)
    a = algorithm(algo)
    cfg = (
        a.config_cls()
        if episodes_parallel is None
        else a.config_cls(episodes_parallel=episodes_parallel)
    )
    clock = time.process_time if cpu_time else time.perf_counter
    t0 = clock()
    # the first ``steps`` of a run with the paper's budget (the entropy schedule of 6e5 steps)
    results = run_population(a, [cfg] * population, scenario_id, n_vehicles, steps,
                             list(range(population)), None, schedule_steps=600_000,
                             device=device)
    return sum(r.steps for r in results) / max(clock() - t0, 1e-9)
