"""The narrow-band SDF volume of a tile on the global extraction lattice (``fusion.extract`` meshes it).

Lattice: points at integer multiples of ``voxel_m`` in the *map* frame, so neighbouring tiles' lattices
coincide. The SDF is first evaluated on a coarse lattice (every ``block`` voxels, one block beyond the tile
so both neighbours take the same decision on shared planes); the band is taken again on half blocks, and
only the (half) blocks near the surface are evaluated at full resolution; the rest are filled with the
value at their block's lower corner (same sign as the whole block, so no zero crossing there by
construction). Blocks where no face the caller keeps can lie (``near``) are left out.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fusion.runtime import cpu_threads
from fusion.tiles import lattice_range
from fusion.types import TileSpec

SdfFn = Callable[[np.ndarray], np.ndarray]  # (n, 3) map-frame metres → (n,) signed distance
StepFn = Callable[[int, int], None]  # (done, total) progress
NearFn = Callable[[np.ndarray, float], np.ndarray]  # block centres (n, 3) map frame, half diagonal m → (n,) bool


@dataclass
class Lattice:
    """Global lattice indices of the tile's extraction volume: axis ``a`` spans ``k0[a] … k1[a]``."""

    voxel_m: float
    k0: tuple[int, int, int]
    k1: tuple[int, int, int]

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.k1[0] - self.k0[0] + 1, self.k1[1] - self.k0[1] + 1, self.k1[2] - self.k0[2] + 1)


def tile_lattice(tile: TileSpec, z_min: float, z_max: float, voxel_m: float) -> Lattice:
    """Lattice of a tile (map frame): lattice points inside the closed tile square × [z_min, z_max]."""
    (x0, x1), (y0, y1) = (lattice_range(lo, hi, voxel_m, inside=True) for lo, hi in zip(tile.xy_min, tile.xy_max, strict=True))
    z0, z1 = lattice_range(z_min, z_max, voxel_m)
    return Lattice(voxel_m, (x0, y0, z0), (x1, y1, z1))


def _eval(fn: SdfFn, k: np.ndarray, voxel_m: float) -> np.ndarray:
    return np.asarray(fn(k.astype(np.float64) * voxel_m), dtype=np.float64)


