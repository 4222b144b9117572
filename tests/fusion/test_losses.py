"""The robust SDF data term (fusion.losses.robust_square)."""

from __future__ import annotations

import torch

from fusion.losses import robust_square


def test_robust_square_is_square_near_zero_and_linear_beyond_delta() -> None:
    r = torch.linspace(-2.0, 2.0, 401, dtype=torch.float64, requires_grad=True)
    loss = robust_square(r, 0.1)
    inside = r.detach().abs() <= 0.1
    assert torch.allclose(loss[inside], r[inside] ** 2)
    (grad,) = torch.autograd.grad(loss.sum(), r)
    assert grad.abs().max() <= 0.2 + 1e-12  # a contradicting sample pulls with at most 2·delta
    assert torch.allclose(grad[~inside].abs(), torch.full_like(grad[~inside], 0.2))
    assert torch.allclose(robust_square(r, 0.0), r**2)  # delta 0: the paper's squared term


def test_a_contradicting_minority_moves_a_robust_fit_little() -> None:
    """80 % of the samples say the surface is at 0, 20 % (another session's depth error) say 1 m: the
    squared term puts it at their mean, 0.2 m; the robust one at 0.025 m (2·δ·0.2 = 2·c·0.8, δ = 0.1)."""
    target = torch.cat([torch.zeros(80), torch.ones(20)]).double()
    fits = {}
    for delta in (0.0, 0.1):
        c = torch.zeros((), dtype=torch.float64, requires_grad=True)
        opt = torch.optim.SGD([c], lr=0.2)
        for _ in range(300):
            opt.zero_grad()
            robust_square(c - target, delta).mean().backward()
            opt.step()
        fits[delta] = float(c.detach())
    assert abs(fits[0.0] - 0.2) < 1e-6
    assert abs(fits[0.1] - 0.025) < 1e-6
