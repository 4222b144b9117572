"""Supervision samples for one tile: surface points (with SDF / normal / label targets) and space points.

Frames: submap meshes are in their *local* frames; poses map local → *tile* frame, which is the map
frame shifted by the tile origin (metres) so float32 keeps millimetre precision. Surface points are
pre-sampled once (area-weighted) in the local frames and moved by the *current* poses every batch, so
the SDF loss differentiates through the pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from fusion.types import SubmapInput


@dataclass
class SurfacePool:
    """Pre-sampled surface points, local frames. Shapes: P points, M submaps."""

    points: Tensor  # (P, 3) float32, local frame of its submap
    normals: Tensor  # (P, 3) float32, unit, local frame
    labels: Tensor  # (P,) int64
    submap: Tensor  # (P,) int64 index into the tile's submap list
    conf_target: Tensor  # (P,) float32 in [0, 1]: confidence target (cross-session consensus)


@dataclass
class SpaceBoxes:
    """Per-submap local boxes (AABB grown by a margin and a height allowance) for space samples."""

    lo: Tensor  # (M, 3) float32, local frame
    hi: Tensor  # (M, 3) float32, local frame
    weight: Tensor  # (M,) float32 sampling weight (box footprint inside the tile box)


@dataclass
class Batch:
    """One batch, tile frame (metres)."""

    surf_x: Tensor  # (n, 3) surface samples offset along the normal
    surf_sdf: Tensor  # (n,) target signed distance ŝ
    surf_normal: Tensor  # (n, 3) target unit normal
    surf_label: Tensor  # (n,) target label (0 = ignore)
    surf_conf: Tensor  # (n,) confidence target
    space_x: Tensor  # (m, 3) space samples


def face_geometry(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face areas (m,) m² and unit normals (m, 3) (winding: counter-clockwise = outward)."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    dbl = np.linalg.norm(cross, axis=1)
    return 0.5 * dbl, cross / np.maximum(dbl, 1e-12)[:, None]


def uniform_barycentric(count: int, rng: np.random.Generator, dtype: type = np.float64) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric weights (u, v), each (count, 1), of points uniform on a triangle: draws in the unit
    square folded into the lower half."""
    u, v = rng.random(count, dtype), rng.random(count, dtype)
    flip = u + v > 1
    return np.where(flip, 1 - u, u)[:, None], np.where(flip, 1 - v, v)[:, None]


