"""Time of one segment's LSTM forward and backward: step by step under autograd, and as
``BatchedLSTMCell.segment`` (docs/populations.md), one torch thread.

Shapes of training's recompute: T = 60 steps, B = 8 episodes, H = 64, for one run (A = 8
agents) and a population of six (A = 48).

    .venv/bin/python docs/scripts/lstm_segment_rate.py
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from marl.layers import BatchedLSTMCell

T_STEPS, BATCH, HIDDEN = 60, 8, 64


def step_by_step(cell: BatchedLSTMCell, gates: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]
                 ) -> torch.Tensor:
    """The recompute before the segment: ``step_from_gates`` per step, stacked."""
    hs = []
    for x in gates.unbind(1):
        state = cell.step_from_gates(x, state)
        hs.append(state[0])
    return torch.stack(hs, 1)


def ms_per_call(fn: Callable[[], torch.Tensor], params: list[torch.Tensor], reps: int = 10) -> float:
    """Milliseconds of a forward and a backward (loss: a weighted sum of the hidden states)."""
    weights = torch.linspace(-1.0, 1.0, HIDDEN)

    def once() -> None:
        for p in params:
            p.grad = None
        (fn() * weights).sum().backward()

    once()
    t0 = time.perf_counter()
    for _ in range(reps):
        once()
    return (time.perf_counter() - t0) / reps * 1000.0


def main() -> None:
    torch.set_num_threads(1)
    print("agents | step by step (ms) | segment (ms) | ratio")
    for agents in (8, 48):
        old, new = compare(agents)
        print(f"{agents:6d} | {old:17.1f} | {new:12.1f} | {old / new:5.2f}")


def compare(agents: int) -> tuple[float, float]:
    """Milliseconds step by step and as a segment, for ``agents`` agents."""
    g = torch.Generator().manual_seed(0)
    cell = BatchedLSTMCell(agents, HIDDEN, HIDDEN, g)
    gates = torch.randn(agents, T_STEPS, BATCH, 4 * HIDDEN, generator=g, requires_grad=True)
    state = (torch.zeros(agents, BATCH, HIDDEN), torch.zeros(agents, BATCH, HIDDEN))
    params = [gates, cell.weight_hh]
    old = ms_per_call(lambda: step_by_step(cell, gates, state), params)
    new = ms_per_call(lambda: cell.segment(gates, state)[0], params)
    return old, new


if __name__ == "__main__":
    main()
