"""fusion.meshio: submap PLY validation (every error code), PLY/GLB writers, confidence filter."""

from __future__ import annotations

import io
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import plyfile
import pytest
import trimesh

from fusion import meshio
from fusion.errors import MeshValidationError
from fusion.labels import LABELS
from fusion.meshio import (
    MeshLimits,
    filter_confidence,
    read_fused_ply,
    read_submap_ply,
    write_fused_ply,
    write_glb,
    write_submap_ply,
)
from fusion.types import FusedMesh, SemanticMesh

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


# ------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_submap_round_trip(encoding: str) -> None:
    mesh = semantic_mesh()
    data = write_submap_ply(mesh, encoding)
    assert f"format {encoding} 1.0".encode() in data[:200]
    back = read_submap_ply(data)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.face_labels, mesh.face_labels)
    assert back.vertices.dtype == np.float64 and back.faces.dtype == np.int64


def test_write_submap_rejects_unknown_encoding() -> None:
    with pytest.raises(ValueError):
        write_submap_ply(semantic_mesh(), "binary_middle_endian")


def test_ascii_text_reads() -> None:
    mesh = read_submap_ply(ASCII_OK.encode())
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(mesh.face_labels, [ROAD, 0])


@pytest.mark.parametrize("label_type", ["i1", "u2", "i4", "u4"])
def test_double_coordinates_and_any_integer_label_type(label_type: str) -> None:
    face = faces([[0, 1, 2], [0, 2, 3]], extra=[("label", label_type, [SIDEWALK, ROAD])])
    mesh = read_submap_ply(ply_bytes(vertices(QUAD + 0.123456789, "f8"), face))
    np.testing.assert_array_equal(mesh.vertices, QUAD + 0.123456789)
    np.testing.assert_array_equal(mesh.face_labels, [SIDEWALK, ROAD])


def test_big_endian_packed_by_hand() -> None:
    # plyfile's writer puts scalars of list elements in native order, so build the bytes directly
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\n"
        "property double z\nelement face 1\nproperty list uchar uint vertex_indices\n"
        "property ushort label\nend_header\n"
    )
    body = b"".join(struct.pack(">3d", *p) for p in QUAD[:3] * 1.5) + struct.pack(
        ">B3IH", 3, 2, 1, 0, OBSTACLE
    )
    mesh = read_submap_ply(header.encode() + body)
    np.testing.assert_array_equal(mesh.vertices, QUAD[:3] * 1.5)
    np.testing.assert_array_equal(mesh.faces, [[2, 1, 0]])
    np.testing.assert_array_equal(mesh.face_labels, [OBSTACLE])


@pytest.mark.parametrize("alias", ["class", "semantic"])
def test_label_aliases(alias: str) -> None:
    face = faces([[0, 1, 2], [0, 2, 3]], extra=[(alias, "u1", [OBSTACLE, ROAD])])
    mesh = read_submap_ply(ply_bytes(vertices(), face))
    np.testing.assert_array_equal(mesh.face_labels, [OBSTACLE, ROAD])


def test_vertex_index_alias() -> None:
    face = faces([[0, 1, 2]], index_name="vertex_index", extra=[("label", "u1", [ROAD])])
    mesh = read_submap_ply(ply_bytes(vertices(), face))
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2]])


def test_vertex_labels_majority_and_tie_goes_to_first_vertex() -> None:
    vertex = vertices(extra=[("label", "u1", [ROAD, SIDEWALK, SIDEWALK, OBSTACLE])])
    face = faces([[0, 1, 2], [0, 1, 3], [3, 0, 1]])
    mesh = read_submap_ply(ply_bytes(vertex, face))
    np.testing.assert_array_equal(mesh.face_labels, [SIDEWALK, ROAD, OBSTACLE])


def test_face_label_wins_over_vertex_label_and_colours() -> None:
    road = LABELS[ROAD].color
    vertex = vertices(extra=[("label", "u1", [SIDEWALK] * 4), ("red", "u1", [road[0]] * 4)])
    face = faces([[0, 1, 2]], extra=[("label", "u1", [OBSTACLE])])
    assert read_submap_ply(ply_bytes(vertex, face)).face_labels.tolist() == [OBSTACLE]


