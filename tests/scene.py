"""A tiny synthetic street for fusion tests: a ground plane with boxes and a wall, in local frames."""

from __future__ import annotations

import numpy as np
import trimesh

from fusion.types import Pose, SemanticMesh, Sigma, SubmapInput


def ground(size: float, step: float, z: float = 0.0) -> trimesh.Trimesh:
    n = int(round(size / step)) + 1
    xs = np.linspace(0.0, size, n)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return trimesh.Trimesh(v, f, process=False)


def street(size: float = 16.0, extra_box: bool = False) -> SemanticMesh:
    """Ground (label road=1) with two boxes (vehicle=10, building=5) and a wall (fence=6), z up."""
    parts = [(ground(size, 1.0), 1)]
    for centre, ext, label in [
        ((4.0, 5.0, 1.0), (2.0, 3.0, 2.0), 10),
        ((11.0, 10.0, 1.5), (3.0, 2.0, 3.0), 5),
        ((8.0, 13.5, 1.25), (8.0, 0.6, 2.5), 6),
    ] + ([((12.0, 4.0, 1.0), (2.0, 2.0, 2.0), 11)] if extra_box else []):
        box = trimesh.creation.box(extents=ext)
        box = box.subdivide().subdivide()
        box.apply_translation(centre)
        parts.append((box, label))
    verts, faces, labels, off = [], [], [], 0
    for mesh, label in parts:
        verts.append(np.asarray(mesh.vertices))
        faces.append(np.asarray(mesh.faces) + off)
        labels.append(np.full(len(mesh.faces), label))
        off += len(mesh.vertices)
    return SemanticMesh(np.concatenate(verts), np.concatenate(faces).astype(np.int64), np.concatenate(labels))


def noisy(mesh: SemanticMesh, sigma: float, rng: np.random.Generator) -> SemanticMesh:
    return SemanticMesh(mesh.vertices + rng.normal(0, sigma, mesh.vertices.shape), mesh.faces, mesh.face_labels)


def rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg / 2)
    return np.array([np.cos(a), 0.0, 0.0, np.sin(a)])


def two_sessions(offset: tuple[float, float, float] = (0.5, -0.4, 0.0), yaw_deg: float = 0.0,
                 seed: int = 0) -> tuple[list[SubmapInput], Pose]:
    """Two noisy copies of the street; session "b" starts with a wrong pose. Returns submaps and b's true pose."""
    rng = np.random.default_rng(seed)
    base = street()
    truth = Pose.identity()
    wrong = Pose(np.asarray(offset, dtype=np.float64), rot_z(yaw_deg))
    subs = [
        SubmapInput("a", "sa", 0, noisy(base, 0.01, rng), Pose.identity(), Pose.identity(), Sigma(1.0, 1.0)),
        SubmapInput("b", "sb", 0, noisy(street(extra_box=True), 0.01, rng), wrong, Pose.identity(), Sigma(1.0, 1.0)),
    ]
    return subs, truth


def tiny_config(**changes: object):  # noqa: ANN201
    """A few-second CPU configuration for 16 m test tiles."""
    from fusion.config import FusionConfig

    base = FusionConfig.preset("cpu").with_(
        iterations=80, surface_samples=1024, space_samples=1024, tile_margin_m=4.0, num_levels=6,
        lod_start_levels=3, base_resolution=8, max_resolution=96, log2_table_size=14, pool_points=40_000,
        pe_frequencies=4, geo_hidden=32, sem_hidden=32, extract_voxel_m=0.25, align_iterations_per_tile=80,
        schedule_full_cover=1e-3,  # any data is a full tile: the full schedule (the 16 m street fills part of a box)
    )
    return base.with_(**changes)