def on_triangles(tri: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The points ``(1 - u - v)·a + u·b + v·c`` of triangles ``tri`` (n, 3, 3)."""
    return tri[:, 0] + u * (tri[:, 1] - tri[:, 0]) + v * (tri[:, 2] - tri[:, 0])


def sample_surface_pool(
    submaps: list[SubmapInput],
    init_tile: list[np.ndarray],
    box_lo: np.ndarray,
    box_hi: np.ndarray,
    num_points: int,
    rng: np.random.Generator,
    class_balance: float = 0.0,
    class_weight_max: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted points on all submap faces whose initially posed position lies in the tile box.

    ``init_tile``: (4, 4) local → tile pose per submap. Returns local points (P, 3), local normals
    (P, 3), labels (P,), submap index (P,).

    Class-balanced sampling: a face's weight is its area times ``class_weights`` of its label (rare
    classes, by the submaps' own labelled area, drawn more often), so thin or small classes (lane
    markings, signs, poles) get enough samples for the semantic head and the SDF; ``class_balance`` 0
    is plain area weighting. Faces whose posed bounding box misses the tile box are left out before
    drawing (a submap reaches 2-4 tiles, so most of its faces lie in another); the draw is conditioned on
    the box either way, so the distribution is the same.
    """
    areas, normals, tris, tris_tile, labels, owner = [], [], [], [], [], []
    all_labels, all_areas = [], []
    for k, sm in enumerate(submaps):
        a, n = face_geometry(sm.mesh.vertices, sm.mesh.faces)
        all_labels.append(sm.mesh.face_labels)
        all_areas.append(a)
        # the triangles posed in the tile frame: a point's tile position is the same barycentric
        # combination, so no per-point pose matrices are gathered
        posed = sm.mesh.vertices @ init_tile[k][:3, :3].T + init_tile[k][:3, 3]
        tri_tile = posed[sm.mesh.faces]
        keep = np.flatnonzero((a > 0) & np.all(tri_tile.min(axis=1) <= box_hi, axis=1)
                              & np.all(tri_tile.max(axis=1) >= box_lo, axis=1))
        areas.append(a[keep])
        normals.append(n[keep])
        tris.append(sm.mesh.vertices[sm.mesh.faces[keep]].astype(np.float32))
        tris_tile.append(tri_tile[keep].astype(np.float32))
        labels.append(sm.mesh.face_labels[keep])
        owner.append(np.full(len(keep), k))
    area = np.concatenate(areas) if areas else np.zeros(0)
    if area.size == 0 or area.sum() <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64)
    tri_all, tri_tile, nrm_all = np.concatenate(tris), np.concatenate(tris_tile), np.concatenate(normals)
    lab_all, own_all = np.concatenate(labels), np.concatenate(owner)
    # class shares from the whole submaps, as before the crop (a tile's own mix would re-weight per tile)
    per_class = class_weights(np.concatenate(all_labels), np.concatenate(all_areas), class_balance, class_weight_max)
    weight = area * per_class[lab_all]
    cdf = np.cumsum(weight)

    def draw(count: int) -> tuple[np.ndarray, ...]:
        # inverse-CDF sampling with sorted queries: face indices come out sorted, so the searches and
        # gathers below walk memory in order (~5× faster than rng.choice(p=...) over millions of faces)
        q = np.sort(rng.random(count)) * cdf[-1]
        f = np.minimum(np.searchsorted(cdf, q, side="right"), area.size - 1)
        u, v = uniform_barycentric(count, rng, np.float32)
        pt = on_triangles(tri_tile[f], u, v)
        inside = np.flatnonzero(np.all((pt >= box_lo) & (pt <= box_hi), axis=1))
        f, u, v = f[inside], u[inside], v[inside]
        p = on_triangles(tri_all[f], u, v)
        return p.astype(np.float64), nrm_all[f], lab_all[f], own_all[f]

    pilot = draw(20_000)
    frac = max(len(pilot[0]) / 20_000, 1e-3)
    out = draw(int(min(num_points / frac * 1.05 + 100, 20 * num_points)))
    extra = len(out[0]) - num_points
    if extra > 0:  # an unbiased subset of exactly num_points (the points are ordered by face)
        drop = rng.choice(len(out[0]), size=extra, replace=False)
        out = tuple(np.delete(a, drop, axis=0) for a in out)
    return out  # type: ignore[return-value]


def class_weights(labels: np.ndarray, area: np.ndarray, balance: float, max_weight: float) -> np.ndarray:
    """Sampling weight per label id (array indexable by label): ``(mean share / share_k) ** balance``
    for labelled classes rarer (by area) than the mean of the classes present, clipped to
    ``[1, max_weight]``; 1 for common classes and unlabeled (0). Shares come from the input submaps."""
    n = int(labels.max(initial=0)) + 1
    w = np.ones(n)
    if balance <= 0 or max_weight <= 1:
        return w
    per = np.bincount(labels, weights=area, minlength=n)
    per[0] = 0.0
    present = per > 0
    if present.sum() < 2:
        return w
    share = per / per.sum()
    mean = 1.0 / present.sum()
    w[present] = np.clip((mean / share[present]) ** balance, 1.0, max_weight)
    return w


def space_boxes(submaps: list[SubmapInput], height_m: float = 4.0, margin_m: float = 1.0) -> tuple[np.ndarray, ...]:
    """Local AABBs (M, 3) lo / hi of each submap, grown by ``margin_m`` and to at least ``height_m``
    above its lowest point so free space above flat submaps (roads) is sampled."""
    lo, hi = [], []
    for sm in submaps:
        v = sm.mesh.vertices
        a, b = v.min(0) - margin_m, v.max(0) + margin_m
        b[2] = max(b[2], a[2] + margin_m + height_m)
        lo.append(a)
        hi.append(b)
    return np.stack(lo), np.stack(hi)


def transform(poses: Tensor, index: Tensor, points: Tensor) -> Tensor:
    """Apply per-point poses ``poses[index]`` ((M, 4, 4) → (n, 4, 4)) to points ``(n, 3)``."""
    t = poses[index]
    return (t[:, :3, :3] @ points[:, :, None])[:, :, 0] + t[:, :3, 3]