def colour_fields(ids: list[int]) -> list:
    colours = np.array([LABELS[i].color for i in ids])
    return [(c, "u1", colours[:, k]) for k, c in enumerate(("red", "green", "blue"))]


def test_vertex_colour_labels() -> None:
    vertex = vertices(extra=colour_fields([ROAD, ROAD, SIDEWALK, SIDEWALK]))
    mesh = read_submap_ply(ply_bytes(vertex, faces([[0, 1, 2], [2, 3, 0]])))
    np.testing.assert_array_equal(mesh.face_labels, [ROAD, SIDEWALK])


def test_face_colours_come_before_vertex_colours() -> None:
    vertex = vertices(extra=colour_fields([ROAD] * 4))
    face = faces([[0, 1, 2], [0, 2, 3]], extra=colour_fields([OBSTACLE, SIDEWALK]))
    mesh = read_submap_ply(ply_bytes(vertex, face))
    np.testing.assert_array_equal(mesh.face_labels, [OBSTACLE, SIDEWALK])


def test_polygons_are_fan_triangulated_with_their_label() -> None:
    points = np.vstack([QUAD, [[2, 0, 0], [3, 1, 0], [2, 2, 0]]])
    face = faces([[0, 1, 2, 3], [1, 4, 5, 6, 2], [3, 2, 6]], extra=[("label", "u1", [ROAD, OBSTACLE, 0])])
    for text in (False, True):
        mesh = read_submap_ply(ply_bytes(vertices(points), face, text=text))
        np.testing.assert_array_equal(
            mesh.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 6], [1, 6, 2], [3, 2, 6]]
        )
        np.testing.assert_array_equal(mesh.face_labels, [ROAD, ROAD, OBSTACLE, OBSTACLE, OBSTACLE, 0])


# ------------------------------------------------------------------------------------- error codes


def test_malformed_ply() -> None:
    expect_code(b"solid cube\nfacet normal 0 0 1\n", "malformed_ply")
    expect_code(b"ply\nformat ascii 1.0\nelement vertex 4\n", "malformed_ply")  # no end_header
    expect_code(ASCII_OK.replace("format ascii", "format utf8").encode(), "malformed_ply")
    expect_code(ASCII_OK.replace("element vertex 4", "element vertex four").encode(), "malformed_ply")
    expect_code(ASCII_OK.replace("0 1 0\n", "0 one 0\n").encode(), "malformed_ply")
    expect_code(ASCII_OK.replace("property float z", "property int z").encode(), "malformed_ply")
    expect_code(b"", "malformed_ply")


def test_truncated_binary() -> None:
    data = write_submap_ply(semantic_mesh())
    expect_code(data[:-3], "truncated_ply")
    expect_code(data[: data.index(b"end_header") + 11 + 20], "truncated_ply")


def test_count_mismatch() -> None:
    expect_code(write_submap_ply(semantic_mesh()) + b"\x00\x00\x00\x00", "count_mismatch")
    expect_code((ASCII_OK + "3 0 1 2 1\n").encode(), "count_mismatch")
    expect_code(ASCII_OK.rsplit("3 0 2 3 0\n", 1)[0].encode(), "count_mismatch")
    assert read_submap_ply((ASCII_OK + "\n\n").encode()).faces.shape == (2, 3)  # trailing blank lines ok


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


def test_missing_property() -> None:
    expect_code(
        ascii_ply("float x,float y", f"{TRI},uchar label", ["0 0", "1 0", "1 1"], ["3 0 1 2 1"]),
        "missing_property",
    )
    expect_code(ascii_ply(XYZ, None, ["0 0 0"], []), "missing_property")
    expect_code(
        ascii_ply(XYZ, "list uchar int corners,uchar label", ["0 0 0"] * 3, ["3 0 1 2 1"]), "missing_property"
    )
    expect_code(
        b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n",
        "missing_property",
    )


def test_bad_vertex_index() -> None:
    expect_code(ASCII_OK.replace("3 0 2 3 0", "3 0 2 4 0").encode(), "bad_vertex_index")
    expect_code(ASCII_OK.replace("3 0 2 3 0", "3 0 -1 3 0").encode(), "bad_vertex_index")


