"""Primitive triangle meshes for the synthetic world (world/map frame, metres, z up).

Every builder returns ``(vertices (n, 3) float64, faces (m, 3) int64)`` with outward-facing
(counter-clockwise) winding, subdivided so that no edge is longer than ``max_edge`` metres: submaps
crop the world face by face, so faces must be small compared with the sensor range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

Mesh = tuple[np.ndarray, np.ndarray]


@dataclass
class Part:
    """One labelled closed (or open, for markings) mesh of the world, map frame.

    ``session``: index of the only session that sees it (a transient object), or None (static).
    ``footprint``: (cx, cy, half_length, half_width, yaw) hiding the ground below it; ``occluder``:
    blocks the view of what lies behind it (buildings).
    """

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray
    kind: str
    session: int | None = None
    footprint: tuple[float, float, float, float, float] | None = None
    occluder: bool = False


def _finish(mesh: trimesh.Trimesh, max_edge: float) -> Mesh:
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    if max_edge > 0:
        v, f = trimesh.remesh.subdivide_to_size(v, f, max_edge=max_edge)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


def _place(mesh: trimesh.Trimesh, xy: np.ndarray, z: float, yaw: float) -> trimesh.Trimesh:
    """Rotate by ``yaw`` (rad, about +z) and translate to ``(x, y, z)`` (map frame)."""
    m = trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])
    m[:3, 3] = [xy[0], xy[1], z]
    mesh.apply_transform(m)
    return mesh


def box(xy: np.ndarray, z0: float, size: tuple[float, float, float], yaw: float, max_edge: float) -> Mesh:
    """Closed box of ``size`` (length along yaw, width, height) whose bottom face is at height z0."""
    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation([0.0, 0.0, size[2] / 2])
    return _finish(_place(mesh, xy, z0, yaw), max_edge)


def cylinder(xy: np.ndarray, z0: float, radius: float, height: float, max_edge: float, sections: int = 10) -> Mesh:
    """Closed vertical cylinder standing on z0."""
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    mesh.apply_translation([0.0, 0.0, height / 2])
    return _finish(_place(mesh, xy, z0, 0.0), max_edge)


def cone(xy: np.ndarray, z0: float, radius: float, height: float, max_edge: float) -> Mesh:
    """Closed cone (traffic cone) standing on z0."""
    mesh = trimesh.creation.cone(radius=radius, height=height, sections=10)
    return _finish(_place(mesh, xy, z0, 0.0), max_edge)


def ellipsoid(center: np.ndarray, radii: tuple[float, float, float], max_edge: float) -> Mesh:
    """Closed ellipsoid (tree crown, bush) centred at ``center``."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    mesh.apply_scale(radii)
    mesh.apply_translation(center)
    return _finish(mesh, max_edge)


def ribbon(centre: np.ndarray, width: float) -> Mesh:
    """Upward-facing strip of ``width`` metres along a 3D polyline ``centre`` (k, 3), k ≥ 2."""
    d = np.gradient(centre[:, :2], axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True) + 1e-12
    left = np.stack([-d[:, 1], d[:, 0], np.zeros(len(d))], axis=1) * (width / 2)
    v = np.concatenate([centre - left, centre + left])  # right side, then left side
    k = len(centre)
    i = np.arange(k - 1)
    f = np.concatenate([np.stack([i, i + 1, i + k], 1), np.stack([i + 1, i + k + 1, i + k], 1)])
    return v.astype(np.float64), f.astype(np.int64)


def grid(xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Regular grid over the axes ``xs`` (nx,), ``ys`` (ny,): xy vertices (nx·ny, 2) and upward faces.

    Vertex (ix, iy) has index ``iy · nx + ix``.
    """
    gx, gy = np.meshgrid(xs, ys)
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    nx, ny = len(xs), len(ys)
    ix, iy = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (iy * nx + ix).ravel()
    b, c, d = a + 1, a + nx, a + nx + 1
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return xy, faces.astype(np.int64)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (m, 3) and areas (m,) (m²) of triangles."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    return cross / np.maximum(norm, 1e-12)[:, None], 0.5 * norm


def merge(parts: list[Mesh]) -> Mesh:
    """Concatenate meshes, re-indexing faces."""
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    v = np.concatenate([p[0] for p in parts])
    f = np.concatenate([p[1] + o for p, o in zip(parts, offsets, strict=True)])
    return v, f


def compact(vertices: np.ndarray, faces: np.ndarray) -> Mesh:
    """Drop vertices no face uses."""
    used, inverse = np.unique(faces.ravel(), return_inverse=True)
    return vertices[used], inverse.reshape(-1, 3).astype(np.int64)