def narrow_band_sdf(
    sdf_fn: SdfFn,
    lat: Lattice,
    block: int,
    band_factor: float = 0.75,
    step: StepFn | None = None,
    strip_points: int = 1 << 22,
    near: NearFn | None = None,
    refine: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """SDF volume (nx, ny, nz) float32 on the lattice and the mask of exactly evaluated points.

    The volume is filled in x-strips of about ``strip_points`` lattice points (coarse fill, then exact
    values in the band), so no full-volume float64 temporaries or index arrays exist: at 128 m and
    0.1 m (~4e8 points) the peak is the float32 volume and the mask, not ~13 GB of intermediates.
    ``step(done, total)`` is called after the coarse pass and after each strip.

    ``refine``: while the block size is even and above 2, the band is taken again on half blocks (the
    corners of the half blocks inside band blocks are evaluated; ``_refine``), so the exact points are those
    of the half blocks near the surface rather than of every point of a band block (a 4-voxel block's band
    is three blocks thick around a surface: ~12 voxels of points, ~6 after one halving).

    ``near(centres, half_diagonal_m)``: (n,) bool per band block (its centre, map frame), False where no
    face the caller keeps can lie within the block; such blocks are left out of the band (filled like the
    blocks outside it, their half blocks too) unless they touch the tile's x or y border planes, which stay
    exact so the seam values neighbours pin to are the same either way. Where the field is left untrained
    (beyond the data) it sits near zero, and the band would otherwise cover almost the whole lattice.
    """
    b, v = block, lat.voxel_m
    c0 = [math.floor(lat.k0[a] / b) - (1 if a < 2 else 0) for a in range(3)]
    c1 = [math.ceil(lat.k1[a] / b) + (1 if a < 2 else 0) for a in range(3)]
    axes = [np.arange(c0[a], c1[a] + 1) * b for a in range(3)]
    ck = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    coarse = _eval(sdf_fn, ck, v).reshape(*(len(ax) for ax in axes))
    band = _band(coarse, band_factor * math.sqrt(3) * b * v)
    dropped = None
    if near is not None:
        border = [_containing(np.array([lat.k0[a], lat.k1[a]]) - c0[a] * b, b, band.shape[a]) for a in (0, 1)]
        dropped = _far_blocks(band, near, c0, b * v, [np.concatenate(pair) for pair in border])
        band &= ~dropped
    # halve the blocks while they are even: the corners of the half blocks inside band blocks are evaluated,
    # the band is taken again on them, and only the half blocks in it are evaluated at every lattice point
    # (half blocks of a block ``near`` dropped stay out: their filled corners are not one-signed)
    while refine and b % 2 == 0 and b > 2:
        coarse, band, c0, b = _refine(sdf_fn, coarse, band, c0, b, v, band_factor)
        if dropped is not None:
            dropped = dropped.repeat(2, axis=0).repeat(2, axis=1).repeat(2, axis=2)
            band &= ~dropped
    # a fine point is exact when any block containing it is in the band: per axis, the block holding
    # it ("first") and, on a block boundary, the block below ("second"); the OR over the 8 choices is
    # separable, so it is taken one axis at a time (x, y on the small coarse arrays, z per strip)
    first, second = zip(*(_containing(np.arange(lat.k0[a], lat.k1[a] + 1) - c0[a] * b, b, band.shape[a])
                          for a in range(3)), strict=True)
    band_x = band[first[0]] | band[second[0]]  # (nx, cy, cz)
    band_xy = band_x[:, first[1]] | band_x[:, second[1]]  # (nx, ny, cz)
    # fill value of a point outside the band: the coarse SDF at its block's lower corner. Every block
    # holding such a point is outside the band, so all its corners share that sign and |s| >= thr:
    # no cube without an exact corner has a zero crossing, and marching cubes skips those cubes.
    fill_xy = coarse[first[0]][:, first[1]].astype(np.float32)  # (nx, ny, cz + 1)
    vol = np.empty(lat.shape, np.float32)
    mask = np.empty(lat.shape, bool)
    # along z, "first" is a run of equal block indices: np.repeat copies runs (several times faster
    # than a gather); "second" differs from "first" only on block-boundary planes
    z_blocks, z_runs = np.unique(first[2], return_counts=True)
    z_edge = np.flatnonzero(second[2] != first[2])
    width = max(1, strip_points // (lat.shape[1] * lat.shape[2]))
    total = 1 + -(-lat.shape[0] // width)
    if step:
        step(1, total)
    for xa in range(0, lat.shape[0], width):
        xb = min(lat.shape[0], xa + width)
        strip = mask[xa:xb]
        strip[:] = np.repeat(band_xy[xa:xb][:, :, z_blocks], z_runs, axis=2)
        strip[:, :, z_edge] |= band_xy[xa:xb][:, :, second[2][z_edge]]
        vol[xa:xb] = np.repeat(fill_xy[xa:xb][:, :, z_blocks], z_runs, axis=2)
        where = np.argwhere(strip)
        if len(where):
            where[:, 0] += xa
            vol[xa:xb][strip] = _eval(sdf_fn, where + np.asarray(lat.k0), v)
        if step:
            step(1 + -(-xb // width), total)
    return vol, mask


def _band(coarse: np.ndarray, thr: float) -> np.ndarray:
    """Band blocks of a block-corner grid of SDF values: a corner closer to the surface than ``thr`` or a
    sign change among the block's corners."""
    cs = np.stack([coarse[dx : coarse.shape[0] - 1 + dx, dy : coarse.shape[1] - 1 + dy, dz : coarse.shape[2] - 1 + dz]
                   for dx, dy, dz in itertools.product((0, 1), repeat=3)])
    return (np.abs(cs).min(0) < thr) | ((cs > 0).any(0) & (cs < 0).any(0))


def _containing(offsets: np.ndarray, b: int, blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """Per point (``offsets`` from the first block's lower corner, in lattice steps, along one axis) the
    block holding it and, on a block boundary, the block below (else the same block), clipped to ``blocks``."""
    first = np.minimum(offsets // b, blocks - 1)
    return first, np.where(offsets % b == 0, np.maximum(offsets // b - 1, 0), first)


def _refine(sdf_fn: SdfFn, coarse: np.ndarray, band: np.ndarray, c0: list[int], b: int, v: float,
            band_factor: float) -> tuple[np.ndarray, np.ndarray, list[int], int]:
    """The block-corner grid and band at half the block size: corners of half blocks in a band block are
    evaluated, the others take the coarse value at their block's lower corner (every block holding them is
    outside the band: one sign, |s| at least the band threshold, which is above the half blocks' own)."""
    h = b // 2
    first, second = zip(*(_containing(np.arange(2 * band.shape[a] + 1), 2, band.shape[a]) for a in range(3)),
                        strict=True)
    needed = band[first[0]] | band[second[0]]
    needed = needed[:, first[1]] | needed[:, second[1]]
    needed = needed[:, :, first[2]] | needed[:, :, second[2]]
    lower = [np.minimum(np.arange(2 * band.shape[a] + 1) // 2, coarse.shape[a] - 1) for a in range(3)]
    fine = coarse[lower[0]][:, lower[1]][:, :, lower[2]]
    # the even points are the coarse corners themselves
    needed[::2, ::2, ::2] = False
    where = np.argwhere(needed)
    if len(where):
        fine[needed] = _eval(sdf_fn, (where + 2 * np.asarray(c0)) * h, v)
    return fine, _band(fine, band_factor * math.sqrt(3) * h * v), [2 * c for c in c0], h


def _far_blocks(band: np.ndarray, near: NearFn, c0: list[int], block_m: float,
                border_blocks: list[np.ndarray]) -> np.ndarray:
    """The band blocks (bool, ``band``'s shape) ``near`` rules out, except those holding a border plane's
    points (``border_blocks``: their x and y block indices)."""
    far = np.zeros_like(band)
    held = np.argwhere(band)
    if not len(held):
        return far
    keep = np.asarray(near((held + np.asarray(c0) + 0.5) * block_m, math.sqrt(3) / 2 * block_m), bool)
    keep |= np.isin(held[:, 0], border_blocks[0]) | np.isin(held[:, 1], border_blocks[1])
    drop = held[~keep]
    far[drop[:, 0], drop[:, 1], drop[:, 2]] = True
    return far


def near_support(tree: cKDTree, radius_m: float, voxel_m: float) -> NearFn:
    """``narrow_band_sdf``'s ``near`` for ``supported_attrs``' rule: a block can hold a kept face only when
    a support point lies within ``radius_m`` of one of the face's vertices, which lie on a lattice cube's
    edges, so within a cube diagonal (plus a voxel of slack) of the block."""
    reach = radius_m + (math.sqrt(3) + 1) * voxel_m

    def fn(centres: np.ndarray, half_diagonal_m: float) -> np.ndarray:
        return np.isfinite(tree.query(centres, k=1, distance_upper_bound=reach + half_diagonal_m,
                                      workers=cpu_threads())[0])

    return fn


def cube_mask(exact: np.ndarray) -> np.ndarray:
    """skimage's marching-cubes mask: True at ``p`` when the cube whose upper corner is ``p`` has an
    exactly evaluated corner. Cubes with no exact corner lie in blocks outside the band whose values are
    filled with same-signed coarse values, so skipping them drops no surface (or in blocks ``near`` left out,
    whose faces would have no support)."""
    out = exact.copy()
    for dx, dy, dz in itertools.product((0, 1), repeat=3):
        if dx or dy or dz:
            out[dx:, dy:, dz:] |= exact[: exact.shape[0] - dx, : exact.shape[1] - dy, : exact.shape[2] - dz]
    return out
