"""Feature grids (``base``: the interface; ``hash``: the multi-resolution hash grid; ``dense``: dense
and sparse-octree grids, the paper's alternative). :func:`make_grid` builds one by name."""

from __future__ import annotations

from typing import Unpack

from fusion.grids.base import FeatureGrid, GridSizes
from fusion.grids.dense import DenseGrid, OctreeGrid
from fusion.grids.hash import HashGrid

GRID_TYPES = ("hash", "dense", "octree")


def make_grid(grid_type: str, aspect: tuple[float, float, float], **kwargs: Unpack[GridSizes]) -> FeatureGrid:
    """Feature grid by name (``FusionConfig.grid_type``); ``log2_table_size`` applies to "hash" only."""
    if grid_type == "hash":
        return HashGrid(aspect=aspect, **kwargs)
    dense_kwargs = {k: v for k, v in kwargs.items() if k != "log2_table_size"}
    if grid_type == "dense":
        return DenseGrid(aspect=aspect, **dense_kwargs)  # type: ignore[arg-type]
    if grid_type == "octree":
        return OctreeGrid(aspect=aspect, **dense_kwargs)  # type: ignore[arg-type]
    raise ValueError(f"unknown grid_type {grid_type!r} (one of {', '.join(GRID_TYPES)})")
