"""Mesh extraction on the global lattice: border pins, marching cubes, confidence, labels, upload detail.

A tile evaluates ``x ∈ [i·S, (i+1)·S]`` and ``y ∈ [j·S, (j+1)·S]`` *inclusive of both borders* × its height
slab, on the narrow-band SDF volume of ``fusion.band`` (lattice points at multiples of ``voxel_m`` in the
map frame, so neighbouring tiles' lattices coincide).

Seams: a neighbour extracted earlier *pins* the shared border plane (``apply_border_pins``): its SDF, and
its confidence and label near the surface there. Marching-cubes vertices on a border plane depend only
on the plane's SDF, and their confidence / label are read from the plane's values (``_border_attrs``),
so both tiles place, keep or drop, and label every seam vertex identically, whatever their fields say.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.ndimage import minimum_filter
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from fusion.band import Lattice, SdfFn, StepFn, cube_mask, narrow_band_sdf, near_support, tile_lattice
from fusion.runtime import cpu_threads
from fusion.types import FusedMesh, TileSpec

AttrFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # (n, 3) → confidence (n,), label (n,)


SIDES = {"x0": (0, 0), "x1": (0, -1), "y0": (1, 0), "y1": (1, -1)}


ATTR_BAND_VOXELS = 3.0  # plane points within this many voxels of the surface get confidence / label


def border_planes(vol: np.ndarray, lat: Lattice, attr_fn: AttrFn | None = None,
                  pinned: dict[str, dict[str, np.ndarray]] | None = None) -> dict[str, dict[str, Any]]:
    """SDF on the 4 border planes with their global lattice placement (see ``apply_border_pins``), and
    with ``attr_fn``: ``conf`` (float32, NaN away from the surface) and ``label`` (int16, -1 there) at
    the plane points within ``ATTR_BAND_VOXELS`` of the surface. ``pinned[side]``: attribute values a
    neighbour pinned on that plane (NaN where it had none) take precedence over ours."""
    out = {}
    for name, (axis, side) in SIDES.items():
        plane = vol[side] if axis == 0 else vol[:, side]
        k = lat.k0[axis] if side == 0 else lat.k1[axis]
        rest = [a for a in range(3) if a != axis]
        entry: dict[str, Any] = {"axis": axis, "k": k, "k0": [lat.k0[a] for a in rest], "voxel_m": lat.voxel_m,
                                 "sdf": plane.copy()}
        if attr_fn is not None:
            conf = np.full(plane.shape, np.nan, np.float32)
            label = np.full(plane.shape, -1, np.int16)
            near = np.argwhere(np.abs(plane) < ATTR_BAND_VOXELS * lat.voxel_m)
            if len(near):
                idx = np.zeros((len(near), 3), np.int64)
                idx[:, axis] = k
                for r, a in enumerate(rest):
                    idx[:, a] = near[:, r] + lat.k0[a]
                c, lab = attr_fn(idx.astype(np.float64) * lat.voxel_m)
                conf[near[:, 0], near[:, 1]] = c
                label[near[:, 0], near[:, 1]] = lab
            theirs = (pinned or {}).get(name)
            if theirs is not None:
                have = ~np.isnan(theirs["conf"])
                conf[have] = theirs["conf"][have]
                label[have] = theirs["label"][have]
            entry |= {"conf": conf, "label": label}
        out[name] = entry
    if attr_fn is not None and pinned:
        _share_corner_pins(out, pinned)
    return out


def _share_corner_pins(planes: dict[str, dict[str, Any]], pinned: dict[str, dict[str, np.ndarray]]) -> None:
    """A corner column (x and y border at once) lies on an x plane and a y plane: where a neighbour
    pinned it on one of them, the other takes the same values, so the four tiles meeting there agree."""
    for xs, ys in itertools.product(("x0", "x1"), ("y0", "y1")):
        x_row = 0 if ys == "y0" else -1  # the corner's row in the x plane (rows run along y)
        y_row = 0 if xs == "x0" else -1  # and in the y plane (rows run along x)
        for src, dst, src_row, dst_row in ((xs, ys, x_row, y_row), (ys, xs, y_row, x_row)):
            if src not in pinned:
                continue
            have = ~np.isnan(pinned[src]["conf"][src_row])
            for key in ("conf", "label"):
                planes[dst][key][dst_row][have] = planes[src][key][src_row][have]
            break


def _pin_entries(pins: Any) -> list[dict[str, Any]]:
    """Border entries from a neighbour's ``border`` dict, a dict of them, or a list."""
    if isinstance(pins, dict) and "sdf" in pins:
        return [pins]
    values = pins.values() if isinstance(pins, dict) else pins
    return [e for v in values for e in _pin_entries(v)]


