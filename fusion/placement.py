"""The map's placement across a joint re-alignment, and the tiles a re-alignment changed (torch-free).

A joint re-alignment (``FusionConfig.realign_share``) frees every submap of a region from its refined
pose. The data fix the submaps relative to each other; where the map stands as a whole (its gauge) is
fixed only by the weak GPS prior, summed over every submap, so each re-alignment moves the whole map
by about the prior's uncertainty: 0.2-0.4 m on the bench's fleets, against a few cm of reshaping away
from the new session (``docs/METHOD_LOG.md``, "Holding the map's placement"). A served map that jumps
by that on every re-alignment makes every tile's mesh stale, though most of them did not change shape;
but the jump is a correction (more sessions, a better GPS average), and a held map keeps the placement
of the sessions it was first aligned from (``FusionConfig.realign_hold``, off by default).

:func:`hold_placement` moves a re-alignment's poses rigidly, all together, so that the submaps the map
held before stand, in least squares over their surface, where they stood; :func:`tile_motion` then says
how far each tile's surface moved, and :func:`settle_realignment` which tiles keep their mesh.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from fusion.drift import Drift
from fusion.types import Pose, SubmapInput

Tile = tuple[int, int]


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (R, t, s) with ``dst ≈ s · R · src + t`` for point sets (n, 3) (Umeyama 1991)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    r, sig, s_fix = _rotation(xd.T @ xs / len(src))
    var = (xs**2).sum() / len(src)
    scale = float(np.trace(np.diag(sig) @ s_fix) / var) if with_scale and var > 0 else 1.0
    return r, mu_d - scale * r @ mu_s, scale


def _rotation(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The proper rotation closest to the cross-covariance ``cov`` (3, 3) (no reflection), its singular
    values and the sign fix."""
    u, sig, vt = np.linalg.svd(cov)
    s_fix = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_fix[2, 2] = -1
    return u @ s_fix @ vt, sig, s_fix


def _shape(submap: SubmapInput, drift: Drift | None) -> np.ndarray:
    """The submap's vertices (local frame) as its drift correction, if any, shapes them."""
    v = np.asarray(submap.mesh.vertices, np.float64)
    return v if drift is None or drift.is_identity() else drift.apply(v)


def hold_placement(submaps: Sequence[SubmapInput], before: Mapping[str, Pose], after: Mapping[str, Pose],
                   drifts_before: Mapping[str, Drift] | None = None, drifts_after: Mapping[str, Drift] | None = None,
                   every: int = 10) -> dict[str, Pose]:
    """``after`` (every pose of it) moved by the one map-frame rigid transform that carries the surface of
    the submaps in both ``before`` and ``after`` (every ``every``-th vertex, shaped by its drift correction
    before and after) from where ``after`` puts it to where ``before`` had it, in least squares. The
    relative poses are untouched; submaps new to the map move with the rest. ``after`` itself where
    fewer than 3 such vertices exist."""
    drifts_before, drifts_after = drifts_before or {}, drifts_after or {}
    src, dst = [], []
    for s in submaps:
        if s.id in before and s.id in after:
            src.append(after[s.id].apply(_shape(s, drifts_after.get(s.id))[::every]))
            dst.append(before[s.id].apply(_shape(s, drifts_before.get(s.id))[::every]))
    if sum(len(p) for p in src) < 3:
        return dict(after)
    r, t, _ = umeyama(np.concatenate(src), np.concatenate(dst))
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    hold = Pose.from_matrix(m)
    return {k: hold.compose(p) for k, p in after.items()}


