"""Tile maths in the map frame (torch-free).

Tile ``(i, j)`` covers ``x ∈ [i·S, (i+1)·S)``, ``y ∈ [j·S, (j+1)·S)`` and all heights (S = tile size,
metres); ``i`` and ``j`` may be negative. A point exactly on the border ``x = k·S`` lies in tile ``k``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from fusion.types import Pose, SemanticMesh, Sigma

# Relative tolerance for snapping lo/step, hi/step onto an integer (tile borders such as 64 / 0.2
# evaluate to 320.00000000000006 in floating point).
_SNAP = 1e-9


def _check_size(size_m: float) -> None:
    if not (math.isfinite(size_m) and size_m > 0):
        raise ValueError(f"tile size must be a positive number of metres, not {size_m!r}")


def tile_of(x: float, y: float, size_m: float) -> tuple[int, int]:
    """Tile (i, j) holding the map-frame point (x, y) in metres (floor division; negatives ok)."""
    _check_size(size_m)
    return math.floor(x / size_m), math.floor(y / size_m)


def tile_bounds(i: int, j: int, size_m: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """((x_min, y_min), (x_max, y_max)) of tile (i, j), map frame, metres; the max side is open."""
    _check_size(size_m)
    return (i * size_m, j * size_m), ((i + 1) * size_m, (j + 1) * size_m)


def tiles_for_box(
    xy_min: Sequence[float] | np.ndarray, xy_max: Sequence[float] | np.ndarray, size_m: float
) -> list[tuple[int, int]]:
    """Every tile a closed map-frame box [xy_min, xy_max] touches, ordered by i then j.

    A box whose max side lies exactly on ``x = k·S`` touches tile ``k`` (half-open tiles)."""
    if not all(math.isfinite(v) for v in (*xy_min, *xy_max)):
        raise ValueError("box bounds must be finite")
    if xy_min[0] > xy_max[0] or xy_min[1] > xy_max[1]:
        raise ValueError(f"box min {tuple(xy_min)} exceeds max {tuple(xy_max)}")
    i0, j0 = tile_of(xy_min[0], xy_min[1], size_m)
    i1, j1 = tile_of(xy_max[0], xy_max[1], size_m)
    return [(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)]


def _box_corners(bbox_min: np.ndarray, bbox_max: np.ndarray) -> np.ndarray:
    lo, hi = np.asarray(bbox_min, dtype=np.float64), np.asarray(bbox_max, dtype=np.float64)
    pick = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)], dtype=bool)
    return np.where(pick, hi, lo)


def posed_bbox(
    bbox_min_local: np.ndarray, bbox_max_local: np.ndarray, pose: Pose
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned map-frame box (min (3,), max (3,)) of a local-frame box moved by ``pose``
    (its 8 corners transformed)."""
    corners = pose.apply(_box_corners(bbox_min_local, bbox_max_local))
    return corners.min(axis=0), corners.max(axis=0)


def submap_tiles(
    bbox_min_local: np.ndarray,
    bbox_max_local: np.ndarray,
    pose: Pose,
    sigma: Sigma,
    size_m: float,
    n_sigma: float = 1.0,
) -> list[tuple[int, int]]:
    """Tiles a submap belongs to: its GPS-posed box grown by its pose uncertainty.

    The growth is ``n_sigma`` times ``sigma.trans_m`` plus the chord a rotation error of
    ``sigma.rot_deg`` sweeps at the box's farthest corner from the local origin (the pose rotates
    about that origin). Bounds in metres; ``bbox_*_local`` in the submap's local frame.
    """
    corners = _box_corners(bbox_min_local, bbox_max_local)
    radius = float(np.linalg.norm(corners, axis=1).max())
    angle = math.radians(n_sigma * sigma.rot_deg)
    lever = 2.0 * radius * math.sin(min(abs(angle), math.pi) / 2.0)
    grow = n_sigma * sigma.trans_m + lever
    lo, hi = posed_bbox(bbox_min_local, bbox_max_local, pose)
    return tiles_for_box(lo[:2] - grow, hi[:2] + grow, size_m)