def apply_border_pins(vol: np.ndarray, lat: Lattice, pins: Any,
                      attrs: dict[str, dict[str, np.ndarray]] | None = None,
                      exact: np.ndarray | None = None) -> int:
    """Overwrite our border-plane SDF with neighbours' values where the planes (axis, global k) match;
    returns the number of values pinned. Keys do not matter: the plane's lattice placement does.
    ``attrs``: filled with the neighbours' pinned ``conf`` / ``label`` planes in our plane's shape,
    keyed by our side (NaN / -1 where the neighbour's plane holds no attribute, 0 / 0 above or below its
    plane; borders stored before these existed have none).
    ``exact``: the narrow band's mask, set on the pinned points: our own coarse pass may have put a plane
    outside our band where the neighbour's field had a surface, and marching cubes skips cubes with no
    exact corner, which left the neighbour's seam vertices without partners here (1.0 m seam, 2x2 bench seed 1)."""
    count = 0
    for e in _pin_entries(pins):
        if abs(float(e["voxel_m"]) - lat.voxel_m) > 1e-9:
            continue
        axis, k = int(e["axis"]), int(e["k"])
        if k == lat.k0[axis]:
            side = 0
        elif k == lat.k1[axis]:
            side = vol.shape[axis] - 1
        else:
            continue
        sdf = np.asarray(e["sdf"], dtype=np.float64)
        rest = [a for a in range(3) if a != axis]
        ours, theirs = [], []
        for r, (a, pk0) in enumerate(zip(rest, e["k0"], strict=True)):
            lo, hi = max(lat.k0[a], int(pk0)), min(lat.k1[a], int(pk0) + sdf.shape[r] - 1)
            if hi < lo:
                break
            ours.append(slice(lo - lat.k0[a], hi - lat.k0[a] + 1))
            theirs.append(slice(lo - int(pk0), hi - int(pk0) + 1))
        else:
            target = vol[side] if axis == 0 else vol[:, side]
            target[ours[0], ours[1]] = sdf[theirs[0], theirs[1]]
            count += target[ours[0], ours[1]].size
            if exact is not None:
                (exact[side] if axis == 0 else exact[:, side])[ours[0], ours[1]] = True
            if attrs is not None and "conf" in e:
                name = next(n for n, (ax, sd) in SIDES.items() if ax == axis and (sd == 0) == (side == 0))
                plane = attrs.setdefault(name, {"conf": np.full(target.shape, np.nan, np.float32),
                                                "label": np.full(target.shape, -1, np.int16)})
                # above or below the neighbour's plane (its lattice spans other heights) the neighbour
                # has no surface: confidence 0 there, so we keep none on the seam either
                plane["conf"][ours[0], :] = 0.0
                plane["label"][ours[0], :] = 0
                plane["conf"][ours[0], ours[1]] = np.asarray(e["conf"])[theirs[0], theirs[1]]
                plane["label"][ours[0], ours[1]] = np.asarray(e["label"])[theirs[0], theirs[1]]
    return count


def _with_pinned_heights(z_range: tuple[float, float], pins: Any, voxel_m: float) -> tuple[float, float]:
    """``z_range`` grown to the heights of the neighbours' border planes: a neighbour's surface on the
    shared plane then always has its partner here (each tile's range comes from its own data)."""
    lo, hi = z_range
    for e in _pin_entries(pins) if pins else []:
        if abs(float(e["voxel_m"]) - voxel_m) <= 1e-9:
            k_z, n_z = int(e["k0"][1]), np.asarray(e["sdf"]).shape[1]
            lo, hi = min(lo, k_z * voxel_m), max(hi, (k_z + n_z - 1) * voxel_m)
    return lo, hi


