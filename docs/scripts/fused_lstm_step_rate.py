"""What fusing the LSTM step's elementwise kernels would gain (docs/populations.md).

Times one acting step of a population of six (A = 48 agents, B = 8 episodes, H = 64), one
torch thread, without gradients: the recurrent product (``torch.baddbmm``), the elementwise
gate update as the learner computes it (``BatchedLSTMCell.step_from_gates``: four sigmoids,
two tanh, products, each its own kernel), and the same update fused by ``torch.compile``
(inductor, which needs a C++ compiler). Prints the median microseconds per call and the largest
difference between the fused and the eager results.

    .venv/bin/python docs/scripts/fused_lstm_step_rate.py
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch
import torch.utils.benchmark as benchmark

AGENTS, BATCH, HIDDEN = 48, 8, 64


def gate_update(gates: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The elementwise half of ``BatchedLSTMCell.step_from_gates``, operation by operation."""
    i, f, g, o = gates.chunk(4, dim=-1)
    c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.sigmoid(o) * torch.tanh(c_new), c_new


def us_per_call(fn: Callable[[], object]) -> float:
    """Median microseconds per call, one thread, without gradients (``torch.utils.benchmark``)."""
    with torch.no_grad():
        timer = benchmark.Timer(stmt="fn()", globals={"fn": fn}, num_threads=1)
        return timer.blocked_autorange(min_run_time=1.0).median * 1e6


def main() -> None:
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(AGENTS, BATCH, 4 * HIDDEN, generator=g)
    h = torch.randn(AGENTS, BATCH, HIDDEN, generator=g)
    c = torch.randn(AGENTS, BATCH, HIDDEN, generator=g)
    w = torch.randn(AGENTS, HIDDEN, 4 * HIDDEN, generator=g) * 0.1
    gates = torch.baddbmm(x, h, w)
    fused = torch.compile(gate_update, dynamic=False)
    t0 = time.perf_counter()
    with torch.no_grad():
        fused_out = fused(gates, c)
    compile_s = time.perf_counter() - t0
    with torch.no_grad():
        eager_out = gate_update(gates, c)
    diff = max(float((a - b).abs().max()) for a, b in zip(fused_out, eager_out, strict=True))
    print(f"compile: {compile_s:.1f} s; largest difference fused - eager: {diff:.2e}")
    for _ in range(2):
        product = us_per_call(lambda: torch.baddbmm(x, h, w))
        eager = us_per_call(lambda: gate_update(gates, c))
        compiled = us_per_call(lambda: fused(gates, c))
        print(f"baddbmm {product:6.1f} us | elementwise eager {eager:6.1f} us | "
              f"fused {compiled:6.1f} us")


if __name__ == "__main__":
    main()