def _face_tiles(xy: np.ndarray, faces: np.ndarray, tile_size: float, band_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Per face, the lowest and highest tile (i, j) its xy bounding box grown by ``band_m`` meets: ``(F, 2)``
    each, as ``fusion.tiles.surface_tiles`` counts a face in a tile."""
    lo_v = np.floor((xy - band_m) / tile_size).astype(np.int64)
    hi_v = np.floor((xy + band_m) / tile_size).astype(np.int64)
    return lo_v[faces].min(axis=1), hi_v[faces].max(axis=1)


def _max_per_tile(lo: np.ndarray, hi: np.ndarray, value: np.ndarray, out: dict[Tile, float]) -> None:
    """``out[tile]`` raised to the largest ``value`` of the faces whose tile box ``lo``..``hi`` holds it."""
    small = np.all(hi - lo <= 1, axis=1)  # the usual face: at most two tiles along each axis
    for a in (lo, hi):
        for b in (lo, hi):
            idx = np.stack([a[small, 0], b[small, 1]], axis=1)
            if not len(idx):
                continue
            base = idx.min(axis=0)
            span = int(idx[:, 1].max() - base[1]) + 1
            keys, inverse = np.unique((idx[:, 0] - base[0]) * span + (idx[:, 1] - base[1]), return_inverse=True)
            far = np.full(len(keys), -1.0)
            np.maximum.at(far, inverse, value[small])
            for key, d in zip(keys.tolist(), far.tolist(), strict=True):
                t = (int(base[0]) + key // span, int(base[1]) + key % span)
                out[t] = max(out.get(t, 0.0), d)
    for (a0, a1), (b0, b1), d in zip(lo[~small].tolist(), hi[~small].tolist(), value[~small].tolist(), strict=True):
        for i in range(a0, b0 + 1):
            for j in range(a1, b1 + 1):
                out[(i, j)] = max(out.get((i, j), 0.0), d)


def tile_motion(submaps: Sequence[SubmapInput], before: Mapping[str, Pose], after: Mapping[str, Pose],
                tile_size: float, band_m: float, drifts_before: Mapping[str, Drift] | None = None,
                drifts_after: Mapping[str, Drift] | None = None) -> dict[Tile, float]:
    """Per tile: the farthest any vertex of a face of a submap in ``after`` moved from ``before`` (m), over
    the faces that reach the tile grown by ``band_m`` at either pose (as ``fusion.tiles.surface_tiles``
    counts them); ``inf`` where a submap not in ``before`` (new to the map) has such a face. Tiles no face
    reaches are absent."""
    drifts_before, drifts_after = drifts_before or {}, drifts_after or {}
    out: dict[Tile, float] = {}
    for s in submaps:
        faces = np.asarray(s.mesh.faces)
        if s.id not in after or not len(faces):
            continue
        now = after[s.id].apply(_shape(s, drifts_after.get(s.id)))
        if s.id in before:
            was = before[s.id].apply(_shape(s, drifts_before.get(s.id)))
            moved = np.linalg.norm(now - was, axis=1)[faces].max(axis=1)
            places = [now[:, :2], was[:, :2]]
        else:
            moved, places = np.full(len(faces), math.inf), [now[:, :2]]
        for xy in places:
            _max_per_tile(*_face_tiles(xy, faces, tile_size, band_m), moved, out)
    return out


def tile_carry(submaps: Sequence[SubmapInput], before: Mapping[str, Pose], after: Mapping[str, Pose],
               tiles: Sequence[Tile], tile_size: float, band_m: float, drifts_before: Mapping[str, Drift] | None = None,
               drifts_after: Mapping[str, Drift] | None = None) -> dict[Tile, np.ndarray]:
    """Per tile of ``tiles``: the map-frame rigid motion (4, 4) that carries, in least squares, the surface
    its field was trained on (the faces of the submaps in both ``before`` and ``after`` that reach the tile
    grown by ``band_m`` at their ``before`` pose, one point per face: its centre) to where ``after`` puts it,
    in the tile's frame (the map frame shifted by the tile's lower corner, as its field is).
    A re-alignment moves a whole map by decimetres (its placement) and reshapes it by centimetres; carried
    by this motion (``fusion.field.moved_state``), a tile's last field starts its re-fusion centimetres from
    its surface instead of decimetres. Tiles with fewer than 3 such faces are absent."""
    drifts_before, drifts_after = drifts_before or {}, drifts_after or {}
    want = {t: k for k, t in enumerate(tiles)}
    if not want:
        return {}
    keys = np.array(list(want), np.int64)
    base, span = keys.min(axis=0), keys.max(axis=0) - keys.min(axis=0) + 1
    lookup = np.full(span, -1, np.int64)  # tile (i, j) - base → its index in ``tiles``
    lookup[keys[:, 0] - base[0], keys[:, 1] - base[1]] = list(want.values())

    def index(ti: np.ndarray, tj: np.ndarray) -> np.ndarray:
        a, b = ti - base[0], tj - base[1]
        inside = (a >= 0) & (a < span[0]) & (b >= 0) & (b < span[1])
        return np.where(inside, lookup[np.clip(a, 0, span[0] - 1), np.clip(b, 0, span[1] - 1)], -1)

    count = np.zeros(len(tiles))
    sum_s, sum_d, cross = np.zeros((len(tiles), 3)), np.zeros((len(tiles), 3)), np.zeros((len(tiles), 3, 3))
    for s in submaps:
        faces = np.asarray(s.mesh.faces)
        if s.id not in before or s.id not in after or not len(faces):
            continue
        was = before[s.id].apply(_shape(s, drifts_before.get(s.id)))
        now = after[s.id].apply(_shape(s, drifts_after.get(s.id)))
        src, dst = was[faces].mean(axis=1), now[faces].mean(axis=1)
        lo, hi = _face_tiles(was[:, :2], faces, tile_size, band_m)
        # the tiles at the corners of each face's tile box, each once (a face longer than a tile, which
        # also meets the tiles between, is fitted in its corner tiles only)
        corners = [(lo[:, 0], lo[:, 1], True), (lo[:, 0], hi[:, 1], hi[:, 1] != lo[:, 1]),
                   (hi[:, 0], lo[:, 1], hi[:, 0] != lo[:, 0]),
                   (hi[:, 0], hi[:, 1], (hi[:, 0] != lo[:, 0]) & (hi[:, 1] != lo[:, 1]))]
        for ti, tj, new in corners:
            idx = index(ti[new], tj[new])
            sel = idx >= 0
            idx, a, b = idx[sel], src[new][sel], dst[new][sel]
            np.add.at(count, idx, 1.0)
            np.add.at(sum_s, idx, a)
            np.add.at(sum_d, idx, b)
            np.add.at(cross, idx, b[:, :, None] * a[:, None, :])
    out: dict[Tile, np.ndarray] = {}
    for t, k in want.items():
        if count[k] < 3:
            continue
        mu_s, mu_d = sum_s[k] / count[k], sum_d[k] / count[k]
        r, _, _ = _rotation(cross[k] / count[k] - np.outer(mu_d, mu_s))
        corner = np.array([t[0] * tile_size, t[1] * tile_size, 0.0])  # x_tile = x_map - corner
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, mu_d - r @ mu_s + r @ corner - corner
        out[t] = m
    return out


def motion_report(motion: Mapping[Tile, float]) -> dict[str, float | None]:
    """:func:`tile_motion` as a job's or a bench row's figures: ``"i_j"`` → metres (4 decimals), None where
    a new submap is."""
    return {f"{i}_{j}": round(d, 4) if math.isfinite(d) else None for (i, j), d in sorted(motion.items())}


def quiet_tiles(tiles: Iterable[Tile], motion: Mapping[Tile, float]) -> list[Tile]:
    """The tiles of ``tiles`` no submap new to the map reaches (:func:`tile_motion` finite there), sorted: a
    carried field there has nothing new to build (``FusionConfig.refusion_carried_fraction``)."""
    return sorted(t for t in tiles if math.isfinite(motion.get(t, math.inf)))


def settle_realignment(
    submaps: Sequence[SubmapInput], before: Mapping[str, Pose], after: Mapping[str, Pose], tiles: Sequence[Tile],
    *, tile_size: float, band_m: float, hold: bool, keep_m: float,
    drifts_before: Mapping[str, Drift] | None = None, drifts_after: Mapping[str, Drift] | None = None,
) -> tuple[dict[str, Pose], list[Tile], dict[Tile, float]]:
    """The poses a registration-only re-alignment commits and the tiles of ``tiles`` that keep their mesh.

    ``before``: the refined poses the map held (submaps new to it have none); ``after``: the
    re-alignment's poses of its free submaps. ``hold`` (and every submap of ``submaps`` free, i.e. in
    ``after``: held submaps would pin the map already): :func:`hold_placement`. A tile keeps its mesh
    where no submap new to the map comes within ``band_m`` of it and no other surface near it moved by
    ``keep_m`` or more (0: every tile is reconstructed again). Returns the poses, the tiles kept and the
    motion per tile (:func:`tile_motion`, after the hold)."""
    poses = dict(after)
    if hold and all(s.id in after for s in submaps):
        poses = hold_placement(submaps, before, after, drifts_before, drifts_after)
    motion = tile_motion(submaps, before, poses, tile_size, band_m, drifts_before, drifts_after)
    keep = sorted(t for t in tiles if keep_m > 0 and motion.get(t, 0.0) < keep_m)
    return poses, keep, motion