def _border_attrs(verts_idx: np.ndarray, lat: Lattice, border: dict[str, dict[str, Any]],
                  conf: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Confidence and label of the vertices lying on a border plane, read from that plane's values
    (linear along the vertex's lattice edge; the label of the nearer end), in place; returns the mask
    of the vertices so set. Both tiles of a seam hold the same plane values (pinned), so they agree on
    every seam vertex."""
    shape = lat.shape
    seam = np.zeros(len(verts_idx), bool)
    for entry in border.values():
        if "conf" not in entry:
            continue
        axis = int(entry["axis"])
        at = 0 if entry["k"] == lat.k0[axis] else shape[axis] - 1
        on = np.flatnonzero(verts_idx[:, axis] == at)
        if not len(on):
            continue
        rest = [a for a in range(3) if a != axis]
        uv = verts_idx[on][:, rest]
        lo = np.floor(uv).astype(np.int64)
        frac = uv - lo
        hi = np.minimum(lo + (frac > 0), np.asarray(entry["conf"].shape) - 1)
        c_lo = entry["conf"][lo[:, 0], lo[:, 1]]
        c_hi = entry["conf"][hi[:, 0], hi[:, 1]]
        w = frac.max(axis=1)  # a vertex lies on one lattice edge: one fractional coordinate
        c = (1 - w) * c_lo + w * c_hi
        near = np.where((w <= 0.5)[:, None], lo, hi)
        lab = entry["label"][near[:, 0], near[:, 1]]
        ok = ~np.isnan(c) & (lab >= 0)
        conf[on[ok]] = c[ok]
        labels[on[ok]] = lab[ok]
        seam[on[ok]] = True
    return seam


def supported_attrs(attr_fn: AttrFn, tree: cKDTree, radius_m: float) -> AttrFn:
    """``attr_fn`` with confidence 0 wherever no point of the support (``tree`` of map-frame points, the
    posed input surfaces) lies within ``radius_m``: the field is only trained near the data, and far from
    it (beyond the space samples' boxes, or behind a hash collision) its confidence is whatever the grid
    makes of it. A surface is reported only where some submap saw one; holes up to ~2 × ``radius_m`` are
    filled."""

    def fn(x_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        conf, labels = attr_fn(x_map)
        far = ~np.isfinite(tree.query(x_map, k=1, distance_upper_bound=radius_m, workers=cpu_threads())[0])
        return np.where(far, 0.0, conf).astype(np.asarray(conf).dtype), labels

    return fn


def voted_labels(points: np.ndarray, head: np.ndarray, support: np.ndarray, support_labels: np.ndarray,
                 k: int = 8, radius_m: float = 0.3) -> np.ndarray:
    """Per query point, the majority label of the ``k`` nearest ``support`` points within ``radius_m``
    (label 0, unlabelled, does not vote); ``head`` (the semantic head's label) where none votes.
    Ties go to the head's label when it is among them, else to the lowest id."""
    tree = cKDTree(np.asarray(support, np.float64))
    dist, idx = tree.query(np.asarray(points, np.float64), k=k, distance_upper_bound=radius_m,
                           workers=cpu_threads())
    found = np.isfinite(dist)
    lab = np.where(found, np.asarray(support_labels)[np.minimum(idx, len(support) - 1)], 0)
    n_cls = int(max(lab.max(initial=0), np.asarray(head).max(initial=0))) + 1
    votes = np.zeros((len(points), n_cls), np.int32)
    rows = np.repeat(np.arange(len(points)), k)
    np.add.at(votes, (rows, lab.ravel()), 1)
    votes[:, 0] = 0
    best = votes.max(axis=1)
    head = np.asarray(head, np.int64)
    keep_head = votes[np.arange(len(points)), head] == best
    return np.where((best == 0) | keep_head, head, votes.argmax(axis=1))


def deflate_faces(vertices: np.ndarray, faces: np.ndarray, face_labels: np.ndarray, labels: Sequence[int],
                  offset_m: float, fixed: np.ndarray | None = None) -> np.ndarray:
    """``vertices`` with those of faces labelled one of ``labels`` moved ``offset_m`` in along their normal
    (area-weighted face normals, which point to free space), except where ``fixed`` (seam vertices: both
    tiles keep them where they are). The inverse of the reconstruction's minimum thickness
    (``fusion.reconstruct.inflate_thin_surfaces``): the samples of a pole or a sign plate sat ``offset_m``
    out so the grid holds an interior; the surface reported is moved back to where the uploads put it."""
    v = np.asarray(vertices, np.float64)
    thin = np.isin(face_labels, np.asarray(labels, np.int64))
    if offset_m <= 0 or not thin.any():
        return v
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    area_normal = np.cross(b - a, c - a)
    normal = np.stack([sum(np.bincount(faces[:, k], area_normal[:, d], len(v)) for k in range(3)) for d in range(3)], 1)
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    move = np.zeros(len(v), bool)
    move[faces[thin].ravel()] = True
    if fixed is not None:
        move &= ~fixed
    return v - offset_m * normal * move[:, None]


def surface_samples(vertices: np.ndarray, faces: np.ndarray, spacing_m: float, edge_m: float) -> np.ndarray:
    """Points on a triangle mesh no farther than about ``spacing_m`` from any point of it: the vertices and a
    barycentric lattice on each face, fine enough for edges up to ``edge_m`` (a marching-cubes face's edges are
    at most a voxel diagonal)."""
    v = np.asarray(vertices, np.float64)
    if not len(faces):
        return v
    k = max(1, math.ceil(edge_m / spacing_m))
    ab = np.array([(a, b) for a in range(k + 1) for b in range(k + 1 - a)], np.float64) / k
    w = np.column_stack([ab, 1.0 - ab.sum(axis=1)])  # (q, 3) barycentric weights, vertices included
    tri = v[faces]  # (m, 3, 3)
    return np.concatenate([v, np.einsum("qk,mkd->mqd", w, tri).reshape(-1, 3)])


def detail_faces(mesh_vertices: np.ndarray, mesh_faces: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                 tile: TileSpec, z_range: tuple[float, float], gap_m: float, voxel_m: float) -> np.ndarray:
    """Indices of the ``faces`` (of the posed uploads, map frame) whose centre lies in ``tile`` (x, y in
    [min, max), z in ``z_range``) and farther than ``gap_m`` from the field's mesh (``mesh_vertices``,
    ``mesh_faces``; its ``surface_samples`` at a third of the gap): what the uploads saw and the field did not
    reconstruct. Each face belongs to the one tile its centre lies in, so neighbouring tiles never both take it.

    A centre with a mesh vertex within the gap is near (vertices are samples); only for the others are the
    samples of the mesh faces within reach drawn (a face's points lie within its longest edge of its
    vertices), so the dense samples of the whole mesh are never built."""
    if not len(faces):
        return np.zeros(0, np.int64)
    centres = np.asarray(vertices, np.float64)[faces].mean(axis=1)
    (x0, y0), size = tile.xy_min, tile.size_m
    inside = np.flatnonzero((centres[:, 0] >= x0) & (centres[:, 0] < x0 + size) & (centres[:, 1] >= y0)
                            & (centres[:, 1] < y0 + size) & (centres[:, 2] >= z_range[0])
                            & (centres[:, 2] <= z_range[1]))
    mv = np.asarray(mesh_vertices, np.float64)
    if not len(inside) or not len(mv):
        return inside
    far = ~np.isfinite(cKDTree(mv).query(centres[inside], distance_upper_bound=gap_m, workers=cpu_threads())[0])
    open_ = inside[far]
    if not len(open_) or not len(mesh_faces):
        return open_
    tri = mv[mesh_faces]
    longest = float(np.sqrt(((tri - np.roll(tri, 1, axis=1)) ** 2).sum(axis=2).max()))
    reach = np.isfinite(cKDTree(centres[open_]).query(mv, distance_upper_bound=gap_m + longest,
                                                   workers=cpu_threads())[0])
    near_faces = mesh_faces[reach[mesh_faces].any(axis=1)]
    surface = surface_samples(mv, near_faces, gap_m / 3, voxel_m * math.sqrt(2))
    dist, _ = cKDTree(surface).query(centres[open_], distance_upper_bound=gap_m, workers=cpu_threads())
    return open_[~np.isfinite(dist)]


def add_detail(
    verts: np.ndarray, faces: np.ndarray, conf: np.ndarray, vertex_labels: np.ndarray, face_labels: np.ndarray,
    detail: tuple[np.ndarray, np.ndarray], tile: TileSpec, z_range: tuple[float, float], gap_m: float, c_th: float,
    attr_fn: AttrFn, label_at: Callable[[np.ndarray], np.ndarray] | None, voxel_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The field's mesh with the upload faces it lost added as measured (``detail_faces``), where the field
    is confident (every vertex at or above ``c_th``; the reconstruction offers only faces the consensus kept,
    ``fusion.reconstruct._posed_uploads``: a car that drove off stays out). A pole, a sign or a small
    obstacle thinner or smaller than the field's finest cells, seen from
    one side and mislabelled by the segmenter (so not inflated as a thin class), leaves no zero crossing
    on the extraction lattice; its uploaded surface does. Labels: ``label_at`` at each face's centre
    (``face_labels`` "centroid" / "vote"), else the majority of its vertices' head labels. Returns the
    vertices, faces, confidence, vertex and face labels, and the number of faces added."""
    dv, df = np.asarray(detail[0], np.float64), np.asarray(detail[1], np.int64)
    chosen = df[detail_faces(verts, faces, dv, df, tile, z_range, gap_m, voxel_m)]
    if not len(chosen):
        return verts, faces, conf, vertex_labels, face_labels, 0
    used, inverse = np.unique(chosen, return_inverse=True)
    new_conf, new_labels = (np.array(a) for a in attr_fn(dv[used]))
    new_faces = inverse.reshape(-1, 3)
    sure = (new_conf >= c_th)[new_faces].all(axis=1)
    if not sure.any():
        return verts, faces, conf, vertex_labels, face_labels, 0
    new_faces = new_faces[sure]
    kept = np.flatnonzero(np.bincount(new_faces.ravel(), minlength=len(used)))
    remap = np.full(len(used), -1, np.int64)
    remap[kept] = np.arange(len(kept))
    new_faces = remap[new_faces]
    new_verts, new_conf, new_vl = dv[used][kept], new_conf[kept], new_labels[kept].astype(np.uint8)
    if label_at is not None:
        new_fl = label_at(new_verts[new_faces].mean(axis=1)).astype(np.uint8)
    else:
        new_fl = _face_labels(new_vl, new_faces).astype(np.uint8)
    return (np.concatenate([verts, new_verts]), np.concatenate([faces, new_faces + len(verts)]),
            np.concatenate([conf, new_conf]), np.concatenate([vertex_labels, new_vl]),
            np.concatenate([face_labels, new_fl]), int(len(new_faces)))


def split_label_boundaries(
    verts: np.ndarray, faces: np.ndarray, conf: np.ndarray, vertex_labels: np.ndarray, face_labels: np.ndarray,
    seam: np.ndarray, label_fn: Callable[[np.ndarray], np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Faces on a class boundary (their vertex and centroid labels disagree) split in four at their edge
    midpoints, each quarter labelled at its own centroid by ``label_fn`` (n, 3) → (n,).

    One face label per lattice voxel steps over what is narrower than a voxel: a 0.15 m lane marking under
    0.25 m faces goes to the road wherever no centroid falls on it, and every class edge is drawn at the
    voxel's resolution. Only boundary faces split, so the cost is one label query per new vertex and
    quarter. Neighbouring split faces share their edge midpoints; a split face's midpoint on an unsplit
    neighbour's edge lies on that edge (a T-junction, no gap). A midpoint is a seam vertex when both ends
    are (it lies on the border plane between them) and takes their confidence's mean; new vertices' labels
    come from ``label_fn``. Returns vertices, faces, confidence, vertex labels, face labels and seam mask."""
    fl = np.asarray(face_labels, np.int64)
    vl = np.asarray(vertex_labels, np.int64)
    mixed = (vl[faces] != fl[:, None]).any(axis=1)
    if not mixed.any():
        return verts, faces, conf, vertex_labels, face_labels, seam
    split = faces[mixed]
    edges = np.sort(np.concatenate([split[:, [0, 1]], split[:, [1, 2]], split[:, [2, 0]]]), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    inverse = inverse.reshape(3, -1).T + len(verts)  # (n, 3): midpoint ids of edges 01, 12, 20
    mid = (verts[unique[:, 0]] + verts[unique[:, 1]]) / 2
    v = np.concatenate([verts, mid])
    c = np.concatenate([conf, (conf[unique[:, 0]] + conf[unique[:, 1]]) / 2])
    sm = np.concatenate([seam, seam[unique[:, 0]] & seam[unique[:, 1]]])
    lab = np.concatenate([vl, np.asarray(label_fn(mid), np.int64)])
    a, b, cc = split[:, 0], split[:, 1], split[:, 2]
    ab, bc, ca = inverse[:, 0], inverse[:, 1], inverse[:, 2]
    quarters = np.concatenate([np.stack(q, axis=1) for q in ((a, ab, ca), (ab, b, bc), (ca, bc, cc), (ab, bc, ca))])
    q_labels = np.asarray(label_fn(v[quarters].mean(axis=1)), np.int64)
    f = np.concatenate([faces[~mixed], quarters])
    out_fl = np.concatenate([fl[~mixed], q_labels])
    return (v, f.astype(faces.dtype), c, lab.astype(np.asarray(vertex_labels).dtype),
            out_fl.astype(np.asarray(face_labels).dtype), sm)


# label geometry (``relabel_by_geometry``): a face is steep below this |n_z| (45°), level above this one (~25°)
STEEP_NZ = 0.7
LEVEL_NZ = 0.9
# ... raised when its centre stands more than this above the lowest mesh vertex within GROUND_REACH_M
# horizontally (a kerb is ~0.15 m), at ground level within AT_GROUND_M of it
RAISED_M = 0.4
AT_GROUND_M = 0.2
GROUND_REACH_M = 1.25
GROUND_CELL_M = 0.5


def ground_heights(verts: np.ndarray, points: np.ndarray, reach_m: float = GROUND_REACH_M,
                   cell_m: float = GROUND_CELL_M) -> np.ndarray:
    """Height of each of ``points`` (n, 3) above the lowest of ``verts`` (m, 3) within about ``reach_m``
    horizontally (square cells of ``cell_m``); 0 for a point with no vertex in reach."""
    pts = np.asarray(points, np.float64)
    if not len(pts) or not len(verts):
        return np.zeros(len(pts))
    v = np.asarray(verts, np.float64)
    lo = np.floor(np.minimum(v[:, :2].min(axis=0), pts[:, :2].min(axis=0)) / cell_m).astype(np.int64)
    vij = np.floor(v[:, :2] / cell_m).astype(np.int64) - lo
    pij = np.floor(pts[:, :2] / cell_m).astype(np.int64) - lo
    shape = tuple(int(n) for n in np.maximum(vij.max(axis=0), pij.max(axis=0)) + 1)
    low = np.full(shape, np.inf)
    np.minimum.at(low, (vij[:, 0], vij[:, 1]), v[:, 2])
    low = minimum_filter(low, size=2 * math.ceil(reach_m / cell_m) + 1, mode="constant", cval=np.inf)
    ground = low[pij[:, 0], pij[:, 1]]
    return np.where(np.isfinite(ground), pts[:, 2] - ground, 0.0)


def relabel_by_geometry(verts: np.ndarray, faces: np.ndarray, face_labels: np.ndarray, ground: Sequence[int],
                        label_among: Callable[[np.ndarray, np.ndarray], np.ndarray], num_classes: int,
                        ) -> tuple[np.ndarray, int]:
    """Face labels that contradict the face's own geometry replaced by the head's best label that does not.

    A camera segmenter's mistakes are 2D: a class bleeds across a border in the image and a pole or sign it
    misses takes the class around it, which on the ground is the pavement. Lifted into 3D those mistakes
    put a ground class (``ground``: road, sidewalk, markings, terrain) on a steep face well above the
    ground beside it (a pole, a wall's foot, a car's flank), and a class of what stands on the ground
    (every other class: walls, fences, poles, signs, vegetation, cars, obstacles) on level ground at ground
    height, where it bled onto the pavement around the object (level vegetation at ground height is
    terrain by the labels' own definition). Such a face takes ``label_among(centres, allowed)`` — the
    semantic head's argmax over the ``allowed`` (num_classes,) mask — over the other group's classes.
    The ground is the lowest mesh vertex within ``GROUND_REACH_M`` (``ground_heights``), so slopes and
    kerbs stay ground and a roof or a car's bonnet is not at ground height. Returns the labels and how
    many changed."""
    fl = np.asarray(face_labels).copy()
    if not len(faces):
        return fl, 0
    tri = np.asarray(verts, np.float64)[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nz = n[:, 2] / np.maximum(np.linalg.norm(n, axis=1), 1e-12)  # normals point to free space
    centres = tri.mean(axis=1)
    height = ground_heights(verts, centres)
    is_ground = np.zeros(num_classes, bool)
    is_ground[np.asarray(ground, np.int64)] = True
    labelled_ground = is_ground[fl.astype(np.int64)]
    changed = 0
    for wrong, allowed in ((labelled_ground & (np.abs(nz) < STEEP_NZ) & (height > RAISED_M), ~is_ground),
                           (~labelled_ground & (fl != 0) & (nz > LEVEL_NZ) & (height < AT_GROUND_M), is_ground)):
        idx = np.flatnonzero(wrong)
        if len(idx):
            keep = allowed.copy()
            keep[0] = False
            fl[idx] = np.asarray(label_among(centres[idx], keep)).astype(fl.dtype)
            changed += len(idx)
    return fl, changed


def _face_labels(vl: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = vl[faces[:, 0]], vl[faces[:, 1]], vl[faces[:, 2]]
    return np.where((a == b) | (a == c), a, np.where(b == c, b, a))


def extract_mesh(
    sdf_fn: SdfFn,
    attr_fn: AttrFn,
    tile: TileSpec,
    z_range: tuple[float, float],
    voxel_m: float,
    block: int = 4,
    band_factor: float = 0.75,
    c_th: float = 0.7,
    border_pins: Any = None,
    step: StepFn | None = None,
    face_labels: str = "vertices",
    support: np.ndarray | None = None,
    support_m: float = 0.0,
    support_labels: np.ndarray | None = None,
    deflate_labels: Sequence[int] = (),
    deflate_m: float = 0.0,
    split_labels: bool = False,
    detail: tuple[np.ndarray, np.ndarray] | None = None,
    detail_m: float = 0.0,
    relabel: tuple[Sequence[int], Callable[[np.ndarray, np.ndarray], np.ndarray], int] | None = None,
) -> tuple[FusedMesh, dict[str, dict[str, Any]], dict[str, Any]]:
    """Fused mesh of one tile (map frame) from an SDF (positive in free space).

    Returns the mesh (faces with a vertex below ``c_th`` dropped, unreferenced vertices removed), the
    border planes (after pinning) and stats. Face normals (right-hand winding) point to free space.
    Face labels: ``"vertices"`` the majority of the vertex labels, ``"centroid"`` the label at the
    face's centroid (one more query per face; keeps structures narrower than a voxel, e.g. lane
    markings, that fall between vertices). ``support`` (n, 3) map-frame input surface points and
    ``support_m`` > 0: confidence is 0 farther than ``support_m`` from every one (``supported_attrs``),
    on seam planes too, so neighbours still agree. ``deflate_labels`` / ``deflate_m``: faces so labelled move
    ``deflate_m`` in along their normals (``deflate_faces``), seam vertices excepted. ``split_labels`` (with
    ``centroid`` or ``vote`` labels): faces on a class boundary split in four, each quarter labelled at its
    centroid (``split_label_boundaries``). ``detail`` (vertices (n, 3) map frame, faces (m, 3)): the posed
    uploads; with ``detail_m`` > 0 their faces farther than that from the field's surface, where it is
    confident, join the mesh as measured (``add_detail``). ``relabel`` (ground label ids, the head's argmax
    among allowed classes, class count): faces whose label contradicts their geometry take
    the best other label (``relabel_by_geometry``), the detail's faces too.
    """
    near = None
    if support is not None and support_m > 0:
        tree = cKDTree(np.asarray(support, np.float64))
        attr_fn = supported_attrs(attr_fn, tree, support_m)
        near = near_support(tree, support_m, voxel_m)
    if face_labels not in ("vertices", "centroid", "vote"):
        raise ValueError(f"face_labels must be 'vertices', 'centroid' or 'vote', got {face_labels!r}")
    if face_labels == "vote" and (support is None or support_labels is None):
        raise ValueError("face_labels 'vote' needs support points and their labels")
    lat = tile_lattice(tile, *_with_pinned_heights(z_range, border_pins, voxel_m), voxel_m)
    vol, mask = narrow_band_sdf(sdf_fn, lat, block, band_factor, step=step, near=near)
    pinned_attrs: dict[str, dict[str, np.ndarray]] = {}
    pinned = apply_border_pins(vol, lat, border_pins, pinned_attrs, exact=mask) if border_pins else 0
    border = border_planes(vol, lat, attr_fn, pinned_attrs)
    stats: dict[str, Any] = {"lattice_shape": list(lat.shape), "band_points": int(mask.sum()), "pinned": pinned}
    z_lat = (lat.k0[2] * voxel_m, lat.k1[2] * voxel_m)

    def label_at(x: np.ndarray) -> np.ndarray:
        head = np.asarray(attr_fn(x)[1])
        if face_labels == "vote":
            assert support is not None and support_labels is not None
            return voted_labels(x, head, support, support_labels)
        return head

    def finish(verts: np.ndarray, faces: np.ndarray, conf: np.ndarray, vl: np.ndarray, fl: np.ndarray,
               ) -> tuple[FusedMesh, dict[str, dict[str, Any]], dict[str, Any]]:
        """The mesh with the uploads' detail added (also where the field left no surface in the tile)."""
        if detail is not None and detail_m > 0:
            verts, faces, conf, vl, fl, stats["detail_faces"] = add_detail(
                verts, faces, conf, vl, fl, detail, tile, z_lat, detail_m, c_th, attr_fn,
                label_at if face_labels in ("centroid", "vote") else None, voxel_m)
        if relabel is not None:
            fl, stats["relabelled_faces"] = relabel_by_geometry(verts, faces, fl, *relabel)
        stats["faces"] = int(len(faces))
        if not len(faces):
            return FusedMesh.empty(), border, stats
        return FusedMesh(verts.astype(np.float32), faces.astype(np.int32), vl, conf.astype(np.float32), fl), border, stats

    def nothing() -> tuple[FusedMesh, dict[str, dict[str, Any]], dict[str, Any]]:
        e = FusedMesh.empty()
        return finish(e.vertices.astype(np.float64), e.faces.astype(np.int64), e.vertex_confidence.astype(np.float64),
                      e.vertex_labels, e.face_labels)

    if not ((vol > 0).any() and (vol < 0).any()):
        return nothing()
    # skimage's "descent" winding makes right-hand face normals point to s > 0 (free space); pinned by
    # the sphere test in tests/fusion/test_extract.py
    try:
        verts_idx, faces, _, _ = marching_cubes(vol, level=0.0, gradient_direction="descent", allow_degenerate=False,
                                                mask=cube_mask(mask))
    except RuntimeError:  # skimage: "No surface found" (the crossings lie outside the band only)
        return nothing()
    verts = (verts_idx.astype(np.float64) + np.asarray(lat.k0, np.float64)) * voxel_m
    stats["raw_faces"] = int(len(faces))
    if len(faces) == 0:
        return nothing()
    conf, labels = attr_fn(verts)
    conf, labels = np.array(conf, np.float64), np.array(labels, np.int64)
    seam = _border_attrs(verts_idx, lat, border, conf, labels)
    stats["seam_vertices"] = int(seam.sum())
    sure = conf >= c_th
    # a face touching a border plane is kept by its seam vertices alone, so the tiles on both sides
    # keep the same seam (at most one voxel of surface the interior confidence would drop)
    keep = np.where(seam[faces].any(1), (sure | ~seam)[faces].all(1), sure[faces].all(1))
    faces = faces[keep]
    used = np.flatnonzero(np.bincount(faces.ravel(), minlength=len(verts)))  # np.unique without the sort
    remap = np.full(len(verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    faces = remap[faces]
    verts, conf, labels, seam = verts[used], conf[used], labels[used], seam[used]
    vl = labels.astype(np.uint8)

    if not len(faces):
        fl = np.zeros(0, np.uint8)
    elif face_labels in ("centroid", "vote"):
        fl = label_at(verts[faces].mean(axis=1)).astype(np.uint8)
        if split_labels:
            before = len(faces)
            verts, faces, conf, vl, fl, seam = split_label_boundaries(verts, faces, conf, vl, fl, seam, label_at)
            stats["split_faces"] = int(len(faces) - before) // 3
    else:
        fl = _face_labels(vl, faces).astype(np.uint8)
    verts = deflate_faces(verts, faces, fl, deflate_labels, deflate_m, fixed=seam)
    return finish(verts, faces, conf, vl, fl)
