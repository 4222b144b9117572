"""Semantic mesh I/O: submap PLY upload validation, fused PLY / GLB export (torch-free).

Submap meshes are in the submap's *local* frame, fused meshes in the *map* frame; both in metres.
PLY conventions follow API.md. Parsing is plyfile's, except ASCII bodies of the usual layouts, which
``fusion.plyascii`` parses with numpy at close to binary speed; this module adds the checks API.md asks
for and turns every way a PLY can be broken into a ``MeshValidationError`` with a stable code and a
location (``("mesh", "header")``, ``("mesh", "vertex", k)``, ``("mesh", "face", k)``).
"""

from __future__ import annotations

import io
import struct
import tempfile
import warnings
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import plyfile
import trimesh

from fusion.errors import MeshValidationError
from fusion.gltf import FEATURE_ID_ATTRIBUTE, add_label_table, split_by_label
from fusion.labels import LABELS, UNLABELED
from fusion.plyascii import read_ascii
from fusion.types import FusedMesh, SemanticMesh

ENCODINGS: dict[str, Literal["=", "<", ">"]] = {
    "ascii": "=",
    "binary_little_endian": "<",
    "binary_big_endian": ">",
}
LABEL_NAMES = ("label", "class", "semantic")  # first present wins within an element
INDEX_NAMES = ("vertex_indices", "vertex_index")
UNKNOWN_LABEL_COLOR = (128, 128, 128)  # colour of ids beyond the default label table
_HEADER_MAX_BYTES = 64 * 1024
# Everything plyfile/numpy may raise on hostile bytes; mapped to MeshValidationError.
_DECODE_ERRORS = (
    plyfile.PlyParseError,
    ValueError,  # includes UnicodeDecodeError
    TypeError,
    IndexError,
    KeyError,
    OverflowError,
    struct.error,
    EOFError,
    MemoryError,
)


@dataclass(frozen=True)
class MeshLimits:
    """Upload limits: faces after triangulation, |coordinate| per axis in metres (local frame)."""

    max_faces: int = 2_000_000
    max_coordinate_m: float = 1000.0
    num_labels: int = len(LABELS)


HEADER: tuple[str, ...] = ("mesh", "header")


def _fail(code: str, message: str, loc: tuple[str | int, ...] = ("mesh",)) -> MeshValidationError:
    """The error for rule ``code``; ``loc`` says where: ``("mesh", "header")``, ``("mesh", "face", k)``..."""
    return MeshValidationError(message, code=code, loc=loc)


def _row_loc(exc: plyfile.PlyElementParseError) -> tuple[str | int, ...]:
    """Where plyfile stopped: element and row when it says so."""
    if exc.element is None:
        return ("mesh",)
    if exc.row is None:
        return ("mesh", exc.element.name)
    return ("mesh", exc.element.name, int(exc.row))


def _locate_row(header: plyfile.PlyData, row: int) -> tuple[str | int, ...]:
    """The element and index of the ``row``-th data row (counting across elements)."""
    for element in header.elements:
        if row < element.count:
            return ("mesh", element.name, row)
        row -= element.count
    return HEADER


# --------------------------------------------------------------------------------------------- reading


def _parse_header(data: bytes) -> tuple[plyfile.PlyData, int]:
    """The header (elements, counts, properties; no data) and the byte offset of the body."""
    if not data.startswith(b"ply"):
        raise _fail("malformed_ply", "not a PLY file: the first line must be 'ply'", HEADER)
    end = data.find(b"end_header", 0, _HEADER_MAX_BYTES)
    if end < 0:
        raise _fail("malformed_ply", "no 'end_header' line within the first 64 KiB of the PLY file", HEADER)
    stream = io.BytesIO(data[: end + len(b"end_header") + 2])
    try:
        # plyfile's header parser (private, stable since 0.x) reads only the header.
        header = plyfile.PlyData._parse_header(stream)
    except _DECODE_ERRORS as exc:
        raise _fail("malformed_ply", f"bad PLY header: {exc}", HEADER) from exc
    for element in header.elements:
        if element.count < 0:
            raise _fail("malformed_ply", f"element '{element.name}' has a negative count", HEADER)
        if element.count and not element.properties:
            # rows of zero bytes: plyfile would loop over a count no file size bounds
            raise _fail("malformed_ply", f"element '{element.name}' has rows but no properties", HEADER)
    return header, stream.tell()


