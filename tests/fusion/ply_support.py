"""Building submap PLYs for the reader tests (tests/fusion/test_meshio.py, test_plyascii.py)."""

from __future__ import annotations

import io

import numpy as np
import plyfile
import pytest

from fusion.errors import MeshValidationError
from fusion.labels import LABELS
from fusion.meshio import MeshLimits, read_submap_ply
from fusion.types import SemanticMesh

QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
ROAD, SIDEWALK, OBSTACLE = 1, 2, 11


def semantic_mesh() -> SemanticMesh:
    return SemanticMesh(
        vertices=QUAD * 2.5 + [0.1, -0.2, 0.3],
        faces=np.array([[0, 1, 2], [0, 2, 3]]),
        face_labels=np.array([ROAD, 0]),
    )


def ply_bytes(vertex: np.ndarray, face: np.ndarray, text: bool = False, byte_order: str = "<") -> bytes:
    """PLY from structured arrays via plyfile (object fields become lists)."""
    elements = [plyfile.PlyElement.describe(vertex, "vertex"), plyfile.PlyElement.describe(face, "face")]
    stream = io.BytesIO()
    plyfile.PlyData(elements, text=text, byte_order=byte_order).write(stream)
    return stream.getvalue()


def vertices(points: np.ndarray = QUAD, dtype: str = "f4", extra: list | None = None) -> np.ndarray:
    fields = [("x", dtype), ("y", dtype), ("z", dtype)] + [(name, t) for name, t, _ in extra or []]
    out = np.empty(len(points), dtype=fields)
    for k, axis in enumerate("xyz"):
        out[axis] = points[:, k]
    for name, _, values in extra or []:
        out[name] = values
    return out


def faces(
    lists: list[list[int]], index_name: str = "vertex_indices", extra: list | None = None
) -> np.ndarray:
    fields = [(index_name, "O")] + [(name, t) for name, t, _ in extra or []]
    out = np.empty(len(lists), dtype=fields)
    out[index_name] = [np.asarray(f, dtype=np.int32) for f in lists]
    for name, _, values in extra or []:
        out[name] = values
    return out


def expect_code(data: bytes, code: str, limits: MeshLimits = MeshLimits()) -> MeshValidationError:
    with pytest.raises(MeshValidationError) as info:
        read_submap_ply(data, limits)
    assert info.value.code == code, info.value.message
    assert info.value.message
    assert info.value.loc and info.value.loc[0] == "mesh"  # every mesh error says where
    return info.value


ASCII_OK = (
    "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    "element face 2\nproperty list uchar int vertex_indices\nproperty uchar label\nend_header\n"
    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2 1\n3 0 2 3 0\n"
)


def colour_fields(ids: list[int]) -> list:
    colours = np.array([LABELS[i].color for i in ids])
    return [(c, "u1", colours[:, k]) for k, c in enumerate(("red", "green", "blue"))]


def ascii_ply(vertex_props: str, face_props: str, vertex_rows: list[str], face_rows: list[str]) -> bytes:
    head = f"ply\nformat ascii 1.0\nelement vertex {len(vertex_rows)}\n"
    head += "".join(f"property {p}\n" for p in vertex_props.split(",") if p)
    if face_props is not None:
        head += f"element face {len(face_rows)}\n" + "".join(
            f"property {p}\n" for p in face_props.split(",") if p
        )
    return (head + "end_header\n" + "".join(r + "\n" for r in vertex_rows + face_rows)).encode()


XYZ = "float x,float y,float z"
TRI = "list uchar int vertex_indices"


def strip_ply(n_faces: int = 20, face_rows: dict[int, str] | None = None, vertex_rows: dict[int, str] | None = None) -> bytes:
    """An ASCII strip of ``n_faces`` labelled triangles with some rows replaced."""
    n = n_faces // 2
    verts = [f"{x} {y} 0" for y in (0, 1) for x in range(n + 1)]
    tris = []
    for k in range(n):
        tris += [f"3 {k} {k + 1} {n + 1 + k} 1", f"3 {k + 1} {n + 2 + k} {n + 1 + k} 2"]
    for k, row in (vertex_rows or {}).items():
        verts[k] = row
    for k, row in (face_rows or {}).items():
        tris[k] = row
    return ascii_ply(XYZ, f"{TRI},uchar label", verts, tris)
