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
from fusion.types import FusedMesh
from tests.fusion.ply_support import (
    ASCII_OK,
    OBSTACLE,
    QUAD,
    ROAD,
    SIDEWALK,
    TRI,
    XYZ,
    ascii_ply,
    colour_fields,
    expect_code,
    faces,
    ply_bytes,
    semantic_mesh,
    strip_ply,
    vertices,
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
    # API.md's layout written out on purpose, not read from fusion.meshio: the test pins the contract.
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
