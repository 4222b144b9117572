"""fusion.plyascii: the vectorised ASCII PLY reader against the binary path and plyfile, and its errors."""

from __future__ import annotations

import numpy as np
import plyfile
import pytest

from fusion import meshio
from fusion.errors import MeshValidationError
from fusion.meshio import read_submap_ply, write_submap_ply
from tests.fusion.ply_support import (
    ASCII_OK,
    OBSTACLE,
    ROAD,
    SIDEWALK,
    colour_fields,
    expect_code,
    faces,
    ply_bytes,
    semantic_mesh,
    strip_ply,
    vertices,
)

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
    monkeypatch.setattr(meshio, "read_ascii", lambda *args: None)


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
