"""What a vehicle's sensor sees: range, facing and occlusion tests on faces (map frame, metres)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Rect = tuple[float, float, float, float, float]  # cx, cy, half_length, half_width, yaw


def _to_rect_frame(xy: np.ndarray, rect: Rect) -> np.ndarray:
    cx, cy, _, _, yaw = rect
    c, s = np.cos(yaw), np.sin(yaw)
    d = xy - np.array([cx, cy])
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])


def inside_rects(xy: np.ndarray, rects: list[Rect], shrink: float = 0.05) -> np.ndarray:
    """Whether each point xy (n, 2) lies inside any rectangle (shrunk by ``shrink`` m)."""
    out = np.zeros(len(xy), bool)
    for rect in rects:
        local = _to_rect_frame(xy, rect)
        out |= (np.abs(local[:, 0]) < rect[2] - shrink) & (np.abs(local[:, 1]) < rect[3] - shrink)
    return out


def segments_blocked(origin: np.ndarray, targets: np.ndarray, rects: list[Rect], shrink: float = 0.1) -> np.ndarray:
    """Whether the 2D segment origin (2,) → target (n, 2) crosses any rectangle (slab test).

    Rectangles are shrunk by ``shrink`` so that faces lying on an occluder's own walls are not hidden
    by it (their back sides are removed by the facing test instead).
    """
    blocked = np.zeros(len(targets), bool)
    for rect in rects:
        o = _to_rect_frame(origin[None], rect)[0]
        t = _to_rect_frame(targets, rect)
        d = t - o
        t_lo, t_hi = np.zeros(len(t)), np.ones(len(t))
        for a, half in ((0, rect[2] - shrink), (1, rect[3] - shrink)):
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-half - o[a]) / d[:, a], (half - o[a]) / d[:, a]
            parallel = np.abs(d[:, a]) < 1e-12
            lo, hi = np.where(parallel, -np.inf, np.minimum(t1, t2)), np.where(parallel, np.inf, np.maximum(t1, t2))
            if abs(o[a]) > half:
                lo = np.where(parallel, np.inf, lo)
            t_lo, t_hi = np.maximum(t_lo, lo), np.minimum(t_hi, hi)
        blocked |= t_lo < t_hi
    return blocked


@dataclass(frozen=True)
class FieldOfView:
    """A forward-looking camera at each sensor position: ``rotations`` (k, 3, 3) camera → map, columns
    forward, left, up (map frame); a rectangular pinhole field of view of ``hfov_deg`` × ``vfov_deg``
    degrees (full angles) about the forward axis."""

    rotations: np.ndarray
    hfov_deg: float
    vfov_deg: float


def in_frustum(local: np.ndarray, hfov_deg: float, vfov_deg: float) -> np.ndarray:
    """Whether camera-frame directions (n, 3) (x forward, y left, z up) lie inside a pinhole field of view
    of ``hfov_deg`` × ``vfov_deg`` degrees (full angles)."""
    x = local[:, 0]
    return ((x > 0) & (np.abs(local[:, 1]) <= x * np.tan(np.radians(hfov_deg) / 2))
            & (np.abs(local[:, 2]) <= x * np.tan(np.radians(vfov_deg) / 2)))


def visible_faces(centroids: np.ndarray, normals: np.ndarray, sensors: np.ndarray, max_range: float,
                  occluders: list[Rect], hidden: list[Rect] | None = None,
                  fov: FieldOfView | None = None) -> np.ndarray:
    """Mask of faces seen from at least one sensor position (k, 3): within ``max_range`` metres,
    facing the sensor, not behind an occluder, (for ground faces) not under a ``hidden`` footprint, and
    with a ``fov``, inside that camera's field of view (``fov.rotations[k]`` at ``sensors[k]``)."""
    seen = np.zeros(len(centroids), bool)
    for k, p in enumerate(sensors):
        diff = p - centroids
        dist = np.linalg.norm(diff, axis=1)
        idx = np.flatnonzero(~seen & (dist <= max_range) & (np.einsum("ij,ij->i", diff, normals) > 0))
        if fov is not None and len(idx):
            idx = idx[in_frustum(-diff[idx] @ fov.rotations[k], fov.hfov_deg, fov.vfov_deg)]
        if len(idx) == 0:
            continue
        near = [r for r in occluders if np.hypot(r[0] - p[0], r[1] - p[1]) < max_range + r[2] + r[3]]
        if near:
            idx = idx[~segments_blocked(p[:2], centroids[idx, :2], near)]
        seen[idx] = True
    if hidden:
        cand = np.flatnonzero(seen)
        seen[cand[inside_rects(centroids[cand, :2], hidden)]] = False
    return seen