def sample_batch(
    pool: SurfacePool,
    boxes: SpaceBoxes,
    poses: Tensor,
    tile_lo: Tensor,
    tile_hi: Tensor,
    n_surf: int,
    n_space: int,
    sigma_s: float,
    gen: torch.Generator,
) -> Batch:
    """Draw one batch. ``poses`` (M, 4, 4) float32 local → tile frame (gradients flow to surface samples).

    Surface points move along their posed normal by ŝ ~ N(0, σ_s) (target SDF ŝ). Space points are uniform
    in the posed submap boxes (pose detached) and kept inside the tile box ``[tile_lo, tile_hi]``.
    """
    dev = pool.points.device
    idx = torch.randint(pool.points.shape[0], (n_surf,), generator=gen, device="cpu").to(dev)
    sm = pool.submap[idx]
    p = transform(poses, sm, pool.points[idx])
    rot = poses[sm][:, :3, :3]
    # target normals follow the pose but carry no gradient: early, untrained field normals would
    # otherwise drag the rotations along
    nrm = (rot.detach() @ pool.normals[idx][:, :, None])[:, :, 0]
    s_hat = (torch.randn(n_surf, generator=gen, device="cpu") * sigma_s).to(dev)
    x = p + s_hat[:, None] * nrm

    want = int(n_space * 1.3) + 16
    box = torch.multinomial(boxes.weight.cpu(), want, replacement=True, generator=gen).to(dev)
    u = torch.rand(want, 3, generator=gen, device="cpu").to(dev)
    local = boxes.lo[box] + u * (boxes.hi[box] - boxes.lo[box])
    xs = transform(poses.detach(), box, local)
    inside = ((xs >= tile_lo) & (xs <= tile_hi)).all(-1)
    xs = xs[inside][:n_space]
    return Batch(x, s_hat, nrm, pool.labels[idx], pool.conf_target[idx], xs)


def calibrated_confidence(fraction: Tensor, keep_fraction: float, c_th: float) -> Tensor:
    """Confidence target from a consensus ``fraction``: piecewise linear, 0 → 0, ``keep_fraction`` →
    ``c_th``, 1 → 1, so extraction (which drops what the field puts below ``c_th``) keeps what at
    least ``keep_fraction`` of the observing sessions saw. With the fraction itself as the target
    (``keep_fraction`` = ``c_th``), a surface that 2 of 3 sessions saw (0.67 < 0.7: one had a hole
    there, or the edge of its field of view) was dropped like a parked car that 1 of 3 saw."""
    k = min(max(keep_fraction, 1e-6), 1 - 1e-6)
    low = fraction * (c_th / k)
    high = c_th + (fraction - k) * ((1 - c_th) / (1 - k))
    return torch.where(fraction <= k, low, high).clamp(0.0, 1.0)


