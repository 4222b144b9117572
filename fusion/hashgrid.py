"""Feature grids: the ``FeatureGrid`` interface and a multi-resolution hash grid (instant-ngp style).

Inputs are normalised coordinates ``x01`` in [0, 1]³ (the tile box, see ``fusion.field``). Levels
whose cell count fits the table are indexed densely (no collisions); finer ones are hashed with the
instant-ngp primes. Trilinear interpolation makes features continuous and differentiable in ``x``
(pose gradients flow through the interpolation weights).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

PRIMES = (1, 2_654_435_761, 805_459_861)


class FeatureGrid(nn.Module):
    """Interface of a spatial feature grid: ``forward(x01: (n, 3)) -> (n, out_dim)``."""

    out_dim: int
    num_levels: int

    def set_active_levels(self, k: int) -> None:
        """Use only the ``k`` coarsest levels (finer ones output zeros): progressive LOD."""
        raise NotImplementedError

    def finest_active_cell(self) -> float:
        """Cell size of the finest active level along the longest axis, in normalised units."""
        raise NotImplementedError


class _Gather(torch.autograd.Function):
    """``table[idx]`` with an ``index_add_`` backward (faster on CPU than advanced indexing's
    sort-based ``index_put_``)."""

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(idx)
        ctx.num_rows = table.shape[0]
        return table.index_select(0, idx)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        (idx,) = ctx.saved_tensors
        out = torch.zeros(ctx.num_rows, grad.shape[1], dtype=grad.dtype, device=grad.device)
        out.index_add_(0, idx, grad)
        return out, None


def gather_rows(table: Tensor, idx: Tensor, custom: bool = True) -> Tensor:
    """Rows ``(m, f)`` of ``table`` ``(T, f)`` at flat indices ``idx`` ``(m,)``."""
    if custom:
        return _Gather.apply(table, idx)
    return table[idx]


class HashGrid(FeatureGrid):
    """Multi-resolution hash grid.

    Args:
        num_levels, features_per_level, log2_table_size: sizes as in instant-ngp.
        base_resolution, max_resolution: cells along the longest axis of [0, 1]³ at the coarsest /
            finest level (geometric growth).
        aspect: extent of each axis relative to the longest one (a 64 m × 64 m × 16 m tile box is
            ``(1, 1, 0.25)``) so cells stay cubic in metres.
    """

    def __init__(
        self,
        num_levels: int = 16,
        features_per_level: int = 2,
        log2_table_size: int = 16,
        base_resolution: int = 16,
        max_resolution: int = 2048,
        aspect: tuple[float, float, float] = (1.0, 1.0, 1.0),
        init_scale: float = 1e-4,
        custom_gather: bool = True,
    ) -> None:
        super().__init__()
        self.num_levels = num_levels
        self.features_per_level = features_per_level
        self.out_dim = num_levels * features_per_level
        self.table_size = 2**log2_table_size
        self.custom_gather = custom_gather
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(num_levels - 1, 1))
        res = [int(math.floor(base_resolution * growth**lv + 1e-6)) for lv in range(num_levels)]
        # per level, per axis: number of cells; the lattice has cells + 1 vertices per axis
        cells = torch.tensor([[max(1, math.ceil(r * a)) for a in aspect] for r in res], dtype=torch.float32)
        verts = cells.long() + 1
        dense = verts.prod(-1) <= self.table_size
        sizes = torch.where(dense, verts.prod(-1), torch.full_like(dense, self.table_size, dtype=torch.long))
        offsets = torch.cat([torch.zeros(1, dtype=torch.long), sizes.cumsum(0)])
        self.register_buffer("cells", cells, persistent=False)  # (L, 3)
        self.register_buffer("verts", verts, persistent=False)  # (L, 3)
        self.register_buffer("dense", dense, persistent=False)  # (L,)
        self.register_buffer("sizes", sizes, persistent=False)  # (L,)
        self.register_buffer("offsets", offsets[:-1].clone(), persistent=False)  # (L,)
        if bool(dense.any()) and not bool(dense[: int(dense.sum())].all()):
            raise ValueError("dense levels must be the coarsest ones")
        self.num_dense = int(dense.sum())
        corners = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=torch.long)
        corner_offsets = corners[:, 0] + verts[:, None, 0] * (corners[:, 1] + verts[:, None, 1] * corners[:, 2])
        self.register_buffer("dense_corner_offsets", corner_offsets, persistent=False)  # (L, 8)
        self.resolutions = res
        self.active_levels = num_levels
        self.table = nn.Parameter(
            (torch.rand(int(offsets[-1]), features_per_level) * 2 - 1) * init_scale
        )  # (sum of level sizes, F)

    def set_active_levels(self, k: int) -> None:
        self.active_levels = max(1, min(int(k), self.num_levels))

    def finest_active_cell(self) -> float:
        return 1.0 / self.resolutions[self.active_levels - 1]

    def forward(self, x01: Tensor) -> Tensor:
        """Features ``(n, L·F)`` of points ``(n, 3)`` in [0, 1]³ (clamped into the grid)."""
        n = x01.shape[0]
        levels = self.active_levels
        cells = self.cells[:levels]  # (l, 3)
        pos = x01.clamp(0.0, 1.0)[:, None, :] * cells  # (n, l, 3) in cell units
        base = pos.detach().floor().clamp_max(cells - 1)  # (n, l, 3), keeps x = 1 in the last cell
        frac = pos - base  # (n, l, 3), differentiable in x
        ib = base.long()
        nd = min(self.num_dense, levels)
        parts = []
        if nd > 0:  # dense levels: flat index of the base vertex + per-level corner offsets
            v = self.verts[:nd]
            flat = ib[:, :nd, 0] + v[:, 0] * (ib[:, :nd, 1] + v[:, 1] * ib[:, :nd, 2])  # (n, nd)
            parts.append(flat[:, :, None] + self.dense_corner_offsets[:nd])  # (n, nd, 8)
        if levels > nd:  # hashed levels: xor of per-axis prime products, corners by broadcasting
            ih = ib[:, nd:levels]
            hx = torch.stack([ih[..., 0], ih[..., 0] + 1], -1) * PRIMES[0]  # (n, lh, 2)
            hy = torch.stack([ih[..., 1], ih[..., 1] + 1], -1) * PRIMES[1]
            hz = torch.stack([ih[..., 2], ih[..., 2] + 1], -1) * PRIMES[2]
            h = hx[..., :, None, None] ^ hy[..., None, :, None] ^ hz[..., None, None, :]
            parts.append(h.reshape(n, levels - nd, 8) & (self.table_size - 1))
        idx = (parts[0] if len(parts) == 1 else torch.cat(parts, 1)) + self.offsets[:levels, None]
        feats = gather_rows(self.table, idx.reshape(-1), self.custom_gather)
        feats = feats.view(n, levels, 8, self.features_per_level)
        wx = torch.stack([1 - frac[..., 0], frac[..., 0]], -1)  # (n, l, 2)
        wy = torch.stack([1 - frac[..., 1], frac[..., 1]], -1)
        wz = torch.stack([1 - frac[..., 2], frac[..., 2]], -1)
        w = (wx[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :]).reshape(n, levels, 8)
        out = (feats * w[..., None]).sum(2)  # (n, l, F)
        if levels < self.num_levels:
            pad = out.new_zeros(n, self.num_levels - levels, self.features_per_level)
            out = torch.cat([out, pad], dim=1)
        return out.reshape(n, self.out_dim)


def make_grid(grid_type: str, aspect: tuple[float, float, float], **kwargs: int) -> FeatureGrid:
    """Feature grid by name: "hash" here, "dense" / "octree" in ``fusion.densegrid``."""
    if grid_type == "hash":
        return HashGrid(aspect=aspect, **kwargs)
    if grid_type in ("dense", "octree"):
        from fusion.densegrid import make_dense_grid

        return make_dense_grid(grid_type, aspect, **kwargs)
    raise NotImplementedError(f"grid_type {grid_type!r} is not implemented yet (available: 'hash')")