def test_faces_need_three_vertices() -> None:
    expect_code(ASCII_OK.replace("3 0 2 3 0", "2 0 2 0").encode(), "not_triangles")


def test_non_finite_coordinates() -> None:
    expect_code(ASCII_OK.replace("1 1 0\n", "1 nan 0\n").encode(), "non_finite_coordinates")
    expect_code(ASCII_OK.replace("1 1 0\n", "inf 1 0\n").encode(), "non_finite_coordinates")


def test_coordinate_limit_per_axis() -> None:
    expect_code(ASCII_OK.replace("1 1 0\n", "1 1 -1000.5\n").encode(), "coordinate_limit")
    # 800 m on two axes is 1131 m away, but every axis is within the limit
    assert read_submap_ply(ASCII_OK.replace("1 1 0\n", "800 800 0\n").encode()).vertices[2, 0] == 800
    expect_code(
        ASCII_OK.replace("1 1 0\n", "60 1 0\n").encode(), "coordinate_limit", MeshLimits(max_coordinate_m=50)
    )


def test_unknown_label() -> None:
    expect_code(ASCII_OK.replace("3 0 1 2 1", "3 0 1 2 12").encode(), "unknown_label")
    face = faces([[0, 1, 2]], extra=[("label", "i2", [-1])])
    expect_code(ply_bytes(vertices(), face), "unknown_label")
    vertex = vertices(extra=[("label", "u1", [1, 1, 1, 40])])
    expect_code(ply_bytes(vertex, faces([[0, 1, 2]])), "unknown_label")
    float_labels = faces([[0, 1, 2]], extra=[("label", "f4", [1.0])])
    expect_code(ply_bytes(vertices(), float_labels), "unknown_label")
    # fewer labels configured: 11 is out of range
    expect_code(
        ASCII_OK.replace("3 0 1 2 1", "3 0 1 2 11").encode(), "unknown_label", MeshLimits(num_labels=5)
    )


def test_colour_matching_no_label_is_unknown_label() -> None:
    extra = colour_fields([ROAD] * 4)
    extra[0] = ("red", "u1", [128, 128, 128, 127])
    error = expect_code(ply_bytes(vertices(extra=extra), faces([[0, 1, 2]])), "unknown_label")
    assert "127" in error.message


def test_no_labelled_face() -> None:
    expect_code(ASCII_OK.replace("3 0 1 2 1", "3 0 1 2 0").encode(), "no_labelled_face")
    error = expect_code(ascii_ply(XYZ, TRI, ["0 0 0", "1 0 0", "1 1 0"], ["3 0 1 2"]), "no_labelled_face")
    assert "label" in error.message


def test_too_many_faces_from_header_before_body() -> None:
    header = ASCII_OK.split("end_header\n")[0].replace("element face 2", "element face 5000000")
    expect_code((header + "end_header\n").encode(), "too_many_faces")  # no body needed


def test_too_many_faces_after_triangulation() -> None:
    face = faces([[0, 1, 2, 3]], extra=[("label", "u1", [ROAD])])
    expect_code(ply_bytes(vertices(), face), "too_many_faces", MeshLimits(max_faces=1))


def test_empty_mesh() -> None:
    empty = ASCII_OK.split("end_header\n")[0].replace("element face 2", "element face 0")
    expect_code((empty + "end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n").encode(), "empty_mesh")


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