def consensus_targets(
    pool_tile: Tensor, pool_session: Tensor, near_m: float, cover_m: float, max_cells: int = 1 << 27,
    keep_fraction: float | None = None, c_th: float = 0.7, normals: Tensor | None = None,
    column_m: float = 3.0, movable: Tensor | None = None, movable_sessions: int = 0,
    movable_cover_m: float = 0.0, overhang_m: float = 0.0, movable_below_m: float | None = None,
) -> Tensor:
    """Confidence target per pool point (P, 3) (tile frame, on any device): the fraction of the sessions
    with evidence about this surface that saw it (had a point within ~``near_m``).

    Evidence, without ``normals`` ("cover"): a session observed the neighbourhood (a point within
    ~``cover_m``). The road under a parked car that one session of five saw keeps ≈ 0.8, the car itself
    gets ≈ 0.2; a facade that only the sessions on its street could see keeps 1. But a session that saw
    the pavement at a wall's foot and not the wall (its camera pointed elsewhere) votes against the wall.

    With ``normals`` (P, 3) (posed, unit; "free space"): a session counts against a surface only if it
    saw through it: the first thing it has below the point (within ``column_m``, the point's column grown
    by ``near_m``) is an upward-facing surface, with nothing of its own in between. A parked car one
    session saw stands where the others saw bare road: dropped. The upper wall a session did not see
    stands above its lower wall (not upward-facing): no evidence, kept. A session that saw nothing there
    (another street, a hole) has no say either way. ``overhang_m`` > 0: nor does any session about a
    surface whose observer saw open ground at least that far beneath it (``_overhangs``: a sign plate or a
    tree crown, under which the others' rays passed).

    ``movable`` (P,) bool marks points of movable classes (vehicles, obstacles): where the pool holds at
    least ``movable_sessions`` sessions, such a point that fewer than ``movable_sessions`` of them saw
    gets 0, evidence or not. A car parked on a street that only one session drove has no session that saw
    through it, so the free-space rule keeps it; this rule asks a movable object for a second witness.
    A static car two sessions passed stays; with fewer sessions in the tile than that, nothing is asked.
    A witness is any surface of the session within ~``near_m``. ``movable_cover_m`` > 0: the second witness
    is asked for only where at least ``movable_sessions`` sessions were there (had any surface within
    ~``movable_cover_m``): a car parked on a street that one session alone drove is kept, as nothing says
    it was not there; where another session passed and did not see it, it is dropped.
    ``movable_below_m``: a movable point's witness must lie at most this far below it (within ~``near_m``
    above it and to the sides, as before). The road another session saw where a car one session saw
    stood is that session's evidence against the car (it saw through it), not a witness of its lower body.

    "Within r" is decided on occupancy grids (cells of r/2, r/4 for the cover), dilated by r with
    shifted ORs along each axis: a cube of half-width r up to one cell, not a ball. That is O(P + cells) per
    session on the pool's device instead of a nearest-neighbour query per point and session (42 s for
    the paper's 2 M points on 2 cores with k-d trees; the thresholds are heuristics either way).
    """
    near = torch.zeros(len(pool_tile), dtype=torch.int32, device=pool_tile.device)
    against = torch.zeros_like(near)
    if len(pool_tile) == 0:
        return near.float()
    near_hit = _within(pool_tile, pool_session, near_m, 2, max_cells)
    if normals is None:
        evidence = _within(pool_tile, pool_session, cover_m, 4, max_cells)
    else:
        evidence = _seen_through(pool_tile, normals, pool_session, near_m, column_m, max_cells, overhang_m)
    for hit_n, hit_e in zip(near_hit, evidence, strict=True):
        near += hit_n
        against += hit_e & ~hit_n
    fraction = (near / (near + against).clamp(min=1)).float()
    if movable is not None and 1 < movable_sessions <= len(near_hit):
        if movable_below_m is not None and movable_below_m < near_m and bool(movable.any()):
            level = _within(pool_tile, pool_session, near_m, 2, max_cells, below_m=movable_below_m)
            near = torch.where(movable, sum(h.int() for h in level), near)
        ask = movable & (near < movable_sessions)
        if movable_cover_m > 0:
            present = sum(h.int() for h in _within(pool_tile, pool_session, movable_cover_m, 2, max_cells))
            ask &= present >= movable_sessions
        fraction = torch.where(ask, torch.zeros_like(fraction), fraction)
    return fraction if keep_fraction is None else calibrated_confidence(fraction, keep_fraction, c_th)


UPWARD_MIN_NZ = 0.7  # a surface faces up (ground, a roof, a table) when its normal is within ~45° of +z


def _seen_through(points: Tensor, normals: Tensor, session: Tensor, near_m: float, column_m: float,
                  max_cells: int, overhang_m: float = 0.0) -> list[Tensor]:
    """Per session: (P,) bool, whether the first surface the session has below each point (more than
    ``near_m`` and at most ``column_m`` down, columns grown by ``near_m`` in x and y) faces up.

    ``overhang_m`` > 0: no session saw through a point that overhangs (``_overhangs``) by at least this."""
    cell, dims, idx = _cells(points, near_m / 2, max_cells)
    k = max(1, round(near_m / cell))
    deepest = int(column_m / cell + 1e-6)
    flat_xy = idx[:, 0] * dims[1] + idx[:, 1]
    up = normals[:, 2] >= UPWARD_MIN_NZ
    out = []
    overhang = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    for s in torch.unique(session):
        mine = session == s
        any_grid = torch.zeros(dims, dtype=torch.bool, device=points.device)
        up_grid = torch.zeros_like(any_grid)
        any_grid[idx[mine, 0], idx[mine, 1], idx[mine, 2]] = True
        up_grid[idx[mine & up, 0], idx[mine & up, 1], idx[mine & up, 2]] = True
        if overhang_m > 0:
            overhang[mine] = _overhangs(idx[mine], any_grid, up_grid, int(math.ceil(overhang_m / cell - 1e-6)),
                                        deepest)
        any_col = _dilate(any_grid, k, (0, 1)).view(-1, dims[2])
        up_col = _dilate(up_grid, k, (0, 1)).view(-1, dims[2])
        decided = torch.zeros(len(points), dtype=torch.bool, device=points.device)
        through = torch.zeros_like(decided)
        for d in range(k + 1, deepest + 1):
            z = idx[:, 2] - d
            ok = z >= 0
            zc = z.clamp(min=0)
            hit = any_col[flat_xy, zc] & ok & ~decided
            through |= hit & up_col[flat_xy, zc]
            decided |= hit
        out.append(through)
    return [t & ~overhang for t in out]


