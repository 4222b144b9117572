"""Hash grid against a straightforward trilinear reference; continuity, x-gradients, LOD, the field."""

from __future__ import annotations

import itertools

import numpy as np
import torch

from fusion.config import FusionConfig
from fusion.field import SemanticSDFField
from fusion.grids.hash import PRIMES, HashGrid
from fusion.labels import NUM_CLASSES


def _reference(grid: HashGrid, x: np.ndarray) -> np.ndarray:
    """Trilinear interpolation written out per level and corner (numpy, float64)."""
    table = grid.table.detach().double().numpy()
    out = []
    for lv in range(grid.num_levels):
        cells = grid.cells[lv].numpy().astype(np.float64)
        verts = grid.verts[lv].numpy()
        pos = np.clip(x, 0, 1) * cells
        base = np.minimum(np.floor(pos), cells - 1)
        frac = pos - base
        acc = np.zeros((len(x), grid.features_per_level))
        for dx, dy, dz in itertools.product((0, 1), repeat=3):
            c = (base + [dx, dy, dz]).astype(np.int64)
            if bool(grid.dense[lv]):
                idx = c[:, 0] + verts[0] * (c[:, 1] + verts[1] * c[:, 2])
            else:
                idx = ((c[:, 0] * PRIMES[0]) ^ (c[:, 1] * PRIMES[1]) ^ (c[:, 2] * PRIMES[2])) & (grid.table_size - 1)
            w = np.prod(np.where([dx, dy, dz], frac, 1 - frac), axis=1)
            acc += w[:, None] * table[idx + int(grid.offsets[lv])]
        out.append(acc)
    return np.concatenate(out, axis=1)


def _grid(**kw: object) -> HashGrid:
    torch.manual_seed(0)
    g = HashGrid(num_levels=6, features_per_level=2, log2_table_size=12, base_resolution=4, max_resolution=64,
                 aspect=(1.0, 0.75, 0.25), init_scale=1.0, **kw)  # type: ignore[arg-type]
    return g


def test_grid_matches_dense_and_hashed_reference() -> None:
    g = _grid()
    assert bool(g.dense[0]) and not bool(g.dense[-1])  # both kinds of level are exercised
    x = torch.rand(500, 3, generator=torch.Generator().manual_seed(1))
    x[:5] = torch.tensor([[0, 0, 0], [1, 1, 1], [1, 0, 0.5], [-0.1, 1.2, 0.3], [0.5, 0.5, 1.0]])
    ref = _reference(g, x.double().numpy())
    assert np.allclose(g(x).detach().double().numpy(), ref, atol=1e-5)


def test_custom_gather_equals_advanced_indexing_including_gradients() -> None:
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(2))
    grads = []
    for custom in (True, False):
        g = _grid(custom_gather=custom)
        y = g(x)
        (y * torch.arange(y.shape[1])).sum().backward()
        grads.append((y.detach(), g.table.grad.clone()))
    assert torch.allclose(grads[0][0], grads[1][0])
    assert torch.allclose(grads[0][1], grads[1][1], atol=1e-6)


def test_grid_is_continuous_and_differentiable_in_x() -> None:
    g = _grid()
    x = torch.rand(200, 3, generator=torch.Generator().manual_seed(3)) * 0.98 + 0.01
    d = torch.randn(200, 3, generator=torch.Generator().manual_seed(4)) * 1e-5
    assert (g(x + d) - g(x)).abs().max() < 1e-2
    xd = x.double().requires_grad_(True)
    gd = _grid().double()
    assert torch.autograd.gradcheck(lambda p: gd(p).sum(-1), (xd[:20],), eps=1e-7, atol=1e-4)
    xg = x.clone().requires_grad_(True)
    g(xg).square().sum().backward()
    assert xg.grad is not None and torch.isfinite(xg.grad).all() and xg.grad.abs().sum() > 0


def test_progressive_lod_zeroes_fine_levels() -> None:
    g = _grid()
    g.set_active_levels(2)
    y = g(torch.rand(50, 3))
    assert y[:, 4:].abs().max() == 0 and y[:, :4].abs().max() > 0
    assert g.finest_active_cell() == 1.0 / g.resolutions[1]