@pytest.mark.parametrize(
    ("data", "code", "loc"),
    [
        (strip_ply(face_rows={13: "3 0 1 99 1"}), "bad_vertex_index", ("mesh", "face", 13)),
        (strip_ply(face_rows={7: "3 0 1 2 200"}), "unknown_label", ("mesh", "face", 7)),
        (strip_ply(face_rows={5: "2 0 1 1"}), "not_triangles", ("mesh", "face", 5)),
        (strip_ply(vertex_rows={17: "1 nan 0"}), "non_finite_coordinates", ("mesh", "vertex", 17)),
        (strip_ply(vertex_rows={4: "1 1 5000"}), "coordinate_limit", ("mesh", "vertex", 4)),
        (strip_ply(vertex_rows={9: "1 one 0"}), "malformed_ply", ("mesh", "vertex", 9)),
        (strip_ply(face_rows={3: "3 0 1 2"}), "malformed_ply", ("mesh", "face", 3)),
        (strip_ply(face_rows={3: "3 0 1 2 1 7"}), "malformed_ply", ("mesh", "face", 3)),
        (strip_ply().replace(b"element face 20", b"element face 22"), "count_mismatch", ("mesh", "face", 20)),
        (strip_ply().replace(b"property float z", b"property int z"), "malformed_ply", ("mesh", "header")),
        (b"not a ply", "malformed_ply", ("mesh", "header")),
        (strip_ply(face_rows={k: f"3 {k // 2} {k // 2 + 1} 11 0" for k in range(20)}), "no_labelled_face", ("mesh", "face")),
    ],
    ids=[
        "index", "label", "short-face", "nan", "far", "bad-token", "few-tokens", "more-tokens", "count",
        "header", "garbage", "unlabelled",
    ],
)
def test_errors_say_where(data: bytes, code: str, loc: tuple) -> None:
    assert expect_code(data, code).loc == loc


def test_binary_errors_say_where() -> None:
    mesh = semantic_mesh()
    mesh.faces[1, 2] = 7
    assert expect_code(write_submap_ply(mesh), "bad_vertex_index").loc == ("mesh", "face", 1)
    data = write_submap_ply(semantic_mesh())
    assert expect_code(data[:-3], "truncated_ply").loc == ("mesh", "face", 1)
    vertex = vertices(extra=[("label", "u1", [1, 1, 40, 1])])
    assert expect_code(ply_bytes(vertex, faces([[0, 1, 2]])), "unknown_label").loc == ("mesh", "vertex", 2)
    extra = colour_fields([ROAD] * 4)
    extra[0] = ("red", "u1", [128, 128, 128, 127])
    error = expect_code(ply_bytes(vertices(extra=extra), faces([[0, 1, 2]])), "unknown_label")
    assert error.loc == ("mesh", "vertex", 3)


# ------------------------------------------------------------------------------------- ASCII reader

GRID = np.array([[x * 0.5 - 1.25, y / 3, 0.1 * x * y] for y in range(3) for x in range(4)])
GRID_TRIS = [[0, 1, 4], [1, 5, 4], [1, 2, 5], [2, 6, 5], [4, 5, 8], [5, 9, 8], [6, 7, 10], [7, 11, 10]]


