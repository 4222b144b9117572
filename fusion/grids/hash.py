"""A multi-resolution hash grid (instant-ngp style), the default ``FeatureGrid``.

Inputs are normalised coordinates ``x01`` in [0, 1]³ (the tile box, see ``fusion.field``). Levels
whose cell count fits the table are indexed densely (no collisions); finer ones are hashed with the
instant-ngp primes. Trilinear interpolation makes features continuous and differentiable in ``x``
(pose gradients flow through the interpolation weights).

CPU performance (``python -m fusion.eval.perf``): all levels are looked up at once by ``_Interp``, a custom
autograd Function: int32 corner indices into the concatenated table (per-level offsets, dense
indexing for coarse levels), trilinear weights computed once, one gather of every corner of every
level (the F=2 float32 row read as one int64 word), feature-planar / point-minor layout so the
elementwise work vectorises, and a hand-written backward (1-D ``index_add_`` per feature into the
table, analytic gradient w.r.t. ``x``). ``forward_reference`` (``custom_gather=False``) is the same
function in plain autograd ops; the tests check one against the other.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from fusion.grids.base import FeatureGrid, gather_words, scatter_add_rows

PRIMES = (1, 2_654_435_761, 805_459_861)


class HashGrid(FeatureGrid):
    """Multi-resolution hash grid.

    Args:
        num_levels, features_per_level, log2_table_size: sizes as in instant-ngp.
        base_resolution, max_resolution: cells along the longest axis of [0, 1]³ at the coarsest /
            finest level (geometric growth).
        aspect: extent of each axis relative to the longest one (a 64 m × 64 m × 16 m tile box is
            ``(1, 1, 0.25)``) so cells stay cubic in metres.
    """

    # non-persistent buffers (registered in ``__init__``)
    cells: Tensor  # (L, 3) cells per axis, float
    verts: Tensor  # (L, 3) lattice vertices per axis
    dense: Tensor  # (L,) level is indexed densely
    sizes: Tensor  # (L,) table rows of each level
    offsets: Tensor  # (L,) first table row of each level
    dense_corner_offsets: Tensor  # (L, 8)
    verts32: Tensor  # (L, 3) int32
    dense_corner_rows: Tensor  # (L, 8) int32
    offsets32: Tensor  # (L,) int32
    primes32: Tensor  # (3,) int32

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
        # int32 copies for the fused path (row indices < 2³¹; hashing wraps modulo 2³² like uint32)
        self.register_buffer("verts32", verts.to(torch.int32), persistent=False)  # (L, 3)
        self.register_buffer("dense_corner_rows", (corner_offsets + offsets[:-1, None]).to(torch.int32),
                             persistent=False)  # (L, 8) corner offsets + level offset
        self.register_buffer("offsets32", offsets[:-1].to(torch.int32), persistent=False)  # (L,)
        primes = [p - 2**32 if p >= 2**31 else p for p in PRIMES]  # same low 32 bits, as int32
        self.register_buffer("primes32", torch.tensor(primes, dtype=torch.int32), persistent=False)  # (3,)
        if int(offsets[-1]) >= 2**31:
            raise ValueError("hash grid tables beyond 2³¹ rows are not supported")
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
        if not self.custom_gather:
            return self.forward_reference(x01)
        n = x01.shape[0]
        levels = self.active_levels
        x01 = x01.to(self.table.dtype)
        idx, frac = self._corners(x01.detach(), levels)  # (8, l, n) int32, (3, l, n)
        out = _Interp.apply(self.table, x01, frac, idx, self.cells[:levels])  # (n, l, F)
        if levels < self.num_levels:
            pad = out.new_zeros(n, self.num_levels - levels, self.features_per_level)
            out = torch.cat([out, pad], dim=1)
        return out.reshape(n, self.out_dim)

    def _corners(self, x01: Tensor, levels: int) -> tuple[Tensor, Tensor]:
        """Row indices (int32) of the 8 lattice corners of every active level into the concatenated
        table, and the fractional position in the cell, for points ``(n, 3)`` (no autograd).

        Point-minor layout (corner / axis, level, point) so every elementwise op runs on long
        contiguous rows. Returns idx ``(8, l, n)`` (corner = 4·dx + 2·dy + dz) and frac ``(3, l, n)``."""
        n = x01.shape[0]
        cells = self.cells[:levels].to(x01.dtype).t()[:, :, None]  # (3, l, 1)
        xt = x01.clamp(0.0, 1.0).t().contiguous()  # (3, n)
        pos = xt[:, None, :] * cells  # (3, l, n) in cell units
        base = pos.floor().clamp_max_(cells - 1)  # (3, l, n), keeps x = 1 in the last cell
        frac = pos.sub_(base)  # (3, l, n); pos is a temporary
        ib = base.to(torch.int32)  # (3, l, n)
        nd = min(self.num_dense, levels)
        idx = torch.empty(8, levels, n, dtype=torch.int32, device=x01.device)
        if nd > 0:  # dense levels: flat index of the base vertex + per-level corner offsets
            v = self.verts32[:nd, :, None]  # (nd, 3, 1)
            flat = ib[1, :nd].mul(v[:, 0]).addcmul_(ib[2, :nd], v[:, 0] * v[:, 1]).add_(ib[0, :nd])  # (nd, n)
            torch.add(flat, self.dense_corner_rows[:nd].t()[:, :, None], out=idx[:, :nd])  # (8, nd, n)
        if levels > nd:  # hashed levels: xor of per-axis prime products (int32 wraps like uint32)
            lh = levels - nd
            hp = ib[:, nd:].mul(self.primes32[:, None, None])  # (3, lh, n): i·p
            h2 = torch.stack([hp, hp + self.primes32[:, None, None]], 1)  # (3, 2, lh, n): i·p, (i + 1)·p
            hxy = (h2[0, :, None] ^ h2[1, None, :]).view(4, 1, lh, n)
            h = (hxy ^ h2[2, None, :]).view(8, lh, n)
            torch.add(h.bitwise_and_(self.table_size - 1), self.offsets32[nd:levels, None], out=idx[:, nd:])
        return idx, frac

    def forward_reference(self, x01: Tensor) -> Tensor:
        """The same features written with plain autograd ops (advanced indexing): the reference that the
        fused ``_Interp`` path is tested against."""
        n = x01.shape[0]
        levels = self.active_levels
        cells = self.cells[:levels].to(x01.dtype)  # (l, 3)
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
        feats = self.table[idx.reshape(-1)]
        feats = feats.view(n, levels, 8, self.features_per_level)
        w = _corner_weights(frac)  # (n, l, 8)
        out = (feats * w[..., None]).sum(2)  # (n, l, F)
        if levels < self.num_levels:
            pad = out.new_zeros(n, self.num_levels - levels, self.features_per_level)
            out = torch.cat([out, pad], dim=1)
        return out.reshape(n, self.out_dim)


def _axis_weights(frac: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-axis linear weights ``(…, 2)`` (for the lower and upper vertex) of ``frac`` ``(…, 3)``."""
    w = torch.stack([1 - frac, frac], -1)  # (…, 3, 2)
    return w[..., 0, :], w[..., 1, :], w[..., 2, :]