def test_field_outputs_and_normalisation() -> None:
    cfg = FusionConfig.preset("cpu").with_(num_levels=4, lod_start_levels=2, max_resolution=64)
    lo, hi = torch.tensor([-8.0, -8.0, -3.0]), torch.tensor([72.0, 72.0, 17.0])
    f = SemanticSDFField(cfg, lo, hi)
    assert torch.allclose(f.norm(torch.stack([lo, hi])), torch.tensor([[0.0, 0, 0], [1, 1, 1]]))
    x = torch.rand(64, 3) * (hi - lo) + lo
    x.requires_grad_(True)
    s, c, logits = f(x)
    assert s.shape == (64,) and c.shape == (64,) and logits is not None and logits.shape == (64, NUM_CLASSES)
    grad = f.numerical_gradient(x, eps_m=f.finest_active_cell_m())
    assert grad.shape == (64, 3)
    grad.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert abs(f.finest_active_cell_m() - 80.0 / 64) < 1e-6


def _tiny_grid(custom: bool) -> HashGrid:
    torch.manual_seed(5)
    return HashGrid(num_levels=3, features_per_level=2, log2_table_size=6, base_resolution=2, max_resolution=8,
                    aspect=(1.0, 0.75, 0.5), init_scale=1.0, custom_gather=custom).double()


def test_fused_backward_passes_gradcheck_and_matches_reference_autograd() -> None:
    """The fused lookup's hand-written backward (table and x) against numerical derivatives (float64) and
    against plain autograd through ``forward_reference``, with all and with fewer (LOD) active levels."""
    g, ref = _tiny_grid(True), _tiny_grid(False)
    assert bool(g.dense[0]) and not bool(g.dense[-1])
    x = torch.rand(24, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64) * 1.1 - 0.05
    table = g.table.detach().clone().requires_grad_(True)
    xg = x.clone().requires_grad_(True)

    def fused(t: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(g, {"table": t}, (p,))

    assert torch.autograd.gradcheck(fused, (table, xg), eps=1e-6, atol=1e-6)
    weights = torch.randn(24, g.out_dim, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    for levels in (3, 2):
        grads = []
        for grid in (g, ref):
            grid.set_active_levels(levels)
            grid.table.grad = None
            xr = x.clone().requires_grad_(True)
            y = grid(xr)
            (y * weights).sum().backward()
            grads.append((y.detach(), grid.table.grad.clone(), xr.grad.clone()))
        for a, b in zip(grads[0], grads[1], strict=True):
            assert torch.allclose(a, b, atol=1e-12)


def test_a_moved_state_is_the_same_field_carried_by_the_motion() -> None:
    """``moved_state``: the new field at ``motion · x`` is the old one at ``x`` (SDF, confidence, labels, and
    the SDF's gradient turns with the motion); carrying twice composes; a state saved before fields had a
    frame loads as trained where it is queried."""
    from fusion.field import field_from_state, field_state, moved_state

    torch.manual_seed(0)
    cfg = FusionConfig.preset("tiny")
    field = SemanticSDFField(cfg, torch.tensor([0.0, 0.0, -2.0]), torch.tensor([10.0, 10.0, 3.0]))
    with torch.no_grad():  # a field with some structure: untrained grids are nearly constant
        for p in field.parameters():
            p.add_(torch.randn_like(p) * 0.1)
    state = field_state(field)

    def motion(yaw: float, t: list[float]) -> np.ndarray:
        m = np.eye(4)
        m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        m[:3, 3] = t
        return m

    first, second = motion(0.1, [0.3, -0.2, 0.05]), motion(-0.04, [0.1, 0.2, 0.0])
    x = torch.rand(200, 3, dtype=torch.float64) * torch.tensor([8.0, 8.0, 3.0]) + torch.tensor([1.0, 1.0, -1.0])

    def at(m: np.ndarray) -> torch.Tensor:
        return (x @ torch.from_numpy(m[:3, :3]).T + torch.from_numpy(m[:3, 3])).float().requires_grad_(True)

    moved = field_from_state(moved_state(state, first), cfg)
    x0 = x.float().requires_grad_(True)
    s0, c0, l0 = field(x0)
    s1, c1, l1 = moved(at(first))
    close = {"rtol": 1e-4, "atol": 1e-4}  # float32 through the frame
    assert torch.allclose(s0, s1, **close) and torch.allclose(c0, c1, **close) and torch.allclose(l0, l1, **close)
    g0 = torch.autograd.grad(s0.sum(), x0)[0].double()
    x1 = at(first)
    g1 = torch.autograd.grad(moved.sdf(x1).sum(), x1)[0].double()
    assert torch.allclose(g0 @ torch.from_numpy(first[:3, :3]).T, g1, rtol=1e-3, atol=1e-3)

    twice = field_from_state(moved_state(moved_state(state, first), second), cfg)
    assert torch.allclose(twice.sdf(at(second @ first)), s0, **close)
    legacy = {k: v for k, v in state.items() if k != "norm.frame"}
    assert torch.equal(field_from_state(legacy, cfg).sdf(x.float()), s0)
