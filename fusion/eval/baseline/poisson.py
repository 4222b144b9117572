"""Reconstruction half of the classical baseline: oriented samples → Poisson mesh → labels.

The paper's baseline meshes each tile with screened Poisson surface reconstruction (Kazhdan & Hoppe
2013) on 1,000,000 oriented points sampled from the aligned submaps, then transfers labels from the
input meshes by a 5-nearest-neighbour majority. Open3D (optional extra ``fleetmap[baseline]``) runs
the Poisson solver; it is imported lazily so that this module imports without it.

Frames: samples are drawn in each submap's local frame and moved to the map frame with the submap's
(refined) pose; everything returned is in the map frame, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from fusion.labels import NUM_CLASSES
from fusion.types import FusedMesh, Pose, SemanticMesh, TileSpec


@dataclass
class OrientedSamples:
    """Points on a surface with unit normals and face labels: points/normals (n, 3), labels (n,)."""

    points: np.ndarray
    normals: np.ndarray
    labels: np.ndarray

    def transformed(self, pose: Pose) -> OrientedSamples:
        """The samples moved from the source (submap-local) into the pose's target frame."""
        r = pose.rotation()
        return OrientedSamples(pose.apply(self.points), self.normals @ r.T, self.labels)

    @staticmethod
    def concatenate(parts: list[OrientedSamples]) -> OrientedSamples:
        if not parts:
            return OrientedSamples(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
        return OrientedSamples(
            np.concatenate([p.points for p in parts]),
            np.concatenate([p.normals for p in parts]),
            np.concatenate([p.labels for p in parts]),
        )


def mesh_area(mesh: SemanticMesh) -> float:
    """Total triangle area of a submap mesh, square metres."""
    tri = mesh.vertices[mesh.faces]
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def sample_oriented(mesh: SemanticMesh, count: int, rng: np.random.Generator) -> OrientedSamples:
    """``count`` points uniformly (area-weighted) on a submap mesh, in its local frame.

    Normals are the face normals of the sampled faces (winding as uploaded), labels the face labels.
    """
    if count <= 0 or len(mesh.faces) == 0:
        return OrientedSamples(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
    tm = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=False, validate=False)
    points, face_index = trimesh.sample.sample_surface(tm, int(count), seed=rng)
    normals = np.asarray(tm.face_normals)[face_index]
    return OrientedSamples(
        np.asarray(points, np.float64), normals, mesh.face_labels[face_index].astype(np.int64)
    )


def majority_labels(neighbour_labels: np.ndarray, num_classes: int = NUM_CLASSES) -> np.ndarray:
    """Most common label per row of ``neighbour_labels`` (n, k); ties go to the smaller id."""
    n = neighbour_labels.shape[0]
    counts = np.zeros((n, num_classes), np.int64)
    np.add.at(counts, (np.repeat(np.arange(n), neighbour_labels.shape[1]), neighbour_labels.ravel()), 1)
    return counts.argmax(axis=1)


def poisson_mesh(
    samples: OrientedSamples,
    depth: int,
    density_quantile: float,
    max_distance_m: float | None,
    scale: float = 1.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Screened Poisson reconstruction of oriented map-frame samples (Open3D).

    Vertices whose Poisson density is below the ``density_quantile`` of all densities are dropped
    (the watertight solver closes the surface far from the data with low-density sheets); with
    ``max_distance_m`` also those farther than that from every sample. Returns vertices (n, 3)
    float64 and faces (m, 3) int64 in the map frame.
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(samples.points))
    pcd.normals = o3d.utility.Vector3dVector(samples.normals)
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth, scale=scale)
    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.triangles).astype(np.int64)
    keep = np.ones(len(vertices), bool)
    dens = np.asarray(densities)
    if density_quantile > 0 and len(dens):
        keep &= dens >= np.quantile(dens, density_quantile)
    if max_distance_m is not None and len(vertices):
        dist, _ = cKDTree(samples.points).query(vertices, k=1)
        keep &= dist <= max_distance_m
    return _keep_vertices(vertices, faces, keep)


def _keep_vertices(
    vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Drops the faces touching a dropped vertex, then the unreferenced vertices."""
    faces = faces[keep[faces].all(axis=1)]
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    remap = -np.ones(len(vertices), np.int64)
    remap[used] = np.arange(int(used.sum()))
    return vertices[used], remap[faces]


def label_and_clip(
    vertices: np.ndarray, faces: np.ndarray, samples: OrientedSamples, tile: TileSpec, k: int = 5
) -> FusedMesh:
    """Labels a map-frame mesh from labelled samples and clips it to the tile.

    Vertex label: majority of the ``k`` nearest samples (scipy cKDTree); face label: majority of its
    three vertex labels (the first vertex's label when all differ); confidence 1 everywhere (Poisson
    has none). Faces are kept when their centroid lies in the tile's ``[min, max)`` xy box.
    """
    if len(faces) == 0 or len(samples.points) == 0:
        return FusedMesh.empty()
    centroid = vertices[faces].mean(axis=1)
    (x0, y0), (x1, y1) = tile.xy_min, tile.xy_max
    inside = (centroid[:, 0] >= x0) & (centroid[:, 0] < x1) & (centroid[:, 1] >= y0) & (centroid[:, 1] < y1)
    keep = np.zeros(len(vertices), bool)
    keep[faces[inside].ravel()] = True
    vertices, faces = _keep_vertices(vertices, faces[inside], keep)
    if len(faces) == 0:
        return FusedMesh.empty()
    k = min(k, len(samples.points))
    _, idx = cKDTree(samples.points).query(vertices, k=k)
    idx = idx.reshape(len(vertices), k)
    vertex_labels = majority_labels(samples.labels[idx])
    fl = vertex_labels[faces]
    face_labels = np.where(fl[:, 1] == fl[:, 2], fl[:, 1], fl[:, 0])
    return FusedMesh(
        vertices=vertices.astype(np.float32),
        faces=faces.astype(np.int32),
        vertex_labels=vertex_labels.astype(np.uint8),
        vertex_confidence=np.ones(len(vertices), np.float32),
        face_labels=face_labels.astype(np.uint8),
    )
