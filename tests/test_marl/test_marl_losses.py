"""The A2C loss against hand formulas, its sign, its mask, and a pinned short training."""

from __future__ import annotations

import pytest
import torch
from pinned_training import NATIVE_PINNED, weights_hash

from marl.a2c import a2c_losses


def _one_step(z: list[float], a: int, v: float, r: float, mask: float = 1.0):
    logits = torch.tensor(z, dtype=torch.float64).reshape(1, 1, 1, 4).requires_grad_(True)
    values = torch.tensor([v], dtype=torch.float64).reshape(1, 1, 1).requires_grad_(True)
    actions = torch.tensor([a]).reshape(1, 1, 1)
    returns = torch.tensor([r], dtype=torch.float64).reshape(1, 1, 1)
    m = torch.tensor([mask], dtype=torch.float64).reshape(1, 1, 1)
    return logits, values, a2c_losses(logits, actions, values, returns, m)


def test_terms_and_gradients_match_the_hand_formulas() -> None:
    z, a, v, r = [0.3, -1.0, 2.0, 0.5], 2, 1.5, 4.0
    logits, values, terms = _one_step(z, a, v, r)
    p = torch.softmax(torch.tensor(z, dtype=torch.float64), -1)
    adv = r - v
    assert terms["policy"].item() == pytest.approx(-torch.log(p[a]).item() * adv)
    assert terms["value"].item() == pytest.approx(0.5 * adv**2)
    h = -(p * torch.log(p)).sum()
    assert terms["entropy"].item() == pytest.approx(h.item())
    # d policy / dz = -(onehot(a) - p) * A: the advantage is a constant (detached)
    (g_pol,) = torch.autograd.grad(terms["policy"], logits, retain_graph=True)
    onehot = torch.nn.functional.one_hot(torch.tensor(a), 4).to(torch.float64)
    torch.testing.assert_close(g_pol.reshape(4), -(onehot - p) * adv)
    assert torch.autograd.grad(terms["policy"], values, retain_graph=True,
                               allow_unused=True)[0] is None
    # d value / dV = V - R
    (g_val,) = torch.autograd.grad(terms["value"], values, retain_graph=True)
    assert g_val.item() == pytest.approx(v - r)
    # d H / dz_k = -p_k (log p_k + H)
    (g_ent,) = torch.autograd.grad(terms["entropy"], logits)
    torch.testing.assert_close(g_ent.reshape(4), -p * (torch.log(p) + h))


@pytest.mark.parametrize(("ret", "up"), [(5.0, True), (-5.0, False)])
def test_one_descent_step_follows_the_sign_of_the_advantage(ret: float, up: bool) -> None:
    """Minimising the policy loss raises log pi(a) when A > 0 and lowers it when A < 0."""
    z, a = [0.0, 0.2, -0.1, 0.4], 1
    logits, _, terms = _one_step(z, a, 0.0, ret)
    terms["policy"].backward()
    before = torch.log_softmax(logits.detach(), -1)[..., a].item()
    after = torch.log_softmax(logits.detach() - 0.1 * logits.grad, -1)[..., a].item()
    assert (after > before) == up and abs(after - before) > 1e-3


def test_masked_steps_contribute_nothing_and_the_mean_is_over_valid_steps() -> None:
    torch.manual_seed(0)
    logits = torch.randn(3, 2, 1, 4, requires_grad=True)  # T = 3, N = 2, B = 1
    values = torch.randn(3, 2, 1, requires_grad=True)
    actions = torch.randint(0, 4, (3, 2, 1))
    returns = torch.randn(3, 1, 2)
    mask = torch.tensor([1.0, 1.0, 0.0]).reshape(3, 1, 1)
    terms = a2c_losses(logits, actions, values, returns, mask)
    sum(terms.values()).backward()
    assert torch.all(logits.grad[2] == 0) and torch.all(values.grad[2] == 0)
    assert torch.any(logits.grad[0] != 0)
    # value term: sum over agents and the two valid steps, divided by 2 (step, episode) pairs
    err = returns[:2] - values[:2].transpose(1, 2)
    assert terms["value"].item() == pytest.approx((0.5 * err.square().sum() / 2).item())


def test_advantage_normalisation_changes_only_the_policy_term() -> None:
    torch.manual_seed(1)
    logits = torch.randn(4, 1, 2, 4)
    values = torch.randn(4, 1, 2)
    actions = torch.randint(0, 4, (4, 1, 2))
    returns = 10.0 * torch.randn(4, 2, 1)
    mask = torch.ones(4, 2, 1)
    plain = a2c_losses(logits, actions, values, returns, mask, False)
    norm = a2c_losses(logits, actions, values, returns, mask, True)
    assert norm["value"] == plain["value"] and norm["entropy"] == plain["entropy"]
    assert norm["policy"] != plain["policy"]


@pytest.mark.parametrize("name", sorted(NATIVE_PINNED))
def test_native_training_is_pinned_per_processor_family(name: str) -> None:
    import platform

    digest, mode = weights_hash(name)
    cpu = f"{platform.processor() or platform.machine()}, {torch.backends.cpu.get_cpu_capability()}"
    assert mode == "native"
    assert digest in NATIVE_PINNED[name], f"{name}: weights hash {digest} on this CPU ({cpu})"


def test_an_agent_with_one_running_step_gets_a_zero_advantage() -> None:
    """One valid entry is its own mean: its standardised advantage is 0 (the running count is
    1, not a floor above it); masked entries do not count."""
    from marl.a2c import normalise_advantages

    adv = torch.tensor([[[3.0, -2.0]], [[5.0, 4.0]]])  # (T=2, B=1, N=2)
    mask = torch.tensor([[[1.0]], [[0.0]]])  # only t = 0 runs
    out = normalise_advantages(adv, mask)
    assert out[0].tolist() == [[0.0, 0.0]]