def surface_tiles(
    vertices: np.ndarray, faces: np.ndarray, pose: Pose, size_m: float, band_m: float = 0.0
) -> list[tuple[int, int]]:
    """Tiles whose square, grown by ``band_m`` (xy, metres, >= 0), meets the map-frame xy
    bounding box of a face of the mesh posed by ``pose`` (local → map), ordered by i then j: where the
    surface lies, not its GPS uncertainty (:func:`submap_tiles`)."""
    _check_size(size_m)
    if not (math.isfinite(band_m) and band_m >= 0.0):
        raise ValueError(f"band must be a finite number of metres >= 0, not {band_m!r}")
    if len(faces) == 0:
        return []
    xy = pose.apply(np.asarray(vertices, dtype=np.float64))[:, :2]
    f = np.asarray(faces)
    # floor is monotone: the tile of a face's lowest corner is the lowest of its vertices' tiles
    lo_v = np.floor((xy - band_m) / size_m).astype(np.int64)
    hi_v = np.floor((xy + band_m) / size_m).astype(np.int64)
    lo = np.minimum(np.minimum(lo_v[f[:, 0]], lo_v[f[:, 1]]), lo_v[f[:, 2]])  # (F, 2)
    hi = np.maximum(np.maximum(hi_v[f[:, 0]], hi_v[f[:, 1]]), hi_v[f[:, 2]])
    found: set[tuple[int, int]] = set()
    for a0, a1, b0, b1 in _distinct_rows(np.concatenate([lo, hi], axis=1)):  # every tile of each distinct box
        found.update((i, j) for i in range(a0, b0 + 1) for j in range(a1, b1 + 1))
    return sorted(found)


def _distinct_rows(rows: np.ndarray) -> list[tuple[int, ...]]:
    """The distinct rows of ``rows`` ((N, k) integers, N > 0), through one int64 key per row (mixed radix
    over each column's range): ``np.unique(axis=0)`` sorts rows as opaque records, ~10x slower on a
    submap's faces."""
    base = rows.min(axis=0)
    span = rows.max(axis=0) - base + 1
    key = np.zeros(len(rows), np.int64)
    for c in range(rows.shape[1]):
        key = key * span[c] + (rows[:, c] - base[c])
    out = []
    for k in np.unique(key).tolist():
        row = []
        for c in reversed(range(rows.shape[1])):
            k, r = divmod(k, int(span[c]))
            row.append(int(base[c]) + r)
        out.append(tuple(reversed(row)))
    return out


def home_tile(
    mesh_or_point: SemanticMesh | tuple[np.ndarray, np.ndarray] | np.ndarray, pose: Pose, size_m: float
) -> tuple[int, int]:
    """Tile of the submap's posed centre: the tile that owns its refined pose.

    Accepts a ``SemanticMesh`` (centre of its local bounding box), a local bounding box
    ``(min, max)``, or a local centroid (3,); the centre is moved into the map frame by ``pose``."""
    if isinstance(mesh_or_point, SemanticMesh):
        vertices = np.asarray(mesh_or_point.vertices, dtype=np.float64)
        centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0
    elif isinstance(mesh_or_point, tuple):
        centre = (np.asarray(mesh_or_point[0], float) + np.asarray(mesh_or_point[1], float)) / 2.0
    else:
        centre = np.asarray(mesh_or_point, dtype=np.float64).reshape(3)
    x, y, _ = pose.apply(centre.reshape(1, 3))[0]
    return tile_of(float(x), float(y), size_m)


def _snap(value: float) -> float:
    nearest = round(value)
    return float(nearest) if abs(value - nearest) <= _SNAP * max(1.0, abs(value)) else value


def lattice_range(lo: float, hi: float, step: float, *, inside: bool = False) -> tuple[int, int]:
    """The global extraction lattice (multiples ``k·step``, metres, map frame) along one axis: the
    integer range [k0, k1] whose points cover [lo, hi], or with ``inside`` the points within it.

    ``lo``/``step`` and ``hi``/``step`` within floating-point noise of an integer count as that
    integer, so a tile border that is a multiple of ``step`` is a lattice point of both tiles and
    neighbouring tiles compute bit-identical coordinates ``k·step`` there."""
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"lattice step must be a positive number of metres, not {step!r}")
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise ValueError(f"lattice bounds must be finite with lo <= hi, not [{lo}, {hi}]")
    a, b = _snap(lo / step), _snap(hi / step)
    return (math.ceil(a), math.floor(b)) if inside else (math.floor(a), math.ceil(b))


# The sides of a tile's border: each names the neighbour across it and that neighbour's name for the
# same plane (the left neighbour's "x1" plane is our "x0").
ACROSS: dict[str, tuple[tuple[int, int], str]] = {
    "x0": ((-1, 0), "x1"), "x1": ((1, 0), "x0"), "y0": ((0, -1), "y1"), "y1": ((0, 1), "y0"),
}


def border_pins(i: int, j: int, border_of: Callable[[tuple[int, int]], dict[str, Any] | None]) -> dict[str, Any]:
    """Border samples of tile (i, j)'s fused neighbours keyed by *our* side (their opposite side's
    samples); ``border_of(key)`` gives a neighbour's ``FusionResult.border`` or None (not fused)."""
    pins: dict[str, Any] = {}
    for side, ((di, dj), theirs) in ACROSS.items():
        border = border_of((i + di, j + dj))
        if border and theirs in border:
            pins[side] = border[theirs]
    return pins