def _overhangs(idx: Tensor, any_grid: Tensor, up_grid: Tensor, gap_cells: int, deepest: int) -> Tensor:
    """(n,) bool for one session's points (cells ``idx`` (n, 3) of its occupancy grids): straight below the
    point's own surface (the occupied cells down from it) a clear gap of at least ``gap_cells`` cells, then
    an upward-facing surface of the session (within one cell across, sampling leaves cells empty), within
    ``deepest`` cells. The session saw open ground under it: a sign plate, a tree crown, a balcony. Another
    session that saw that ground did not see through it (its rays passed under it), so that is no evidence
    against it. A car or a wall standing on the ground reaches down to it (no gap) and stays open to the
    free-space evidence; so does a car's roof, whose observer could not see the road beneath it (up to a
    band one cell wide along the roof's edge)."""
    col = any_grid.view(-1, any_grid.shape[2])
    up_col = _dilate(up_grid, 1, (0, 1)).view(-1, up_grid.shape[2])
    flat = idx[:, 0] * any_grid.shape[1] + idx[:, 1]
    own = torch.ones(len(idx), dtype=torch.bool, device=idx.device)  # still on the point's own surface
    gap = torch.zeros(len(idx), dtype=torch.long, device=idx.device)
    decided = torch.zeros_like(own)
    result = torch.zeros_like(own)
    for d in range(1, deepest + 1):
        z = idx[:, 2] - d
        live = (z >= 0) & ~decided
        zc = z.clamp(min=0)
        occ = col[flat, zc]
        own &= occ
        below = live & ~own
        ground = below & up_col[flat, zc]
        result |= ground & (gap >= gap_cells)
        decided |= ground | (below & occ)  # the ground, or something else under the gap (a post, a second object)
        gap += (below & ~occ & ~ground).long()
    return result


def _cells(points: Tensor, cell: float, max_cells: int) -> tuple[float, list[int], Tensor]:
    """Cell size (grown ×1.5 until the grid has at most ``max_cells``), grid dims and each point's cell."""
    lo = points.min(0).values
    extent = points.max(0).values - lo
    while float(torch.prod(torch.floor(extent / cell) + 1)) > max_cells:  # huge boxes: coarser cells
        cell *= 1.5
    idx = torch.floor((points - lo) / cell).long()
    return cell, [int(d) + 1 for d in idx.max(0).values], idx


def _within(points: Tensor, session: Tensor, radius_m: float, cells_per_radius: int, max_cells: int,
            below_m: float | None = None) -> list[Tensor]:
    """Per session: (P,) bool, whether the session has a point within ``radius_m`` (cube, ±1 cell).
    ``below_m``: of the points below, only those within ``below_m`` (rounded to cells) count."""
    cell, dims, idx = _cells(points, radius_m / cells_per_radius, max_cells)
    k = max(1, round(radius_m / cell))
    down = k if below_m is None else min(k, round(below_m / cell))
    flat = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
    out = []
    for s in torch.unique(session):
        occ = torch.zeros(dims[0] * dims[1] * dims[2], dtype=torch.bool, device=points.device)
        occ[flat[session == s]] = True
        grown = _dilate(occ.view(*dims), k, (0, 1))
        out.append(_dilate(grown, k, (2,), down=down).reshape(-1)[flat])
    return out


def _dilate(grid: Tensor, k: int, axes: tuple[int, ...] | None = None, down: int | None = None) -> Tensor:
    """Boolean dilation by a (2k+1)³ cube (along ``axes``: all by default), one axis at a time with
    shifted ORs (max_pool3d on float grids was ~10× slower on CPU). ``down``: along an axis, occupancy
    reaches only this many cells towards higher indices (a surface below a point, for the z axis), k the
    other way."""
    for axis in range(grid.ndim) if axes is None else axes:
        src, grid = grid, grid.clone()
        n = src.shape[axis]
        for o in range(1, min(k, n - 1) + 1):
            if down is None or o <= down:
                grid.narrow(axis, o, n - o).logical_or_(src.narrow(axis, 0, n - o))
            grid.narrow(axis, 0, n - o).logical_or_(src.narrow(axis, o, n - o))
    return grid
