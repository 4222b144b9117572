"""Dense and sparse ("OcTree") multi-resolution feature grids, the paper's alternative to the hash grid.

``DenseGrid``: one dense vertex lattice per level, no hashing, trilinear interpolation; parameters
grow with the tile *volume*. ``OctreeGrid``: the same lattices, but only the vertices of cells near
the data are allocated (each level's occupied cells, dilated); lookups of unallocated vertices read
zeros. It mimics the feature octree of Kaolin Wisp that the paper used (4 levels, leaf voxel 0.5 m,
``N_F = 4`` features per level; see :func:`octree_config`) with sorted keys instead of a pointer tree.

Both implement :class:`fusion.grids.hash.FeatureGrid`: inputs are normalised tile-box coordinates
``x01`` ``(n, 3)`` in [0, 1]³, outputs ``(n, num_levels · features_per_level)``, inactive levels
(progressive LOD) output zeros. Features are differentiable in ``x01``, so pose gradients flow.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from fusion.config import FusionConfig
from fusion.grids.base import FeatureGrid, gather_rows

CORNERS = [[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)]


class DenseGrid(FeatureGrid):
    """Multi-resolution dense feature grid.

    Args:
        num_levels, features_per_level: as in the hash grid.
        base_resolution, max_resolution: cells along the longest axis at the coarsest / finest level
            (geometric growth; ``max = base · 2^(L-1)`` gives octree-style halving).
        aspect: extent of each axis relative to the longest one, so cells stay cubic in metres.
        max_level_vertices: refuse lattices larger than this (a dense 512³ level is 0.5 GB).
    """

    cells: Tensor  # (L, 3) cells per axis, float
    verts: Tensor  # (L, 3) lattice vertices per axis
    offsets: Tensor  # (L,) first table row of each level
    corners: Tensor  # (8, 3) cell-corner offsets

    def __init__(
        self,
        num_levels: int = 4,
        features_per_level: int = 4,
        base_resolution: int = 16,
        max_resolution: int = 128,
        aspect: tuple[float, float, float] = (1.0, 1.0, 1.0),
        init_scale: float = 1e-4,
        max_level_vertices: int = 2**27,
    ) -> None:
        super().__init__()
        self.num_levels = num_levels
        self.features_per_level = features_per_level
        self.out_dim = num_levels * features_per_level
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(num_levels - 1, 1))
        self.resolutions = [int(round(base_resolution * growth**lv)) for lv in range(num_levels)]
        cells = torch.tensor(
            [[max(1, math.ceil(r * a)) for a in aspect] for r in self.resolutions], dtype=torch.float32
        )
        verts = cells.long() + 1  # (L, 3) lattice vertices per axis
        sizes = verts.prod(-1)
        if int(sizes.max()) > max_level_vertices:
            raise ValueError(
                f"dense level of {int(sizes.max())} vertices exceeds {max_level_vertices}; "
                "lower max_resolution or use the sparse 'octree' grid"
            )
        self.register_buffer("cells", cells, persistent=False)  # (L, 3)
        self.register_buffer("verts", verts, persistent=False)  # (L, 3)
        offsets = torch.cat([torch.zeros(1, dtype=torch.long), sizes.cumsum(0)[:-1]])
        self.register_buffer("offsets", offsets, persistent=False)  # (L,) first row of each level
        self.register_buffer("corners", torch.tensor(CORNERS, dtype=torch.long), persistent=False)  # (8, 3)
        self.active_levels = num_levels
        self.init_scale = init_scale
        self.table = nn.Parameter((torch.rand(int(sizes.sum()), features_per_level) * 2 - 1) * init_scale)

    def set_active_levels(self, k: int) -> None:
        self.active_levels = max(1, min(int(k), self.num_levels))

    def finest_active_cell(self) -> float:
        return 1.0 / self.resolutions[self.active_levels - 1]

    def _corner_indices(self, x01: Tensor, levels: int) -> tuple[Tensor, Tensor]:
        """Per point, level and cell corner: flat lattice index ``(n, l, 8)`` (level-local) and
        trilinear weight ``(n, l, 8)`` (differentiable in ``x01``)."""
        cells = self.cells[:levels]  # (l, 3)
        pos = x01.clamp(0.0, 1.0)[:, None, :] * cells  # (n, l, 3) in cell units
        base = pos.detach().floor().clamp_max(cells - 1)  # x = 1 stays in the last cell
        frac = pos - base
        ib = base.long()[:, :, None, :] + self.corners  # (n, l, 8, 3)
        v = self.verts[:levels]
        flat = ib[..., 0] + v[:, None, 0] * (ib[..., 1] + v[:, None, 1] * ib[..., 2])
        c = self.corners.to(frac.dtype)
        w = (frac[:, :, None, :] * c + (1 - frac[:, :, None, :]) * (1 - c)).prod(-1)
        return flat, w

    def _lookup(self, flat: Tensor, levels: int) -> Tensor:
        """Features ``(n, l, 8, F)`` at level-local lattice indices ``(n, l, 8)``."""
        idx = flat + self.offsets[:levels, None]
        return gather_rows(self.table, idx.reshape(-1)).view(*flat.shape, self.features_per_level)

    def forward(self, x01: Tensor) -> Tensor:
        """Features ``(n, L·F)`` of points ``(n, 3)`` in [0, 1]³ (clamped into the grid)."""
        n, levels = x01.shape[0], self.active_levels
        flat, w = self._corner_indices(x01, levels)
        out = (self._lookup(flat, levels) * w[..., None]).sum(2)  # (n, l, F)
        if levels < self.num_levels:
            out = torch.cat([out, out.new_zeros(n, self.num_levels - levels, self.features_per_level)], 1)
        return out.reshape(n, self.out_dim)


class OctreeGrid(DenseGrid):
    """Sparse variant: only lattice vertices of cells within ``dilation`` cells of the data exist.

    Call :meth:`allocate` with the data (normalised coordinates) before creating the optimiser; until
    then every vertex is allocated (a dense grid). Allocated vertices are kept as sorted flat keys per
    level; a lookup binary-searches them and reads zeros where the vertex does not exist.
    """

    keys: Tensor  # (V,) sorted flat keys (level offset + lattice index) of the allocated vertices

    def __init__(self, *args, dilation: int = 2, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.dilation = dilation
        self.register_buffer("keys", torch.zeros(0, dtype=torch.long))  # sorted level-offset keys
        self.allocated = False

    @torch.no_grad()
    def allocate(self, points01: Tensor) -> int:
        """Keeps the vertices of the cells around ``points01`` ``(m, 3)``; returns their count."""
        keys = []
        dev = self.cells.device
        points01 = points01.to(dev)
        d = torch.arange(-self.dilation, self.dilation + 2, device=dev)  # cells ± dilation, their vertices
        stencil = torch.stack(torch.meshgrid(d, d, d, indexing="ij"), -1).reshape(-1, 3)
        for lv in range(self.num_levels):
            cells, verts = self.cells[lv], self.verts[lv]
            cell = (points01.clamp(0, 1) * cells).floor().clamp_max(cells - 1).long().unique(dim=0)
            v = (cell[:, None, :] + stencil).reshape(-1, 3)
            v = v[((v >= 0) & (v < verts)).all(-1)]
            flat = v[:, 0] + verts[0] * (v[:, 1] + verts[1] * v[:, 2])
            keys.append(flat.unique() + self.offsets[lv])
        self.keys = torch.cat(keys)  # sorted: unique() sorts, level offsets increase
        self.table = nn.Parameter(
            (torch.rand(len(self.keys), self.features_per_level, device=dev) * 2 - 1) * self.init_scale
        )
        self.allocated = True
        return len(self.keys)

    def _lookup(self, flat: Tensor, levels: int) -> Tensor:
        if not self.allocated:
            return super()._lookup(flat, levels)
        key = (flat + self.offsets[:levels, None]).reshape(-1)
        pos = torch.searchsorted(self.keys, key).clamp_max(len(self.keys) - 1)
        found = (self.keys[pos] == key).to(self.table.dtype)
        feats = gather_rows(self.table, pos) * found[:, None]
        return feats.view(*flat.shape, self.features_per_level)


def octree_config(
    config: FusionConfig, box_m: float, leaf_m: float = 0.5, levels: int = 4, features: int = 4
):
    """The paper's OcTree set-up on top of ``config``: ``levels`` levels halving from a leaf voxel of
    ``leaf_m`` metres over a tile box whose longest side is ``box_m`` metres, ``features`` per level."""
    finest = max(2, round(box_m / leaf_m))
    return config.with_(
        grid_type="octree",
        num_levels=levels,
        features_per_level=features,
        max_resolution=finest,
        base_resolution=max(1, round(finest / 2 ** (levels - 1))),
        lod_start_levels=min(config.lod_start_levels, max(1, levels // 2)),
    )


def grid_size_bytes(grid: nn.Module) -> int:
    """Stored size of a feature grid: its parameters plus persistent index buffers (bytes)."""
    params = sum(p.numel() * p.element_size() for p in grid.parameters())
    keys = getattr(grid, "keys", None)
    return params + (keys.numel() * 4 if isinstance(keys, Tensor) else 0)  # keys fit int32 on disk