def ascii_vs_binary_cases() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    ids = [ROAD, SIDEWALK, OBSTACLE, 0, ROAD, 3, 4, SIDEWALK]
    vertex_ids = [ROAD, ROAD, SIDEWALK, OBSTACLE, 0, 3, 3, SIDEWALK, ROAD, 4, 5, 6]
    quads = [[0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [4, 5, 9, 8], [5, 6, 10], [6, 7, 11, 10]]
    return {
        "float": (vertices(GRID), faces(GRID_TRIS, extra=[("label", "u1", ids)])),
        "double": (vertices(GRID * 1e-3 + 0.1, "f8"), faces(GRID_TRIS, extra=[("label", "i4", ids)])),
        "extra-properties": (
            vertices(GRID, "f8", extra=[("nx", "f4", np.linspace(-1, 1, 12)), ("flags", "u4", np.arange(12) * 7**9)]),
            faces(GRID_TRIS, extra=[("quality", "f4", np.linspace(0, 1, 8)), ("label", "u2", ids)]),
        ),
        "label-before-list": (vertices(GRID), label_first(GRID_TRIS, ids)),
        "vertex-labels": (vertices(GRID, extra=[("semantic", "u1", vertex_ids)]), faces(GRID_TRIS)),
        "vertex-index-alias": (vertices(GRID), faces(GRID_TRIS, "vertex_index", extra=[("class", "i1", ids)])),
        "face-colours": (vertices(GRID), faces(GRID_TRIS, extra=colour_fields(ids))),
        "vertex-colours": (vertices(GRID, extra=colour_fields(vertex_ids)), faces(GRID_TRIS)),
        "quads": (vertices(GRID), faces(quads, extra=[("label", "u1", [1, 2, 3, 4, 5, 6])])),
    }


def label_first(lists: list[list[int]], ids: list[int]) -> np.ndarray:
    out = np.empty(len(lists), dtype=[("label", "u1"), ("vertex_indices", "O")])
    out["label"] = ids
    out["vertex_indices"] = [np.asarray(f, dtype=np.int32) for f in lists]
    return out


def plyfile_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(meshio, "_read_ascii", lambda *args: None)


@pytest.mark.parametrize("case", sorted(ascii_vs_binary_cases()))
def test_ascii_reader_equals_binary_and_plyfile(case: str, monkeypatch: pytest.MonkeyPatch) -> None:
    vertex, face = ascii_vs_binary_cases()[case]
    text = ply_bytes(vertex, face, text=True)
    fast = read_submap_ply(text)
    if case != "quads":  # the vectorised reader takes it: plyfile's would raise here
        with monkeypatch.context() as patch:
            patch.setattr(plyfile.PlyData, "read", None)
            read_submap_ply(text)
    binary = read_submap_ply(ply_bytes(vertex, face))
    plyfile_only(monkeypatch)
    slow = read_submap_ply(text)
    for other in (binary, slow):
        np.testing.assert_array_equal(fast.vertices, other.vertices)
        np.testing.assert_array_equal(fast.faces, other.faces)
        np.testing.assert_array_equal(fast.face_labels, other.face_labels)
        assert fast.faces.dtype == other.faces.dtype and fast.face_labels.dtype == other.face_labels.dtype


def test_ascii_reader_handles_crlf_and_tabs() -> None:
    crlf = ASCII_OK.replace("\n", "\r\n").replace("3 0 1 2 1", "3\t0  1 2 1 ").encode()
    mesh = read_submap_ply(crlf)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(mesh.face_labels, [ROAD, 0])


@pytest.mark.parametrize(
    ("data", "loc"),
    [
        (strip_ply(vertex_rows={6: "1 1"}), ("mesh", "vertex", 6)),  # too few values
        (strip_ply(vertex_rows={6: "1 1 0 0"}), ("mesh", "vertex", 6)),  # too many
        (strip_ply(vertex_rows={5: ""}), ("mesh", "vertex", 5)),  # a blank row
        (strip_ply(vertex_rows={21: "1 0x1 0"}), ("mesh", "vertex", 21)),  # not a number
        (strip_ply(vertex_rows={21: "1 \xff 0"}), ("mesh", "vertex", 21)),  # not even text
        (strip_ply(vertex_rows={3: "1 x 0", 8: "1 1"}), ("mesh", "vertex", 3)),  # the first error wins
        (strip_ply(vertex_rows={3: "1 1", 8: "1 x 0"}), ("mesh", "vertex", 3)),
        (strip_ply(face_rows={19: "3 0 1 2 one"}), ("mesh", "face", 19)),
        (strip_ply(face_rows={8: "3 0 1 2.5 1"}), ("mesh", "face", 8)),  # a float index
        (strip_ply(face_rows={8: "3 0 1 2 1", 9: "3 0 1 2 1 2"}), ("mesh", "face", 9)),
        (strip_ply(face_rows={11: "4 0 1 2 1"}), ("mesh", "face", 11)),  # count disagrees with the row
        (strip_ply(face_rows={2: "3 0 1 2 300"}), ("mesh", "face", 2)),  # label beyond uchar
        (strip_ply(face_rows={2: "3 0 1 2 -1"}), ("mesh", "face", 2)),
        (strip_ply(face_rows={4: "3 0 1 99999999999 1"}), ("mesh", "face", 4)),  # beyond int32
    ],
)
def test_ascii_reader_errors_match_plyfile(data: bytes, loc: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    fast = expect_code(data, "malformed_ply")
    assert fast.loc == loc, fast.message
    plyfile_only(monkeypatch)
    slow = expect_code(data, "malformed_ply")
    assert slow.loc in (loc, ("mesh",))  # plyfile's overflow errors name no row


@pytest.mark.parametrize("case", ["extra-properties", "vertex-colours", "label-before-list", "quads"])
def test_ascii_reader_agrees_with_plyfile_on_mutated_tokens(case: str, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(11)
    vertex, face = ascii_vs_binary_cases()[case]
    base = ply_bytes(vertex, face, text=True)
    head, body = base.split(b"end_header\n")
    replacements = [b"", b"x", b"1.5", b"-1", b"300", b"7", b"1e3", b"nan", b"1 2", b"\n", b"\t", b"0", b"3.0", b"+2"]

    def outcome(data: bytes) -> tuple:
        try:
            mesh = read_submap_ply(data)
        except MeshValidationError as error:
            return ("error", error.code)
        return ("ok", mesh.vertices.tobytes(), mesh.faces.tobytes(), mesh.face_labels.tobytes())

    cases = []
    for _ in range(300):
        tokens = body.split(b" ")
        for _ in range(rng.integers(1, 3)):
            k = int(rng.integers(0, len(tokens)))
            tokens[k] = replacements[int(rng.integers(0, len(replacements)))]
        cases.append(head + b"end_header\n" + b" ".join(tokens))
    fast = [outcome(case) for case in cases]
    plyfile_only(monkeypatch)
    slow = [outcome(case) for case in cases]
    assert fast == slow
    assert {o[0] for o in fast} == {"ok", "error"}


@pytest.mark.parametrize("cut", [1, 2, 7])
def test_truncated_ascii_body_is_count_mismatch(cut: int) -> None:
    data = strip_ply()
    body = data.split(b"end_header\n")[1].splitlines()
    error = expect_code(data.replace(b"\n".join(body), b"\n".join(body[:-cut])), "count_mismatch")
    assert error.loc == ("mesh", "face", 20 - cut)


def test_fuzzed_bytes_raise_only_validation_errors() -> None:
    rng = np.random.default_rng(7)
    polygon = ply_bytes(vertices(), faces([[0, 1, 2, 3], [0, 2, 3]], extra=[("label", "u1", [ROAD, 0])]))
    sources = [
        write_submap_ply(semantic_mesh(), e) for e in ("ascii", "binary_little_endian", "binary_big_endian")
    ]
    for base in [*sources, polygon]:
        cases = [base[:k] for k in range(0, len(base), 3)]
        for _ in range(150):
            flipped = bytearray(base)
            for position in rng.integers(0, len(base), size=rng.integers(1, 4)):
                flipped[position] = int(rng.integers(0, 256))
            cases.append(bytes(flipped))
        for case in cases:
            try:
                mesh = read_submap_ply(case)
            except MeshValidationError as error:
                assert error.code and error.message
            else:
                assert mesh.faces.shape[1] == 3


# ------------------------------------------------------------------------------------- fused meshes


def fused_mesh() -> FusedMesh:
    return FusedMesh(
        vertices=np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [5, 5, 1]], dtype=np.float32) + 640,
        faces=np.array([[0, 1, 2], [0, 2, 3], [2, 4, 3]], dtype=np.int32),
        vertex_labels=np.array([ROAD, ROAD, SIDEWALK, 3, OBSTACLE], dtype=np.uint8),
        vertex_confidence=np.array([0.9, 0.8, 0.75, 0.5, 0.99], dtype=np.float32),
        face_labels=np.array([ROAD, SIDEWALK, OBSTACLE], dtype=np.uint8),
    )


def test_fused_ply_properties_and_round_trip() -> None:
    mesh = fused_mesh()
    data = write_fused_ply(mesh)
    ply = plyfile.PlyData.read(io.BytesIO(data))
    assert not ply.text and ply.byte_order == "<"
    vertex, face = ply["vertex"], ply["face"]
    # the fused PLY's vertex layout spelled out again on purpose: the test pins the wire format, so it
    # must not read it from fusion.meshio (duplicates: deliberate)
    assert [(p.name, p.val_dtype) for p in vertex.properties] == [
        ("x", "f4"),
        ("y", "f4"),
        ("z", "f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("label", "u1"),
        ("confidence", "f4"),
    ]
    index = face.properties[0]
    assert isinstance(index, plyfile.PlyListProperty)
    assert (index.name, index.len_dtype, index.val_dtype) == ("vertex_indices", "u1", "i4")
    assert [(p.name, p.val_dtype) for p in face.properties[1:]] == [("label", "u1")]
    assert tuple(int(vertex[c][2]) for c in ("red", "green", "blue")) == LABELS[SIDEWALK].color

    back = read_fused_ply(data)
    for name in ("vertices", "faces", "vertex_labels", "vertex_confidence", "face_labels"):
        np.testing.assert_array_equal(getattr(back, name), getattr(mesh, name))
        assert getattr(back, name).dtype == getattr(mesh, name).dtype


def test_fused_ply_empty_round_trip() -> None:
    back = read_fused_ply(write_fused_ply(FusedMesh.empty()))
    assert back.vertices.shape == (0, 3) and back.faces.shape == (0, 3)


def test_read_fused_ply_rejects_a_submap_ply() -> None:
    with pytest.raises(MeshValidationError) as info:
        read_fused_ply(write_submap_ply(semantic_mesh()))
    assert info.value.code == "missing_property"


def test_glb_loads_back_with_label_colours() -> None:
    mesh = fused_mesh()
    scene = trimesh.load(io.BytesIO(write_glb(mesh)), file_type="glb")
    (geometry,) = scene.geometry.values()
    np.testing.assert_allclose(geometry.vertices, mesh.vertices)
    np.testing.assert_array_equal(geometry.faces, mesh.faces)
    np.testing.assert_array_equal(geometry.visual.vertex_colors[:, :3][4], LABELS[OBSTACLE].color)
    upright = scene.to_mesh()  # glTF is y-up: map z becomes glTF y
    np.testing.assert_allclose(upright.vertices[4], [645, 641, -645])


def test_glb_of_empty_mesh_is_a_valid_empty_scene() -> None:
    data = write_glb(FusedMesh.empty())
    assert data[:4] == b"glTF"
    scene = trimesh.load(io.BytesIO(data), file_type="glb")
    assert len(scene.geometry) == 0


def test_filter_confidence_drops_faces_and_reindexes() -> None:
    mesh = fused_mesh()
    kept = filter_confidence(mesh, 0.7)  # vertex 3 (0.5) is below: faces 1 and 2 go
    np.testing.assert_array_equal(kept.faces, [[0, 1, 2]])
    np.testing.assert_array_equal(kept.vertices, mesh.vertices[:3])
    np.testing.assert_array_equal(kept.face_labels, [ROAD])
    np.testing.assert_array_equal(kept.vertex_labels, [ROAD, ROAD, SIDEWALK])

    strict = filter_confidence(mesh, 0.76)  # vertex 2 (0.75) drops face 2 too; vertex 4 unreferenced
    assert strict.faces.shape == (0, 3) and strict.vertices.shape == (0, 3)
    everything = filter_confidence(mesh, 0.0)
    np.testing.assert_array_equal(everything.faces, mesh.faces)
    assert everything.faces.dtype == np.int32 and everything.vertex_confidence.dtype == np.float32


def test_filter_confidence_reindexes_after_a_dropped_vertex() -> None:
    mesh = fused_mesh()
    mesh.vertex_confidence[0] = 0.1
    kept = filter_confidence(mesh, 0.7)  # only face [2, 4, 3] ... vertex 3 is 0.5: nothing left
    assert len(kept.faces) == 0
    mesh.vertex_confidence[3] = 0.95
    kept = filter_confidence(mesh, 0.7)
    np.testing.assert_array_equal(kept.faces, [[0, 2, 1]])  # old vertices 2, 4, 3 -> 0, 2, 1
    np.testing.assert_array_equal(kept.vertices, mesh.vertices[[2, 3, 4]])


def test_io_and_geometry_modules_do_not_import_torch() -> None:
    code = "import sys, fusion.meshio, fusion.geo, fusion.tiles; sys.exit('torch' in sys.modules)"
    root = Path(__file__).resolve().parents[2]
    assert subprocess.run([sys.executable, "-c", code], cwd=root, check=False).returncode == 0