def _corner_weights(frac: Tensor) -> Tensor:
    """Trilinear weights ``(…, 8)`` of the 8 corners (x major, z minor) from ``frac`` ``(…, 3)``."""
    wx, wy, wz = _axis_weights(frac)
    wxy = (wx[..., :, None] * wy[..., None, :]).flatten(-2)  # (…, 4)
    return (wxy[..., :, None] * wz[..., None, :]).flatten(-2)  # (…, 8)


class _Interp(torch.autograd.Function):
    """Fused trilinear lookup of all active levels: one gather of the 8 corners of every level from the
    concatenated table, weighted sum; backward scatters into the table (1-D ``index_add_`` per
    feature) and, when ``x01`` needs it, returns the gradient w.r.t. ``x01`` (pose gradients).

    Inputs: table ``(R, F)``, x01 ``(n, 3)`` (only its clamp mask is used), frac ``(3, l, n)`` (no
    grad), idx ``(8, l, n)`` int32, cells ``(l, 3)``. Output ``(n, l, F)``."""

    @staticmethod
    def forward(ctx, table: Tensor, x01: Tensor, frac: Tensor, idx: Tensor, cells: Tensor) -> Tensor:  # type: ignore[override]
        w3 = torch.stack([1 - frac, frac], 1)  # (3, 2, l, n): per-axis weights of the lower / upper vertex
        wxy = w3[0, :, None] * w3[1, None, :]  # (2, 2, l, n)
        w = (wxy[:, :, None] * w3[2, None, None, :]).flatten(0, 2)  # (8, l, n)
        feats = gather_words(table, idx).permute(3, 0, 1, 2).contiguous()  # (F, 8, l, n) feature-planar
        out = (feats * w).sum(1)  # (F, l, n)
        need_x = ctx.needs_input_grad[1]
        ctx.save_for_backward(idx, w, w3 if need_x else None, feats if need_x else None,
                              x01 if need_x else None, cells if need_x else None)
        ctx.num_rows = table.shape[0]
        return out.permute(2, 1, 0).contiguous()  # (n, l, F)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None, None, None, None]:  # type: ignore[override]
        idx, w, w3, feats, x01, cells = ctx.saved_tensors
        g = grad.permute(2, 1, 0).contiguous()  # (F, l, n)
        grad_table = grad_x = None
        if ctx.needs_input_grad[0]:
            grad_table = scatter_add_rows(ctx.num_rows, idx, w[None] * g[:, None])  # (R, F)
        if ctx.needs_input_grad[1]:
            gw = feats[0] * g[0]  # (8, l, n): dL/dw per corner
            for k in range(1, g.shape[0]):
                gw.addcmul_(feats[k], g[k])
            gw = gw.view(2, 2, 2, *gw.shape[1:])  # (x, y, z, l, n)
            wx, wy, wz = w3[0], w3[1], w3[2]  # (2, l, n) each
            dx = ((gw[1] - gw[0]) * (wy[:, None] * wz[None, :])).sum((0, 1))  # (l, n)
            dy = ((gw[:, 1] - gw[:, 0]) * (wx[:, None] * wz[None, :])).sum((0, 1))
            dz = ((gw[:, :, 1] - gw[:, :, 0]) * (wx[:, None] * wy[None, :])).sum((0, 1))
            gpos = torch.stack([dx, dy, dz])  # (3, l, n): d/dpos, pos = clamp(x01) · cells
            inside = (x01 >= 0) & (x01 <= 1)  # clamp's gradient mask, as torch.clamp
            grad_x = (gpos * cells.t()[:, :, None]).sum(1).t() * inside  # (n, 3)
        return grad_table, grad_x, None, None, None
