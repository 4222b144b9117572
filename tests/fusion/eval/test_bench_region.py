"""Multi-tile bench helpers: the seam check and mesh merging (no fusion run)."""

from __future__ import annotations

import numpy as np

from fusion.eval.bench_region import merge_meshes, seam_gaps
from fusion.types import FusedMesh, FusionResult


def _mesh(vertices: np.ndarray) -> FusedMesh:
    n = len(vertices)
    faces = np.array([[0, 1, 2]], np.int32) if n >= 3 else np.zeros((0, 3), np.int32)
    return FusedMesh(vertices.astype(np.float32), faces, np.ones(n, np.uint8), np.ones(n, np.float32),
                     np.ones(len(faces), np.uint8))


def _result(vertices: np.ndarray) -> FusionResult:
    return FusionResult(_mesh(vertices), {}, {}, {}, {})


def test_seam_gaps_zero_when_border_vertices_coincide_and_flags_a_gap() -> None:
    border = np.array([[10.0, y, 0.0] for y in np.arange(0.0, 10.0, 0.5)])
    left = np.concatenate([border, [[5.0, 5.0, 0.0]]])
    right = np.concatenate([border, [[15.0, 5.0, 0.0]]])
    out = seam_gaps({(0, 0): _result(left), (1, 0): _result(right)}, 10.0, 0.25)
    assert out["seam_borders"] == 1 and out["seam_max_m"] == 0.0 and out["seam_far_share"] == 0.0
    shifted = right.copy()
    shifted[:len(border), 2] += 0.6  # the right tile's surface meets the border 0.6 m higher
    out = seam_gaps({(0, 0): _result(left), (1, 0): _result(shifted)}, 10.0, 0.25)
    assert abs(out["seam_max_m"] - 0.6) < 1e-5 and out["seam_far_share"] == 1.0


def test_merge_meshes_reindexes_faces() -> None:
    a = _mesh(np.eye(3))
    b = _mesh(np.eye(3) + 5)
    m = merge_meshes([a, FusedMesh.empty(), b])
    assert len(m.vertices) == 6 and m.faces.tolist() == [[0, 1, 2], [3, 4, 5]]
