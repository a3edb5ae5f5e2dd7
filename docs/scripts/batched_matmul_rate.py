"""Rate of the learner's batched products at population sizes (docs/populations.md).

Times ``torch.baddbmm`` of A agents' (M, k) x (k, n) products, one torch thread: the acting
step of the LSTM (M = B = 8 rows per agent, 64 -> 256) and the encoder (15 -> 64), for one run
(A = 8 agents) and a population of six (A = 48), and the segment recompute's M = 480 rows.

    .venv/bin/python docs/scripts/batched_matmul_rate.py
"""

from __future__ import annotations

import time

import torch


def rate(a: int, m: int, k: int, n: int, reps: int = 300) -> tuple[float, float]:
    """(microseconds per call, GFLOP/s) of ``baddbmm`` on random data."""
    g = torch.Generator().manual_seed(0)
    x, w = torch.randn(a, m, k, generator=g), torch.randn(a, k, n, generator=g)
    b = torch.randn(a, 1, n, generator=g)
    for _ in range(10):
        torch.baddbmm(b, x, w)
    t0 = time.perf_counter()
    for _ in range(reps):
        torch.baddbmm(b, x, w)
    dt = (time.perf_counter() - t0) / reps
    return dt * 1e6, 2 * a * m * k * n / dt / 1e9


if __name__ == "__main__":
    torch.set_num_threads(1)
    print(f"{'agents':>6} {'rows':>5} {'k x n':>9} {'us/call':>9} {'GFLOP/s':>8} {'weights MB':>10}")
    for a in (8, 48):
        for m in (8, 480):
            for k, n in ((64, 256), (15, 64)):
                us, gf = rate(a, m, k, n)
                print(f"{a:>6} {m:>5} {f'{k}x{n}':>9} {us:9.1f} {gf:8.1f} {a * k * n * 4 / 1e6:10.2f}")
