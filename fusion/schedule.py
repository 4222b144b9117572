"""How many optimisation steps a tile or a region gets: in proportion to its content.

Every step draws a batch of a fixed size, so a tile's surface gets ``steps × batch / area`` samples per
square metre. A tile its submaps only graze (a few square metres inside it through their GPS
uncertainty or sensor range) reaches the same sample density with a fraction of the steps, so the
schedule scales with the surface the tile holds: the full schedule once the observed surface reaches
``schedule_full_cover`` × the tile box's ground area, proportionally less below, never under
``schedule_min_fraction`` of one tile's schedule: the field must also learn where there is nothing (an
undertrained field is confident everywhere and extracts surfaces all over the tile, see ``FusionConfig``).

Content is measured as the distinct ``schedule_voxel_m`` cubes that hold a surface sample, so sessions
driving the same street count once and the pool's size (capped) does not matter. It is a coarse
measure (a flat surface lying on a voxel boundary counts twice, so do sessions more than a voxel apart,
as before the alignment with GPS errors of a metre or two): enough to tell a grazed tile from a full
one; the one-tile bench's tile (0, 0) measures 1.9 full tiles (5 sessions; 1.8 with 3).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from fusion.config import FusionConfig

ArrayLike = Any  # numpy array, torch tensor or sequence of floats


def _numpy(x: ArrayLike) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, float)


def tile_content(points: np.ndarray | torch.Tensor, lo: ArrayLike, hi: ArrayLike, config: FusionConfig) -> float:
    """A tile's content as a fraction of a full tile, in [0, 1]: the distinct ``schedule_voxel_m`` cubes
    holding one of ``points`` ((N, 3), metres, the frame of ``lo``/``hi``), times a cube's face area,
    over ``schedule_full_cover`` × the ground area of the tile box ``lo``..``hi`` ((3,) corners)."""
    pts = _numpy(points)
    extent = _numpy(hi)[:2] - _numpy(lo)[:2]
    box_area_m2 = float(extent[0] * extent[1])
    if len(pts) == 0 or box_area_m2 <= 0:
        return 0.0
    cell = np.floor(pts / config.schedule_voxel_m).astype(np.int64)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 1
    occupied = len(np.unique((cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]))  # 10x np.unique(axis=0)
    surface_m2 = occupied * config.schedule_voxel_m**2
    return min(1.0, surface_m2 / (config.schedule_full_cover * box_area_m2))


def content_iterations(per_tile: int, contents: Sequence[float], config: FusionConfig) -> int:
    """Steps for ``contents`` (one ``tile_content`` per tile trained together):
    ``clamp(per_tile × Σ contents, floor, per_tile × len(contents))`` with
    ``floor = ceil(schedule_min_fraction × per_tile)``; a full tile gets ``per_tile``."""
    full = per_tile * len(contents)
    floor = math.ceil(config.schedule_min_fraction * per_tile)
    scaled = round(per_tile * sum(min(1.0, max(0.0, c)) for c in contents))
    return max(1, min(full, max(floor, scaled)))
