"""Dense / sparse ("OcTree") feature grids against a trilinear reference; gradients w.r.t. x."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.interpolate import RegularGridInterpolator

from fusion.config import FusionConfig
from fusion.grids import make_grid
from fusion.grids.dense import DenseGrid, OctreeGrid, grid_size_bytes, octree_config
from fusion.grids.hash import HashGrid


def _reference(grid: DenseGrid, level: int, x01: np.ndarray) -> np.ndarray:
    """scipy trilinear interpolation of one level's lattice at ``x01`` (n, 3)."""
    cells = grid.cells[level].long().tolist()
    verts = [c + 1 for c in cells]
    start = int(grid.offsets[level])
    values = grid.table.detach()[start : start + int(np.prod(verts))].double().numpy()
    values = values.reshape(verts[2], verts[1], verts[0], -1).transpose(2, 1, 0, 3)  # x fastest → (x, y, z)
    axes = [np.arange(v) / c for v, c in zip(verts, cells, strict=True)]
    return RegularGridInterpolator(axes, values)(x01)


def test_dense_grid_matches_trilinear_reference() -> None:
    torch.manual_seed(0)
    grid = DenseGrid(
        num_levels=3, features_per_level=2, base_resolution=4, max_resolution=16, aspect=(1, 0.5, 0.25)
    )
    with torch.no_grad():
        grid.table.normal_()
    x = torch.rand(200, 3)  # every axis spans [0, 1]; the aspect only sets its number of cells
    out = grid(x).view(200, 3, 2).detach().double().numpy()
    for level in range(3):
        ref = _reference(grid, level, x.numpy())
        np.testing.assert_allclose(out[:, level], ref, rtol=1e-4, atol=1e-5)


def test_gradients_flow_to_x_and_table() -> None:
    torch.manual_seed(1)
    grid = DenseGrid(num_levels=2, features_per_level=2, base_resolution=3, max_resolution=6).double()
    with torch.no_grad():
        grid.table.normal_()
    x = (torch.rand(16, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: grid(p), (x,), eps=1e-6, atol=1e-5)
    grid(x).sum().backward()
    assert grid.table.grad is not None and grid.table.grad.abs().sum() > 0


def test_progressive_lod_zeros_inactive_levels() -> None:
    grid = DenseGrid(num_levels=4, features_per_level=3, base_resolution=2, max_resolution=16)
    grid.set_active_levels(2)
    out = grid(torch.rand(10, 3)).view(10, 4, 3)
    assert torch.all(out[:, 2:] == 0) and torch.any(out[:, :2] != 0)
    assert grid.finest_active_cell() == pytest.approx(1 / grid.resolutions[1])


def test_octree_matches_dense_near_data_and_is_smaller() -> None:
    torch.manual_seed(2)
    kw = dict(num_levels=3, features_per_level=4, base_resolution=8, max_resolution=32)
    dense, octree = DenseGrid(**kw), OctreeGrid(**kw)
    with torch.no_grad():
        dense.table.normal_()
    plane = torch.rand(2000, 3)
    plane[:, 2] = 0.5  # data on a horizontal plane
    count = octree.allocate(plane)
    with torch.no_grad():
        octree.table.copy_(dense.table[octree.keys])
    near = plane[:100] + torch.randn(100, 3) * 0.002
    torch.testing.assert_close(octree(near), dense(near))
    far = torch.rand(50, 3)
    far[:, 2] = 0.05
    assert torch.all(octree(far).view(50, 3, 4)[:, 2] == 0)  # finest level: nothing allocated there
    assert count < dense.table.shape[0] / 3
    assert grid_size_bytes(octree) < grid_size_bytes(dense) / 2


def test_factory_and_octree_config() -> None:
    grid = make_grid(
        "dense",
        (1, 1, 0.25),
        num_levels=2,
        features_per_level=2,
        log2_table_size=16,
        base_resolution=4,
        max_resolution=8,
    )
    assert isinstance(grid, DenseGrid) and grid.out_dim == 4
    assert isinstance(
        make_grid("octree", (1, 1, 1), num_levels=2, base_resolution=4, max_resolution=8), OctreeGrid
    )
    cfg = octree_config(FusionConfig(), box_m=80.0)
    assert cfg.grid_type == "octree" and cfg.num_levels == 4 and cfg.features_per_level == 4
    assert cfg.max_resolution == 160 and cfg.base_resolution == 20 and cfg.lod_start_levels <= 4
    hashgrid = HashGrid(
        num_levels=4, features_per_level=2, log2_table_size=10, base_resolution=4, max_resolution=32
    )
    assert grid_size_bytes(hashgrid) == hashgrid.table.numel() * 4


def test_dense_grid_refuses_huge_levels() -> None:
    with pytest.raises(ValueError, match="octree"):
        DenseGrid(num_levels=1, base_resolution=1024, max_resolution=1024, max_level_vertices=2**20)


@pytest.mark.parametrize("grid_type", ["dense", "octree"])
def test_field_builds_dense_grids_from_the_config(grid_type: str) -> None:
    from fusion.field import SemanticSDFField

    cfg = octree_config(FusionConfig(), box_m=16.0, leaf_m=1.0).with_(grid_type=grid_type)
    field = SemanticSDFField(cfg, torch.zeros(3), torch.tensor([16.0, 16.0, 4.0]))
    assert isinstance(field.grid, DenseGrid) and field.grid.out_dim == 16
    x = (torch.rand(7, 3) * torch.tensor([16.0, 16.0, 4.0])).requires_grad_(True)
    s, c_logit, logits = field(x)
    assert s.shape == (7,) and logits is not None and logits.shape[0] == 7
    s.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
