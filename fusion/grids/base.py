"""The feature grid interface every encoding implements, and the row gather/scatter they share.

A grid maps normalised coordinates ``x01`` ``(n, 3)`` in [0, 1]³ (the tile box, see ``fusion.field``)
to features ``(n, out_dim)``, continuous and differentiable in ``x`` (pose gradients flow through it).
"""

from __future__ import annotations

from typing import TypedDict

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable


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
    """``table[idx]`` via the word-view gather, backward by 1-D ``index_add_`` per feature (both several
    times faster on CPU than advanced indexing or 2-column ``index_select`` / ``index_add_``)."""

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(idx)
        ctx.num_rows = table.shape[0]
        return gather_words(table, idx)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        (idx,) = ctx.saved_tensors
        return scatter_add_rows(ctx.num_rows, idx, grad.t()), None


def gather_rows(table: Tensor, idx: Tensor, custom: bool = True) -> Tensor:
    """Rows ``(m, f)`` of ``table`` ``(T, f)`` at flat indices ``idx`` ``(m,)``."""
    if custom:
        return _Gather.apply(table, idx)
    return table[idx]


def gather_words(table: Tensor, idx: Tensor) -> Tensor:
    """Rows of ``table`` ``(R, F)`` at ``idx`` (any shape, int32/int64) → ``(*idx.shape, F)``.

    A row of F=2 float32 is one 8-byte word: gathering the table viewed as 1-D int64 is several
    times faster on CPU than ``index_select`` of 2-column rows (and bit-exact)."""
    f = table.shape[1]
    word = {4: torch.int32, 8: torch.int64, 16: torch.complex128}.get(f * table.element_size())
    flat = idx.reshape(-1)
    if word is None or not table.is_contiguous():
        return table.index_select(0, flat).view(*idx.shape, f)
    rows = table.view(word).view(-1).index_select(0, flat)  # (m,) one word per row
    return rows.view(table.dtype).view(*idx.shape, f)


def scatter_add_rows(num_rows: int, idx: Tensor, values: Tensor) -> Tensor:
    """``(R, F)`` zeros with ``values`` ``(F, *idx.shape)`` added at rows ``idx``: one 1-D
    ``index_add_`` per feature (several times faster on CPU than ``index_add_`` of 2-column rows)."""
    flat = idx.reshape(-1)
    planar = values.new_zeros(values.shape[0], num_rows)  # (F, R)
    for k in range(values.shape[0]):
        planar[k].index_add_(0, flat, values[k].reshape(-1))
    if planar.shape[0] == 2 and planar.dtype in (torch.float32, torch.float64):
        # interleave the two planes as (re, im) pairs: ~10× faster than the strided transpose copy
        return torch.view_as_real(torch.complex(planar[0], planar[1]))  # (R, 2)
    return planar.t().contiguous()


class GridSizes(TypedDict, total=False):
    """Size arguments of ``make_grid`` (``log2_table_size`` is ignored by the dense grids)."""

    num_levels: int
    features_per_level: int
    log2_table_size: int
    base_resolution: int
    max_resolution: int
