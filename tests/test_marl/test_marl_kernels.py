"""Shared MARL kernels against slow reference loops and hand-made numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from infra.errors import ConfigError
from marl.a2c import nstep_returns, share_rewards
from marl.checkpoint import FORMAT_VERSION, load_checkpoint, save_checkpoint
from marl.consensus import bdc, consensus_round, dcea, degree, neighbour_sum, wac
from marl.layers import BatchedLinear, BatchedLSTMCell, per_agent_clip_
from marl.quantize import (
    ErrorFeedbackQSGD,
    qsgd,
    qsgd_bits,
    qsgd_variance_bound,
    ternary,
    ternary_bits,
)


# ----------------------------------------------------------------------------- returns
def _slow_returns(reward, bootstrap, terminal, gamma):
    t_len, b, n = reward.shape
    out = np.zeros((t_len, b, n))
    for bi in range(b):
        for i in range(n):
            r_next = bootstrap[bi, i]
            for t in reversed(range(t_len)):
                r_next = reward[t, bi, i] + gamma * (1.0 - terminal[t, bi]) * r_next
                out[t, bi, i] = r_next
    return out


def test_share_rewards_matches_loop() -> None:
    rng = np.random.default_rng(0)
    r = rng.normal(size=(5, 3, 6))
    for alpha in (0.0, 0.5, 0.9, 1.0):
        got = share_rewards(torch.tensor(r), alpha).numpy()
        want = np.zeros_like(r)
        for i in range(6):
            for j in range(6):
                want[..., i] += (alpha ** abs(i - j) if i != j else 1.0) * r[..., j]
        np.testing.assert_allclose(got, want, rtol=1e-12)
    # alpha = 0: own reward; alpha = 1: global sum
    np.testing.assert_allclose(share_rewards(torch.tensor(r), 0.0).numpy(), r)
    np.testing.assert_allclose(
        share_rewards(torch.tensor(r), 1.0).numpy(), np.repeat(r.sum(-1, keepdims=True), 6, -1)
    )


def test_nstep_returns_match_slow_loop_with_terminals() -> None:
    rng = np.random.default_rng(1)
    t_len, b, n = 7, 4, 3
    r = rng.normal(size=(t_len, b, n))
    boot = rng.normal(size=(b, n))
    term = np.zeros((t_len, b))
    term[2, 1] = 1  # ends mid-segment: later rewards and bootstrap cut
    term[6, 2] = 1  # ends at the segment's end: no bootstrap
    term[0, 3] = term[4, 3] = 1
    got = nstep_returns(torch.tensor(r), torch.tensor(boot), torch.tensor(term), 0.9).numpy()
    np.testing.assert_allclose(got, _slow_returns(r, boot, term, 0.9), rtol=1e-10)


def test_nstep_returns_by_hand() -> None:
    r = torch.tensor([1.0, 2.0, 3.0]).reshape(3, 1, 1)
    boot = torch.tensor([[10.0]])
    none = torch.zeros(3, 1)
    got = nstep_returns(r, boot, none, 0.5).flatten().tolist()
    assert got == pytest.approx([1 + 0.5 * 2 + 0.25 * 3 + 0.125 * 10, 2 + 1.5 + 2.5, 3 + 5])
    end = torch.tensor([[0.0], [0.0], [1.0]])
    assert nstep_returns(r, boot, end, 0.5).flatten().tolist() == pytest.approx([2.75, 3.5, 3.0])


# ----------------------------------------------------------------------------- quantisers
def test_ternary_is_sign() -> None:
    w = torch.tensor([-2.0, -0.1, 0.0, 0.3, 5.0])
    assert ternary(w).tolist() == [-1.0, -1.0, 0.0, 1.0, 1.0]


@pytest.mark.parametrize("s", [1, 2, 4])
def test_qsgd_unbiased_and_on_grid(s: int) -> None:
    g = torch.tensor([[0.5, -1.0, 0.25, 0.0, 2.0], [3.0, 0.0, -4.0, 0.0, 0.0]], dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    k = 20000
    samples = qsgd(g.repeat(k, 1), s, gen).reshape(k, *g.shape)  # k independent draws
    norm = torch.linalg.vector_norm(g, dim=1, keepdim=True)
    levels = samples.abs() / norm * s
    assert torch.allclose(levels, levels.round(), atol=1e-9)  # values are norm * l/s
    assert (torch.sign(samples) * torch.sign(g) >= 0).all()  # sign kept, zeros stay zero
    mean = samples.mean(0)
    # standard error of the mean is at most norm / sqrt(4 s^2 k) per entry
    tol = 5 * norm / (2 * s * math.sqrt(k))
    assert ((mean - g).abs() <= tol).all()


def test_qsgd_buckets_unbiased_with_their_own_norms() -> None:
    """Bucketed QSGD: every bucket of 2 entries (the last one padded) is quantised with its own
    norm, stays unbiased, and bucket=None equals one norm per tensor."""
    g = torch.tensor([[3.0, -4.0, 0.6, 0.8, 2.0]], dtype=torch.float64)  # buckets: 5, 1, 2
    gen = torch.Generator().manual_seed(0)
    k = 20000
    q = qsgd(g.repeat(k, 1), 1, gen, bucket=2)
    norms = torch.tensor([5.0, 5.0, 1.0, 1.0, 2.0], dtype=torch.float64)
    ok = torch.isclose(q.abs(), norms.expand_as(q)) | (q == 0)
    assert ok.all()
    assert q.mean(0).tolist() == pytest.approx(g[0].tolist(), abs=5 * 5.0 / (2 * math.sqrt(k)))
    a = qsgd(g, 1, torch.Generator().manual_seed(1), bucket=None)
    b = qsgd(g, 1, torch.Generator().manual_seed(1), bucket=99)
    assert torch.equal(a, b)
    assert qsgd_bits(300, 1, bucket=128) == pytest.approx(3 * 32 + 300 * math.log2(3))
    with pytest.raises(ValueError):
        qsgd(g, 1, gen, bucket=0)


def test_qsgd_rounds_up_with_probability_p() -> None:
    """Round-up frequency is ``p = s|g|/||g|| - l`` (the published code used ``1 - p``)."""
    g = torch.tensor([[0.6, 0.8]], dtype=torch.float64)  # norm 1: p = 0.6 and 0.8
    gen = torch.Generator().manual_seed(0)
    q = qsgd(g.repeat(20000, 1), 1, gen)
    up = (q.abs() > 0.5).to(torch.float64).mean(0)
    assert up.tolist() == pytest.approx([0.6, 0.8], abs=0.015)


def test_error_feedback_residual_is_exact() -> None:
    gen = torch.Generator().manual_seed(3)
    ef = ErrorFeedbackQSGD(1, gen)
    rng = torch.Generator().manual_seed(4)
    f64 = torch.float64
    grads_seen = [torch.zeros(3, 4, 5, dtype=f64), torch.zeros(3, 7, dtype=f64)]
    sent = [torch.zeros(3, 4, 5, dtype=f64), torch.zeros(3, 7, dtype=f64)]
    for _ in range(25):
        gs = [
            torch.randn(3, 4, 5, generator=rng, dtype=f64),
            torch.randn(3, 7, generator=rng, dtype=f64),
        ]
        qs = ef.compress(gs)
        for i in range(2):
            grads_seen[i] += gs[i]
            sent[i] += qs[i]
    assert ef.residual is not None
    for i in range(2):  # sum of true gradients = sum sent + residual
        torch.testing.assert_close(grads_seen[i], sent[i] + ef.residual[i], atol=1e-12, rtol=0)


def test_qsgd_variance_bound() -> None:
    """Alistarh et al.'s bound ``min(d/s^2, sqrt(d)/s)`` holds for the measured error, and is
    reached within a factor of two by a flat vector (s = 1, one bucket of 64 entries)."""
    assert qsgd_variance_bound(64, 1) == 8.0
    assert qsgd_variance_bound(4, 4) == 0.25
    assert qsgd_variance_bound(10_000, 1, bucket=128) == pytest.approx(math.sqrt(128))
    gen = torch.Generator().manual_seed(5)
    k = 20_000
    for g in (torch.ones(1, 64, dtype=torch.float64), torch.randn(1, 64, generator=gen)):
        g = g.to(torch.float64)
        err = (qsgd(g.repeat(k, 1), 1, gen) - g).square().sum(1).mean()
        ratio = float(err / g.square().sum())
        assert ratio <= qsgd_variance_bound(64, 1) * 1.02
    flat = torch.ones(1, 64, dtype=torch.float64)
    err = (qsgd(flat.repeat(k, 1), 1, gen) - flat).square().sum(1).mean() / 64.0
    assert float(err) == pytest.approx(7.0, rel=0.03)  # sqrt(64) - 1 for a flat vector


def test_error_feedback_residual_stays_bounded() -> None:
    """Error feedback with the contractive scaling keeps the residual of the size of the
    gradients over many rounds; plain unbiased QSGD (s = 1) lets it grow geometrically."""
    rng = torch.Generator().manual_seed(6)
    grads = [torch.randn(2, 256, generator=rng) for _ in range(200)]
    g_max = max(float(g.norm()) for g in grads)
    ef = ErrorFeedbackQSGD(1, torch.Generator().manual_seed(7), bucket=128)
    for g in grads:
        ef.compress([g])
    assert ef.residual is not None
    assert float(ef.residual[0].norm()) < 10 * g_max
    plain = ErrorFeedbackQSGD(1, torch.Generator().manual_seed(7), bucket=128, contractive=False)
    for g in grads[:60]:
        plain.compress([g])
    assert plain.residual is not None
    norm = float(plain.residual[0].norm())
    assert not math.isfinite(norm) or norm > 1e6 * g_max


def test_bit_counts() -> None:
    assert ternary_bits(100) == pytest.approx(100 * math.log2(3))
    assert ternary_bits(100, packed=True) == 200
    assert qsgd_bits(10, 1) == pytest.approx(32 + 10 * math.log2(3))


# ----------------------------------------------------------------------------- consensus
def test_neighbour_sum_and_degree() -> None:
    w = torch.tensor([[1.0], [2.0], [4.0], [8.0]])
    assert neighbour_sum(w).flatten().tolist() == [2.0, 5.0, 10.0, 4.0]
    assert degree(4, w).flatten().tolist() == [1.0, 2.0, 2.0, 1.0]


def test_wac_synchronous_mean() -> None:
    w = torch.tensor([[3.0], [6.0], [0.0], [9.0]])
    # agent 0: (3+6)/2; agent 1: (3+6+0)/3; agent 2: (6+0+9)/3; agent 3: (0+9)/2 -- all from
    # the snapshot (in-place agent-by-agent averaging would give agent 1 (4.5+6+0)/3 = 3.5)
    assert wac(w).flatten().tolist() == [4.5, 3.0, 5.0, 4.5]


def test_dcea_by_hand() -> None:
    w = torch.tensor([[1.0], [2.0], [4.0]])
    got = dcea(w, 0.1).flatten().tolist()
    assert got == pytest.approx([1 + 0.1 * (2 - 1), 2 + 0.1 * (1 - 2 + 4 - 2), 4 + 0.1 * (2 - 4)])


def test_bdc_by_hand() -> None:
    w = torch.tensor([[0.5, -0.2], [-0.3, -0.1], [0.0, 0.4]])
    got = bdc(w, 0.01)
    # q = [[1,-1],[-1,-1],[0,1]]
    want = torch.tensor(
        [
            [0.5 + 0.01 * (-1 - 1), -0.2 + 0.01 * (-1 + 1)],
            [-0.3 + 0.01 * ((1 + 1) + (0 + 1)), -0.1 + 0.01 * ((-1 + 1) + (1 + 1))],
            [0.0 + 0.01 * (-1 - 0), 0.4 + 0.01 * (-1 - 1)],
        ]
    )
    torch.testing.assert_close(got, want)


def test_consensus_round_updates_parameters_in_place_from_snapshot() -> None:
    p = torch.nn.Parameter(torch.tensor([[3.0], [6.0], [0.0], [9.0]]))
    n = consensus_round([p], wac)
    assert n == 1
    assert p.detach().flatten().tolist() == [4.5, 3.0, 5.0, 4.5]


# ----------------------------------------------------------------------------- layers
def test_batched_linear_equals_separate_linears() -> None:
    torch.manual_seed(0)
    layers = [torch.nn.Linear(5, 3) for _ in range(4)]
    bl = BatchedLinear.from_linears(layers)
    x = torch.randn(4, 6, 5)
    got = bl(x)
    want = torch.stack([layers[i](x[i]) for i in range(4)])
    torch.testing.assert_close(got, want)


def test_batched_lstm_equals_separate_cells_and_gradients() -> None:
    torch.manual_seed(0)
    cells = [torch.nn.LSTMCell(5, 7) for _ in range(3)]
    bc = BatchedLSTMCell.from_cells(cells)
    x = torch.randn(4, 3, 2, 5)  # (T, N, B, in)
    h = torch.randn(3, 2, 7)
    c = torch.randn(3, 2, 7)
    hb, cb = h, c
    hs = [h[i] for i in range(3)]
    cs = [c[i] for i in range(3)]
    for t in range(4):
        hb, cb = bc(x[t], (hb, cb))
        for i in range(3):
            hs[i], cs[i] = cells[i](x[t, i], (hs[i], cs[i]))
    torch.testing.assert_close(hb, torch.stack(hs), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(cb, torch.stack(cs), atol=1e-6, rtol=1e-5)
    hb.sum().backward()
    sum(hh.sum() for hh in hs).backward()
    want = torch.stack([cell.weight_hh.grad.T for cell in cells])
    torch.testing.assert_close(bc.weight_hh.grad, want, atol=1e-5, rtol=1e-4)


def test_lstm_segment_gradients_pass_gradcheck() -> None:
    """The written-out backward of :meth:`BatchedLSTMCell.segment` against finite differences
    (float64), for the gradients of the gates, the initial state and ``W_hh``."""
    from marl.layers import _LSTMSegment

    g = torch.Generator().manual_seed(3)
    n, t_len, b, hidden = 2, 4, 3, 5
    args = (torch.randn(n, t_len, b, 4 * hidden, generator=g, dtype=torch.float64),
            torch.randn(n, b, hidden, generator=g, dtype=torch.float64),
            torch.randn(n, b, hidden, generator=g, dtype=torch.float64),
            0.5 * torch.randn(n, hidden, 4 * hidden, generator=g, dtype=torch.float64))
    for x in args:
        x.requires_grad_(True)
    assert torch.autograd.gradcheck(_LSTMSegment.apply, args)


def test_lstm_segment_equals_torch_lstm() -> None:
    """A segment of separate agents equals ``torch.nn.LSTM`` run on each agent's sequence:
    outputs, final state and every gradient (a reference we did not write)."""
    torch.manual_seed(4)
    n, t_len, b, d_in, hidden = 3, 6, 2, 5, 7
    refs = [torch.nn.LSTM(d_in, hidden) for _ in range(n)]
    cell = BatchedLSTMCell.from_cells(
        [torch.nn.LSTMCell(d_in, hidden) for _ in range(n)])
    with torch.no_grad():
        for i, lstm in enumerate(refs):
            cell.weight_ih[i] = lstm.weight_ih_l0.T
            cell.weight_hh[i] = lstm.weight_hh_l0.T
            cell.bias[i] = lstm.bias_ih_l0 + lstm.bias_hh_l0
    x = torch.randn(n, t_len, b, d_in)
    h0, c0 = torch.randn(n, b, hidden), torch.randn(n, b, hidden)
    weights = torch.randn(t_len, b, hidden)
    hs, (h_t, c_t) = cell.segment(
        cell.input_gates(x.reshape(n, t_len * b, d_in)).reshape(n, t_len, b, -1), (h0, c0))
    ((hs * weights).sum() + c_t.square().sum()).backward()
    for i, lstm in enumerate(refs):
        out, (hn, cn) = lstm(x[i], (h0[i : i + 1], c0[i : i + 1]))
        torch.testing.assert_close(hs[i], out, atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(c_t[i], cn[0], atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(h_t[i], hn[0], atol=1e-6, rtol=1e-5)
        ((out * weights).sum() + cn.square().sum()).backward()
        torch.testing.assert_close(cell.weight_hh.grad[i], lstm.weight_hh_l0.grad.T,
                                   atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(cell.weight_ih.grad[i], lstm.weight_ih_l0.grad.T,
                                   atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(cell.bias.grad[i], lstm.bias_ih_l0.grad, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("name", ["fprint", "wac", "bdc"])
def test_segment_recompute_equals_step_by_step(name: str) -> None:
    """The networks that run their recurrence as one LSTM segment give the step-by-step
    recompute's logits, values and final state to the last bit, and its gradients to float
    rounding."""
    from marl.config import algorithm
    from marl.networks import AgentNet

    algo = algorithm(name)
    net = algo.build_net(algo.config_cls(), 4, True, torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(1)
    a, t_len, b = 4, 5, 4
    state = {k: 0.3 * torch.randn(v.shape, generator=g)
             for k, v in net.initial_state(b).items()}
    obs = torch.randn(a, t_len, b, 15, generator=g)
    actions = torch.randint(0, 4, (a, t_len, b), generator=g)
    msgs = None
    if net.msg_width:
        msgs = (torch.rand(a, t_len, b, net.msg_width, generator=g),
                torch.rand(a, t_len, b, net.msg_width, generator=g))

    def grads(step_by_step: bool):
        net.zero_grad()
        with pytest.MonkeyPatch.context() as mp:
            if step_by_step:  # the base class's loop
                mp.setattr(type(net), "recur_segment", AgentNet.recur_segment)
            logits, values, after = net(state, obs, actions, msgs)
        (logits.square().sum() + values.sum()).backward()
        return logits.detach(), values.detach(), after, [p.grad.clone() for p in net.parameters()]

    fused, steps = grads(False), grads(True)
    assert torch.equal(fused[0], steps[0]) and torch.equal(fused[1], steps[1])
    assert all(torch.equal(fused[2][k], steps[2][k]) for k in steps[2])
    for got, want in zip(fused[3], steps[3], strict=True):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-4)


def test_input_gates_split_equals_full_cell() -> None:
    torch.manual_seed(1)
    bc = BatchedLSTMCell(2, 6, 4)
    x = torch.randn(2, 3, 6)
    st = (torch.randn(2, 3, 4), torch.randn(2, 3, 4))
    g = bc.input_gates(x[..., :4], slice(0, 4)) + bc.input_gates(
        x[..., 4:], slice(4, 6), bias=False
    )
    for a, b in zip(bc(x, st), bc.step_from_gates(g, st)):
        torch.testing.assert_close(a, b)


def test_per_agent_clip_equals_separate_clipping() -> None:
    w = torch.nn.Parameter(torch.zeros(2, 3))
    b = torch.nn.Parameter(torch.zeros(2))
    w.grad = torch.tensor([[3.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    b.grad = torch.tensor([4.0, 0.0])
    norms = per_agent_clip_([w, b], 1.0)
    assert norms.tolist() == pytest.approx([5.0, 0.1])
    assert w.grad[0].tolist() == pytest.approx([0.6, 0, 0], abs=1e-6)
    assert b.grad[0].item() == pytest.approx(0.8, abs=1e-6)
    assert w.grad[1].tolist() == pytest.approx([0.1, 0, 0])  # below the limit: untouched


def test_per_agent_clip_norms_do_not_depend_on_the_stack() -> None:
    """An agent's norm is the same bits whether 3 or 6 agents are stacked (a population of two
    runs of 3 agents, or one run): a sum over the stacked per-tensor sums rounded otherwise for
    3 and 6 columns on an AVX-512 CPU, and a population of WAC runs then clipped differently
    from its runs alone."""
    from marl.networks import SeparateActorCriticNet

    gen = torch.Generator().manual_seed(0)
    for _ in range(20):
        params = [torch.nn.Parameter(p.detach().clone())
                  for p in SeparateActorCriticNet(6, 64, True, gen).parameters()]
        for p in params:
            p.grad = torch.randn(p.shape, generator=gen) * 0.1
        halves = [[torch.nn.Parameter(p[sl].detach().clone()) for p in params]
                  for sl in (slice(0, 3), slice(3, 6))]
        for half in halves:
            for p, q in zip(half, params, strict=True):
                p.grad = q.grad[: 3].clone() if half is halves[0] else q.grad[3:].clone()
        whole = per_agent_clip_(params, 1.0)
        parts = torch.cat([per_agent_clip_(h, 1.0) for h in halves])
        assert torch.equal(whole, parts)
        for h, sl in zip(halves, (slice(0, 3), slice(3, 6)), strict=True):
            for p, q in zip(h, params, strict=True):
                assert torch.equal(p.grad, q.grad[sl])


# ----------------------------------------------------------------------------- checkpoints
def _save(path, **over):
    """A checkpoint with every acting weight of its network (zeros) but those given."""
    from marl.checkpoint import acting_weight_shapes

    kw = dict(
        algo="ia2c",
        config={"n_step": 60},
        scenario="catchup-v1",
        n_vehicles=8,
        seed=0,
        steps=1000,
        curve_summary={"final_eval_reward": -80.0},
        weights={"fc.weight": torch.randn(8, 15, 64)},
    )
    kw.update(over)
    shapes = acting_weight_shapes(kw["algo"], kw["config"], kw["n_vehicles"])
    kw["weights"] = {**{k: torch.zeros(v) for k, v in shapes.items()}, **kw["weights"]}
    return save_checkpoint(path, **kw)


def test_checkpoint_round_trip_float16(tmp_path) -> None:
    w = torch.randn(8, 15, 64)
    p = _save(tmp_path / "a.pt", weights={"fc.weight": w})
    d = load_checkpoint(p, algo="ia2c", n_vehicles=8)
    assert d["format_version"] == FORMAT_VERSION and d["steps"] == 1000
    assert d["weights"]["fc.weight"].dtype == torch.float32
    torch.testing.assert_close(d["weights"]["fc.weight"], w.half().float())
    assert d["curve_summary"]["final_eval_reward"] == -80.0
    from envs.energy import load_power_polynomial

    # the energy model the reward used: the shipped model's fingerprint
    assert d["energy_model"] == load_power_polynomial().fingerprint
    assert len(d["energy_model"]) == 12


def test_checkpoint_mismatches_fail_clearly(tmp_path) -> None:
    p = _save(tmp_path / "a.pt")
    with pytest.raises(ConfigError, match=r"a\.pt.*'ia2c'.*cacc-bench train --algo bdc"):
        load_checkpoint(p, algo="bdc", n_vehicles=8)
    with pytest.raises(ConfigError, match=r"N = 8.*--vehicles 4"):
        load_checkpoint(p, algo="ia2c", n_vehicles=4)
    with pytest.raises(ConfigError, match="does not exist.*cacc-bench train"):
        load_checkpoint(tmp_path / "missing.pt", algo="ia2c", n_vehicles=8)
    data = torch.load(p, weights_only=True)
    data["format_version"] = 999
    torch.save(data, tmp_path / "old.pt")
    with pytest.raises(ConfigError, match=r"old\.pt has format version 999.*cacc-bench train"):
        load_checkpoint(tmp_path / "old.pt", algo="ia2c", n_vehicles=8)
    w = torch.randn(8, 15, 64)
    w[3, 0, 0] = float("nan")
    _save(tmp_path / "nan.pt", weights={"fc.weight": w})
    with pytest.raises(ConfigError, match=r"non-finite weights \(fc\.weight\).*cacc-bench train"):
        load_checkpoint(tmp_path / "nan.pt", algo="ia2c", n_vehicles=8)


@pytest.mark.parametrize("alpha", [-0.1, 1.5, 2.0])
def test_sharing_alpha_outside_the_unit_interval_is_refused(alpha: float) -> None:
    from marl.a2c import sharing_matrix

    with pytest.raises(ValueError, match=r"alpha must lie in \[0, 1\]"):
        sharing_matrix(3, alpha)


def test_returns_and_sharing_keep_float64() -> None:
    """Double precision in, double precision out (a learner in float64 stays exact)."""
    from marl.a2c import sharing_matrix

    assert sharing_matrix(3, 0.5, torch.float64).dtype == torch.float64
    np.testing.assert_array_equal(sharing_matrix(3, 0.5, torch.float64).numpy(),
                                  [[1, 0.5, 0.25], [0.5, 1, 0.5], [0.25, 0.5, 1]])
    r = torch.full((3, 1, 2), 1.0 / 3.0, dtype=torch.float64)
    out = nstep_returns(r, torch.zeros(1, 2, dtype=torch.float64),
                        torch.zeros(3, 1, 2, dtype=torch.bool), 0.9)
    assert out.dtype == torch.float64
    assert out[0, 0, 0].item() == (1 + 0.9 + 0.81) / 3.0


def test_qsgd_defaults_are_the_papers_one_level() -> None:
    """s = 1 (ternary entries, the paper's setting) is every QSGD function's default."""
    import inspect

    from marl.quantize import ErrorFeedbackQSGD, qsgd, qsgd_bits, qsgd_variance_bound

    for fn in (qsgd, qsgd_bits, qsgd_variance_bound, ErrorFeedbackQSGD.__init__):
        assert inspect.signature(fn).parameters["s"].default == 1, fn


@pytest.mark.parametrize(("d", "s", "bucket"), [(100, 2, None), (100, 4, None), (100, 2, 16),
                                                  (9, 3, None)])
def test_qsgd_bound_and_bits_for_several_levels(d: int, s: int, bucket: int | None) -> None:
    """omega = min(d_b / s^2, sqrt(d_b) / s) with d_b the bucket size; bits = one 32-bit norm per
    bucket + log2(2s + 1) per entry (by hand)."""
    import math

    from marl.quantize import qsgd_bits, qsgd_variance_bound

    db = d if bucket is None else min(bucket, d)
    assert qsgd_variance_bound(d, s, bucket) == min(db / s**2, math.sqrt(db) / s)
    norms = 1 if bucket is None else math.ceil(d / bucket)
    assert qsgd_bits(d, s, bucket=bucket) == norms * 32 + d * math.log2(2 * s + 1)
    assert qsgd_variance_bound(100, 2) == 5.0 and qsgd_bits(10, 2) == 32 + 10 * math.log2(5)


def test_qsgd_with_a_bucket_that_does_not_divide_the_tensor() -> None:
    """9 entries in buckets of 4 (the last bucket padded): shape kept, every entry a multiple
    of its own bucket's norm / s, and unbiased over many draws."""
    from marl.quantize import qsgd

    g = torch.arange(1.0, 19.0).reshape(2, 9)
    gen = torch.Generator().manual_seed(0)
    q = qsgd(g, 2, gen, bucket=4)
    assert q.shape == (2, 9)
    for row in range(2):
        for start in (0, 4, 8):
            blk = g[row, start:start + 4]
            norm = torch.linalg.vector_norm(blk)
            k = q[row, start:start + 4] / (norm / 2)
            torch.testing.assert_close(k, k.round(), atol=1e-5, rtol=0)
    mean = torch.stack([qsgd(g, 2, gen, bucket=4) for _ in range(4000)]).mean(0)
    torch.testing.assert_close(mean, g, atol=0.35, rtol=0.03)


def test_qsgd_argument_checks() -> None:
    """s >= 1 and bucket >= 1 (a one-entry bucket is allowed: each entry sent as +-norm or 0)."""
    from marl.quantize import qsgd

    g = torch.tensor([[3.0, -4.0]])
    with pytest.raises(ValueError, match="QSGD needs s >= 1 levels, got 0"):
        qsgd(g, 0)
    with pytest.raises(ValueError, match="QSGD bucket must be >= 1 entries, got 0"):
        qsgd(g, 1, bucket=0)
    q = qsgd(g, 1, torch.Generator().manual_seed(0), bucket=1)
    torch.testing.assert_close(q, g)  # |g_k| / ||g_k|| = 1: exactly +-norm


def _draw_by_hand(probs: list[float], u: float) -> int:
    """The first action whose cumulative probability exceeds u (a loop, in Python floats)."""
    c = 0.0
    for a, p in enumerate(probs):
        c += p
        if u < c:
            return a
    return len(probs) - 1


def test_sample_from_logits_draws_the_policy() -> None:
    """Inverse-CDF draws follow softmax(logits): 40,000 draws within 1 % of each probability,
    and u just below / at a cumulative boundary picks the action on each side."""
    from marl.acting import sample_from_logits

    logits = torch.log(torch.tensor([0.1, 0.2, 0.3, 0.4])).reshape(1, 1, 4).expand(1, 40_000, 4)
    u = (np.arange(40_000) + 0.5).reshape(40_000, 1) / 40_000
    u = np.random.default_rng(0).permutation(u)
    a = sample_from_logits(logits, u)
    freq = np.bincount(a.ravel(), minlength=4) / a.size
    np.testing.assert_allclose(freq, [0.1, 0.2, 0.3, 0.4], atol=0.01)
    edge = sample_from_logits(logits[:, :2], np.array([[0.0999999], [0.3000001]]))
    assert edge.ravel().tolist() == [0, 2]


def test_sample_from_logits_per_agent_and_episode_by_hand() -> None:
    """Logits ``(N, B, A)`` with a different policy for every agent and episode, uniforms
    ``(B, N)``: each action is the hand-drawn one of its own agent and episode; a uniform
    exactly on a cumulative boundary takes the next action."""
    from marl.acting import sample_from_logits

    n, b = 3, 2
    logits = torch.tensor([[[0.1 * (i + 1) * (k - 1.5) + 0.3 * j for k in range(4)]
                            for j in range(b)] for i in range(n)], dtype=torch.float32)
    u = np.array([[0.05, 0.45, 0.93], [0.61, 0.18, 0.77]])
    got = sample_from_logits(logits, u)
    assert got.shape == (b, n) and got.dtype == np.int64
    for i in range(n):
        for j in range(b):
            probs = torch.softmax(logits[i, j].double(), -1).tolist()
            assert got[j, i] == _draw_by_hand(probs, float(u[j, i])), (i, j)
    assert len(set(got.ravel().tolist())) >= 3  # the table exercises several actions
    flat = torch.zeros(1, 1, 4)  # probabilities 1/4 each, cumulative 0.25, 0.5, 0.75 exactly
    on_edges = np.array([[0.0], [0.25], [0.5], [0.75]])
    assert sample_from_logits(flat.expand(1, 4, 4), on_edges).ravel().tolist() == [0, 1, 2, 3]


def test_sample_from_logits_uses_double_precision_probabilities() -> None:
    """The cumulative probabilities are computed in float64: for these logits float32's
    softmax puts the first boundary 7e-9 higher, and a uniform on the float64 boundary takes
    action 1 (float32 would take action 0)."""
    from marl.acting import sample_from_logits

    logits = torch.tensor([3 / 37.0, 0.0, -0.5, 0.3], dtype=torch.float32)
    p64 = torch.softmax(logits.double(), -1)
    assert float(torch.softmax(logits, -1)[0]) > float(p64[0])  # the premise
    u = np.array([[float(p64[0])]])
    assert sample_from_logits(logits.reshape(1, 1, 4), u).item() == 1


def test_two_runs_stacked_as_one_agent_stack_act_and_learn_as_alone() -> None:
    """The measured premise of population training (issue 17): K runs' networks stacked along
    the agent axis (K x N agents in one ``BatchedLinear``/``BatchedLSTMCell`` stack) give each
    run, to the last bit, the actor's logits, next state and gradients it has alone. (What
    would mix runs is everything that shifts along the agent axis: the critic's neighbour
    actions, messages, consensus; those need the run axis kept apart.)"""
    from marl.config import algorithm

    spec = algorithm("ia2c")
    cfg = spec.config_cls()
    nets = [spec.build_net(cfg, 4, False, torch.Generator().manual_seed(s)) for s in (1, 2)]
    stack = spec.build_net(cfg, 8, False)
    with torch.no_grad():
        for name, p in stack.named_parameters():
            p.copy_(torch.cat([dict(n.named_parameters())[name] for n in nets]))
    gen = torch.Generator().manual_seed(3)
    obs = torch.randn(8, 16, 15, generator=gen)
    state = {k: torch.randn(v.shape, generator=gen) for k, v in stack.initial_state(16).items()}
    actions = torch.randint(0, 4, (8, 16), generator=gen)

    def loss_and_out(net, o, s, a):
        logits, _, new = net.act_step(o, s, None, None)
        logp = torch.log_softmax(logits, -1).gather(-1, a.unsqueeze(-1))
        return -logp.mean(), logits, new

    total, logits, new = loss_and_out(stack, obs, state, actions)
    parts = [loss_and_out(n, obs[4 * k:4 * k + 4], {key: v[4 * k:4 * k + 4] for key, v in
                                                    state.items()}, actions[4 * k:4 * k + 4])
             for k, n in enumerate(nets)]
    # each run's loss is its own mean: the stack's is their average, so scale back by K = 2
    (2 * total).backward()
    for k, (loss, lg, nw) in enumerate(parts):
        loss.backward()
        assert torch.equal(logits[4 * k:4 * k + 4], lg)
        assert all(torch.equal(new[key][4 * k:4 * k + 4], nw[key]) for key in nw)
        for name, p in stack.named_parameters():
            g = dict(nets[k].named_parameters())[name].grad
            assert g is not None and p.grad is not None
            assert torch.equal(p.grad[4 * k:4 * k + 4], g), name