def _min_body_bytes(header: plyfile.PlyData) -> int:
    """Smallest binary body the header allows (every list empty)."""
    total = 0
    for element in header.elements:
        row = 0
        for prop in element.properties:
            is_list = isinstance(prop, plyfile.PlyListProperty)
            row += np.dtype(prop.len_dtype if is_list else prop.val_dtype).itemsize
        total += row * element.count
    return total


def _truncation_loc(header: plyfile.PlyData, size: int) -> tuple[str | int, ...]:
    """The element and (lower-bound) row where a binary body of ``size`` bytes runs out."""
    for element in header.elements:
        row = sum(
            np.dtype(p.len_dtype if isinstance(p, plyfile.PlyListProperty) else p.val_dtype).itemsize
            for p in element.properties
        )
        if size < row * element.count:
            return ("mesh", element.name, size // row)
        size -= row * element.count
    return ("mesh",)


def _count_text_rows(body: bytes) -> int:
    body = body.strip()
    if not body:
        return 0
    newline = b"\n" if b"\n" in body else b"\r"
    return body.count(newline) + 1


def _check_body_size(header: plyfile.PlyData, body: bytes) -> None:
    """Cheap checks before parsing, so bogus counts never allocate huge arrays."""
    counts = ", ".join(f"{e.count} {e.name}" for e in header.elements)
    if header.text:
        rows, declared = _count_text_rows(body), sum(e.count for e in header.elements)
        if rows != declared:
            what = "fewer" if rows < declared else "more"
            raise _fail(
                "count_mismatch",
                f"the ASCII body has {rows} rows, {what} than the header's {declared} ({counts}); "
                "make the element counts match the data",
                _locate_row(header, rows),
            )
    elif len(body) < _min_body_bytes(header):
        raise _fail(
            "truncated_ply",
            f"the PLY body ({len(body)} bytes) is shorter than the header requires ({counts}); "
            "the file is truncated: re-export it or retry the upload",
            _truncation_loc(header, len(body)),
        )


def _read_body(data: bytes, header: plyfile.PlyData, offset: int, index_name: str) -> plyfile.PlyData:
    """Parse the whole file: ASCII bodies with ``read_ascii`` where it can; otherwise plyfile, binary
    files through a temporary file so plyfile can memory-map all-triangle faces (its per-row list
    reader is ~100x slower)."""
    if header.text:
        fast = read_ascii(header, data[offset:], index_name)
        if fast is not None:
            return fast
        try:
            with warnings.catch_warnings():  # numpy warns on empty lists; plyfile then raises
                warnings.simplefilter("ignore", UserWarning)
                return plyfile.PlyData.read(io.BytesIO(data))
        except plyfile.PlyElementParseError as exc:
            code = "count_mismatch" if exc.message == "early end-of-file" else "malformed_ply"
            raise _fail(code, f"bad PLY data: {exc}", _row_loc(exc)) from exc
        except _DECODE_ERRORS as exc:
            raise _fail("malformed_ply", f"bad PLY data: {exc}") from exc
    with tempfile.TemporaryFile() as tmp:
        tmp.write(data)
        for known in ({"face": {index_name: 3}}, {}):
            tmp.seek(0)
            try:
                ply = plyfile.PlyData.read(tmp, mmap="c" if known else False, known_list_len=known)
                ply = _materialise(ply)
            except plyfile.PlyElementParseError as exc:
                if known and exc.message == "unexpected list length":
                    continue  # polygons: take plyfile's general reader
                code = "truncated_ply" if exc.message == "early end-of-file" else "malformed_ply"
                raise _fail(code, f"bad PLY data: {exc}", _row_loc(exc)) from exc
            except _DECODE_ERRORS as exc:
                raise _fail("malformed_ply", f"bad PLY data: {exc}") from exc
            extra = len(data) - tmp.tell()
            if extra > 0:
                counts = ", ".join(f"{e.count} {e.name}" for e in header.elements)
                raise _fail(
                    "count_mismatch",
                    f"{extra} bytes follow the last element the header declares ({counts}); "
                    "make the element counts match the data",
                    HEADER,
                )
            return ply
    raise AssertionError("unreachable")  # pragma: no cover


def _materialise(ply: plyfile.PlyData) -> plyfile.PlyData:
    """Copy memory-mapped element data into memory (the temporary file goes away)."""
    for element in ply.elements:
        element.data = np.array(element.data)
    return ply


def _property(element: plyfile.PlyElement, names: tuple[str, ...]) -> plyfile.PlyProperty | None:
    by_name = {p.name: p for p in element.properties if not isinstance(p, plyfile.PlyListProperty)}
    return next((by_name[n] for n in names if n in by_name), None)


def _schema(header: plyfile.PlyData) -> str:
    """Check the header has what a submap needs; returns the face index property's name."""
    names = {e.name for e in header.elements}
    if "vertex" not in names:
        raise _fail("missing_property", "the PLY has no 'vertex' element", HEADER)
    if "face" not in names:
        raise _fail(
            "missing_property", "the PLY has no 'face' element: submaps must be triangle meshes", HEADER
        )
    vertex, face = header["vertex"], header["face"]
    for axis in "xyz":
        prop = _property(vertex, (axis,))
        if prop is None:
            raise _fail("missing_property", f"vertex property '{axis}' is missing (need x, y, z)", HEADER)
        if np.dtype(prop.val_dtype).kind != "f":
            raise _fail("malformed_ply", f"vertex property '{axis}' must be float or double", HEADER)
    lists = {p.name: p for p in face.properties if isinstance(p, plyfile.PlyListProperty)}
    index_name = next((n for n in INDEX_NAMES if n in lists), None)
    if index_name is None:
        raise _fail("missing_property", "face list property 'vertex_indices' is missing", HEADER)
    if np.dtype(lists[index_name].val_dtype).kind not in "iu":
        raise _fail("malformed_ply", f"face property '{index_name}' must be a list of integers", HEADER)
    return index_name


def _triangulate(lists: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate face index lists; returns triangles (m, 3) int64 and each one's source face."""
    flat: np.ndarray
    if lists.dtype != object:  # memory-mapped path: all faces are triangles
        tris = lists.astype(np.int64).reshape(len(lists), lists.shape[-1])
        lengths = np.full(len(tris), tris.shape[1], dtype=np.int64)
        flat = tris.reshape(-1)
    else:
        lengths = np.fromiter((len(f) for f in lists), dtype=np.int64, count=len(lists))
        chunks = [np.asarray(f, dtype=np.int64).reshape(-1) for f in lists]
        flat = np.concatenate(chunks) if chunks else np.zeros(0, dtype=np.int64)
    short = np.flatnonzero(lengths < 3)
    if short.size:
        raise _fail(
            "not_triangles",
            f"face {short[0]} has {lengths[short[0]]} vertices; faces need at least 3",
            ("mesh", "face", int(short[0])),
        )
    bad = np.flatnonzero((flat < 0) | (flat >= n_vertices))
    if bad.size:
        face = int(np.searchsorted(np.cumsum(lengths), bad[0], side="right"))
        raise _fail(
            "bad_vertex_index",
            f"face {face} refers to vertex {flat[bad[0]]}, but vertex indices must be in "
            f"0..{n_vertices - 1} ({bad.size} bad indices in all)",
            ("mesh", "face", face),
        )
    if np.all(lengths == 3):
        return flat.reshape(-1, 3), np.arange(len(lengths))
    n_tris = lengths - 2
    source = np.repeat(np.arange(len(lengths)), n_tris)
    starts = (np.cumsum(lengths) - lengths)[source]
    k = np.arange(len(source)) - np.repeat(np.cumsum(n_tris) - n_tris, n_tris)
    return np.stack([flat[starts], flat[starts + k + 1], flat[starts + k + 2]], axis=1), source


def _check_ids(values: np.ndarray, where: str, num_labels: int, element: str) -> np.ndarray:
    if values.dtype.kind not in "iu":
        raise _fail("unknown_label", f"{where} must be an integer type, not {values.dtype}", HEADER)
    values = values.astype(np.int64)
    out = (values < 0) | (values >= num_labels)
    if np.any(out):
        bad = np.unique(values[out])
        raise _fail(
            "unknown_label",
            f"{where}: label ids {bad[:5].tolist()} are not in the label set 0..{num_labels - 1} "
            "(GET /v1/labels)",
            ("mesh", element, int(np.flatnonzero(out)[0])),
        )
    return values


def _colour_ids(data: np.ndarray, where: str, num_labels: int) -> np.ndarray:
    """Label ids of exact label colours (red, green, blue); any other colour is unknown_label;
    ``where`` is the element's name."""
    rgb = np.stack([np.asarray(data[c], dtype=np.float64) for c in ("red", "green", "blue")], axis=1)
    keys = np.where(
        np.all((rgb >= 0) & (rgb <= 255) & (rgb == np.round(rgb)), axis=1),
        rgb[:, 0] * 65536 + rgb[:, 1] * 256 + rgb[:, 2],
        -1,
    ).astype(np.int64)
    table = {(lab.color[0] << 16) + (lab.color[1] << 8) + lab.color[2]: lab.id for lab in LABELS[:num_labels]}
    uniq, inverse = np.unique(keys, return_inverse=True)
    mapped = np.array([table.get(int(k), -1) for k in uniq], dtype=np.int64)
    if np.any(mapped < 0):
        index = int(np.flatnonzero(mapped[inverse.reshape(-1)] < 0)[0])
        first = rgb[index]
        raise _fail(
            "unknown_label",
            f"{where} colour {tuple(first.tolist())} matches no label colour; colours must equal a label "
            "colour exactly (GET /v1/labels)",
            ("mesh", where, index),
        )
    return mapped[inverse.reshape(-1)]


def _has_colour(element: plyfile.PlyElement) -> bool:
    return all(_property(element, (c,)) is not None for c in ("red", "green", "blue"))


def _majority(vertex_ids: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Face label = majority of its 3 vertices' labels; ties (all different) go to the first vertex."""
    a, b, c = (vertex_ids[tris[:, i]] for i in range(3))
    return np.where((b == c) & (a != b), b, a)


def _face_labels(
    ply: plyfile.PlyData, tris: np.ndarray, source: np.ndarray, limits: MeshLimits
) -> np.ndarray:
    """Labels per triangle from the first source API.md lists: face label, vertex label, face colour,
    vertex colour (aliases ``class`` and ``semantic`` for ``label``)."""
    face, vertex = ply["face"], ply["vertex"]
    n = limits.num_labels
    if (prop := _property(face, LABEL_NAMES)) is not None:
        return _check_ids(np.asarray(face.data[prop.name]), f"face property '{prop.name}'", n, "face")[source]
    if (prop := _property(vertex, LABEL_NAMES)) is not None:
        ids = _check_ids(np.asarray(vertex.data[prop.name]), f"vertex property '{prop.name}'", n, "vertex")
        return _majority(ids, tris)
    if _has_colour(face):
        return _colour_ids(face.data, "face", n)[source]
    if _has_colour(vertex):
        return _majority(_colour_ids(vertex.data, "vertex", n), tris)
    raise _fail(
        "no_labelled_face",
        "the PLY has no semantic labels: add a face or vertex property 'label' (or label colours)",
        HEADER,
    )


def read_submap_ply(data: bytes, limits: MeshLimits = MeshLimits()) -> SemanticMesh:
    """Parse and validate an uploaded submap PLY (local frame, metres) as API.md defines it.

    Raises ``MeshValidationError`` (``.code`` says which rule failed) for anything API.md rejects and
    for any bytes that are not a well-formed PLY; polygons are fan-triangulated.
    """
    header, offset = _parse_header(bytes(data))
    index_name = _schema(header)
    n_faces, n_vertices = header["face"].count, header["vertex"].count
    if n_faces > limits.max_faces:
        raise _fail(
            "too_many_faces", f"the mesh has {n_faces} faces; at most {limits.max_faces} are accepted", HEADER
        )
    if n_faces == 0 or n_vertices == 0:
        raise _fail("empty_mesh", f"the mesh is empty ({n_vertices} vertices, {n_faces} faces)", HEADER)
    _check_body_size(header, data[offset:])
    ply = _read_body(data, header, offset, index_name)

    vertex = ply["vertex"].data
    vertices = np.stack([np.asarray(vertex[a], dtype=np.float64) for a in "xyz"], axis=1)
    finite = np.all(np.isfinite(vertices), axis=1)
    if not np.all(finite):
        first = int(np.flatnonzero(~finite)[0])
        raise _fail(
            "non_finite_coordinates",
            f"{np.count_nonzero(~finite)} vertices have NaN or infinite coordinates (first: vertex {first})",
            ("mesh", "vertex", first),
        )
    extent = float(np.abs(vertices).max())
    if extent > limits.max_coordinate_m:
        far = int(np.flatnonzero(np.abs(vertices).max(axis=1) > limits.max_coordinate_m)[0])
        raise _fail(
            "coordinate_limit",
            f"vertex {far} is {extent:.1f} m from the local origin on an axis; coordinates must be "
            f"within {limits.max_coordinate_m:g} m (split the submap or re-centre its local frame)",
            ("mesh", "vertex", far),
        )
    tris, source = _triangulate(np.asarray(ply["face"].data[index_name]), n_vertices)
    if len(tris) > limits.max_faces:
        raise _fail(
            "too_many_faces",
            f"the mesh has {len(tris)} triangles after triangulating polygons; at most {limits.max_faces}",
            ("mesh", "face"),
        )
    labels = _face_labels(ply, tris, source, limits)
    if not np.any(labels != UNLABELED):
        raise _fail(
            "no_labelled_face",
            "every face is unlabeled (label 0); at least one labelled face is needed",
            ("mesh", "face"),
        )
    return SemanticMesh(vertices=vertices, faces=tris, face_labels=labels.astype(np.int64))


# --------------------------------------------------------------------------------------------- writing


def _encode(elements: list[tuple[str, np.ndarray]], encoding: str) -> bytes:
    """Serialise structured arrays as PLY elements; (k,) subarray fields become lists (uchar count).

    The header is plyfile's; binary bodies are numpy-packed rows (plyfile writes lists row by row)."""
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {sorted(ENCODINGS)}, not {encoding!r}")
    byte_order = ENCODINGS[encoding]
    ply = plyfile.PlyData(
        [plyfile.PlyElement.describe(arr, name) for name, arr in elements],
        text=encoding == "ascii",
        byte_order=byte_order,
    )
    stream = io.BytesIO()
    if encoding == "ascii":
        ply.write(stream)
        return stream.getvalue()
    stream.write(ply.header.encode("ascii") + b"\n")
    for _, arr in elements:
        fields: list[tuple[Any, ...]] = []
        values: list[np.ndarray] = []
        for name in arr.dtype.names or ():
            base, shape = arr.dtype[name].base, arr.dtype[name].shape
            if shape:
                fields.append((name + "_count", "u1"))
                values.append(np.full(len(arr), shape[0], dtype=np.uint8))
            fields.append((name, base.newbyteorder(byte_order), shape))
            values.append(arr[name])
        packed = np.empty(len(arr), dtype=np.dtype(fields))
        for (name, *_), value in zip(fields, values, strict=True):
            packed[name] = value
        stream.write(packed.tobytes())
    return stream.getvalue()


def label_palette(num_labels: int = 256) -> np.ndarray:
    """(num_labels, 3) uint8 colour per label id; ids beyond the label table get a neutral grey."""
    palette = np.tile(np.array(UNKNOWN_LABEL_COLOR, dtype=np.uint8), (num_labels, 1))
    for label in LABELS[:num_labels]:
        palette[label.id] = label.color
    return palette


def write_submap_ply(mesh: SemanticMesh, encoding: str = "binary_little_endian") -> bytes:
    """Submap PLY (local frame, metres): vertex x, y, z double; face vertex_indices and label uchar."""
    vertex = np.empty(len(mesh.vertices), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    for k, axis in enumerate("xyz"):
        vertex[axis] = mesh.vertices[:, k]
    face = np.empty(len(mesh.faces), dtype=[("vertex_indices", "i4", (3,)), ("label", "u1")])
    face["vertex_indices"] = mesh.faces
    face["label"] = mesh.face_labels
    return _encode([("vertex", vertex), ("face", face)], encoding)


def write_fused_ply(mesh: FusedMesh) -> bytes:
    """Fused tile PLY (map frame, metres), binary little endian, with the exact properties of API.md."""
    vertex = np.empty(
        len(mesh.vertices),
        dtype=[
            ("x", "f4"),
            ("y", "f4"),
            ("z", "f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
            ("label", "u1"),
            ("confidence", "f4"),
        ],
    )
    for k, axis in enumerate("xyz"):
        vertex[axis] = mesh.vertices[:, k]
    colours = label_palette()[np.asarray(mesh.vertex_labels, dtype=np.uint8)]
    for k, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = colours[:, k]
    vertex["label"] = mesh.vertex_labels
    vertex["confidence"] = mesh.vertex_confidence
    face = np.empty(len(mesh.faces), dtype=[("vertex_indices", "i4", (3,)), ("label", "u1")])
    face["vertex_indices"] = mesh.faces
    face["label"] = mesh.face_labels
    return _encode([("vertex", vertex), ("face", face)], "binary_little_endian")


def read_fused_ply(data: bytes) -> FusedMesh:
    """Read a fused tile PLY (as ``write_fused_ply`` writes it) back; raises MeshValidationError."""
    header, offset = _parse_header(bytes(data))
    index_name = _schema(header)
    for element, names in (("vertex", ("label", "confidence")), ("face", ("label",))):
        for name in names:
            if _property(header[element], (name,)) is None:
                raise _fail(
                    "missing_property", f"{element} property '{name}' is missing from the fused PLY", HEADER
                )
    _check_body_size(header, data[offset:])
    ply = _read_body(data, header, offset, index_name)
    vertex, face = ply["vertex"].data, ply["face"].data
    n_vertices = len(vertex)
    tris, source = _triangulate(np.asarray(face[index_name]), n_vertices)
    return FusedMesh(
        vertices=np.stack([np.asarray(vertex[a], dtype=np.float32) for a in "xyz"], axis=1).reshape(-1, 3),
        faces=tris.astype(np.int32).reshape(-1, 3),
        vertex_labels=np.asarray(vertex["label"]).astype(np.uint8),
        vertex_confidence=np.asarray(vertex["confidence"]).astype(np.float32),
        face_labels=np.asarray(face["label"]).astype(np.uint8)[source],
    )


# glTF is +y up: the node turns the map frame's z-up into y-up (x, y, z) -> (x, z, -y).
MAP_TO_GLTF = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])


def write_glb(mesh: FusedMesh, *, centre: np.ndarray | None = None, features: bool = False) -> bytes:
    """Binary glTF of the fused mesh with vertex colours = label colours.

    The vertex buffer holds map-frame coordinates (metres, as in the PLY) less ``centre`` (a map-frame
    point, default the map origin); the mesh's node carries ``MAP_TO_GLTF`` times the translation by
    ``centre``, so glTF viewers (+y up) show the map upright and in place, and float32 positions stay
    small however far the tile lies from the origin. ``features``: the per-face classes for 3D Tiles
    (``fusion.gltf``): vertices split by label, colours and ``_FEATURE_ID_0`` per face label, and the
    label table in ``EXT_structural_metadata``. An empty mesh gives a valid GLB holding an empty scene."""
    if features:
        mesh = split_by_label(mesh)
    labels = np.asarray(mesh.vertex_labels, dtype=np.uint8)
    offset = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64).reshape(3)
    colours = label_palette()[labels]
    rgba = np.concatenate([colours, np.full((len(colours), 1), 255, dtype=np.uint8)], axis=1)
    geometry = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3) - offset,
        faces=np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3),
        vertex_colors=rgba,
        vertex_attributes={FEATURE_ID_ATTRIBUTE: labels.astype(np.float32)} if features else None,
        process=False,
    )
    if len(geometry.faces) == 0:
        data = geometry.export(file_type="glb")  # trimesh refuses to export an empty Scene
    else:
        placement = np.eye(4)
        placement[:3, 3] = offset
        scene = trimesh.Scene()
        scene.add_geometry(geometry, geom_name="tile", node_name="tile", transform=MAP_TO_GLTF @ placement)
        data = scene.export(file_type="glb")
    if not isinstance(data, bytes):
        raise TypeError(f"trimesh returned {type(data).__name__} for a GLB export")
    if features and len(geometry.faces):
        data = add_label_table(data, feature_count=len(np.unique(labels)))
    return data


def filter_confidence(mesh: FusedMesh, min_confidence: float) -> FusedMesh:
    """Drop faces with any vertex confidence below ``min_confidence``, then unreferenced vertices
    (indices are renumbered; vertex order is kept)."""
    if not np.isfinite(min_confidence):
        raise ValueError("min_confidence must be a finite number")
    confident = np.asarray(mesh.vertex_confidence) >= min_confidence
    keep_faces = np.all(confident[mesh.faces], axis=1) if len(mesh.faces) else np.zeros(0, dtype=bool)
    faces = np.asarray(mesh.faces)[keep_faces]
    used = np.zeros(len(mesh.vertices), dtype=bool)
    used[faces.reshape(-1)] = True
    new_index = np.cumsum(used) - 1
    return FusedMesh(
        vertices=np.asarray(mesh.vertices)[used].astype(np.float32).reshape(-1, 3),
        faces=new_index[faces].astype(np.int32).reshape(-1, 3),
        vertex_labels=np.asarray(mesh.vertex_labels)[used].astype(np.uint8),
        vertex_confidence=np.asarray(mesh.vertex_confidence)[used].astype(np.float32),
        face_labels=np.asarray(mesh.face_labels)[keep_faces].astype(np.uint8),
    )
