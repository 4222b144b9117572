"""Semantic classes in glTF (torch-free): ``EXT_mesh_features`` feature ids and an
``EXT_structural_metadata`` label table, as 3D Tiles 1.1 viewers (CesiumJS, deck.gl) read them.

A fused mesh labels its faces; glTF feature ids live on vertices. ``split_by_label`` duplicates every
vertex shared by faces of different labels, so the three vertices of a face carry its label and no
interpolation mixes classes. ``add_label_table`` then turns a GLB whose first primitive has the
``_FEATURE_ID_0`` attribute (the label id per vertex) into one whose feature ids index a property table
of the label set: one row per label id with its ``id``, ``name`` and ``color``.

``fusion.meshio.write_glb(mesh, features=True)`` is the one caller: trimesh writes the geometry, this
module adds the extensions (trimesh's glTF exporter has no hook for binary metadata of its own).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np

from fusion.labels import LABELS, Label
from fusion.types import FusedMesh

FEATURE_ID_ATTRIBUTE = "_FEATURE_ID_0"
LABEL_CLASS = "label"
MESH_FEATURES = "EXT_mesh_features"
STRUCTURAL_METADATA = "EXT_structural_metadata"

_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
_ALIGN = 8  # property table buffer views: 8 bytes suits every component type


def split_by_label(mesh: FusedMesh) -> FusedMesh:
    """The same triangles (same order, same map-frame positions) over vertices that are never shared
    by faces of different labels; each vertex's label is its faces' label. Unreferenced vertices go."""
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    labels = np.asarray(mesh.face_labels, dtype=np.int64).reshape(-1)
    keys = faces * 256 + labels[:, None]  # labels are uchar: (vertex, label) in one integer
    unique, inverse = np.unique(keys.reshape(-1), return_inverse=True)
    source = unique // 256
    return FusedMesh(
        vertices=np.asarray(mesh.vertices, dtype=np.float32).reshape(-1, 3)[source],
        faces=inverse.reshape(-1, 3).astype(np.int32),
        vertex_labels=(unique % 256).astype(np.uint8),
        vertex_confidence=np.asarray(mesh.vertex_confidence, dtype=np.float32)[source],
        face_labels=labels.astype(np.uint8),
    )


def glb_chunks(data: bytes) -> tuple[dict[str, Any], bytes]:
    """The JSON document and the BIN chunk (``b""`` when absent) of a GLB 2.0 file."""
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC or version != 2 or length != len(data):
        raise ValueError("not a GLB 2.0 file")
    json_length, json_type = struct.unpack_from("<II", data, 12)
    if json_type != _JSON_CHUNK:
        raise ValueError("the GLB's first chunk is not JSON")
    document = json.loads(data[20 : 20 + json_length])
    offset, binary = 20 + json_length, b""
    if offset + 8 <= len(data):
        bin_length, bin_type = struct.unpack_from("<II", data, offset)
        if bin_type == _BIN_CHUNK:
            binary = data[offset + 8 : offset + 8 + bin_length]
    return document, binary


def pack_glb(document: dict[str, Any], binary: bytes) -> bytes:
    """A GLB 2.0 file of a JSON document and a BIN chunk (omitted when empty), padded as the spec says."""
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), _JSON_CHUNK) + text
    if binary:
        binary += b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(binary), _BIN_CHUNK) + binary
    return struct.pack("<III", _GLB_MAGIC, 2, 12 + len(chunks)) + chunks


def label_schema() -> dict[str, Any]:
    """The ``EXT_structural_metadata`` schema: one class, ``label``, with id, name and colour."""
    return {
        "id": "fleetmap_labels",
        "classes": {
            LABEL_CLASS: {
                "name": "Semantic label",
                "description": "The class of a face of the fused map (GET /v1/labels)",
                "properties": {
                    "id": {"type": "SCALAR", "componentType": "UINT8", "required": True},
                    "name": {"type": "STRING", "required": True},
                    "color": {
                        "type": "VEC3",
                        "componentType": "UINT8",
                        "required": True,
                        "description": "sRGB colour, 0-255 per channel",
                    },
                },
            }
        },
    }


def _label_columns(labels: Sequence[Label]) -> dict[str, bytes]:
    """The property table's columns (binary table format of the 3D Metadata spec), row k = label id k."""
    if [label.id for label in labels] != list(range(len(labels))):
        raise ValueError("label ids must be 0..n-1 in order: they are the property table's rows")
    names = [label.name.encode() for label in labels]
    offsets = np.concatenate([[0], np.cumsum([len(n) for n in names])]).astype("<u4")
    return {
        "id": np.arange(len(labels), dtype=np.uint8).tobytes(),
        "name": b"".join(names),
        "name_offsets": offsets.tobytes(),
        "color": np.array([label.color for label in labels], dtype=np.uint8).tobytes(),
    }


def add_label_table(glb: bytes, feature_count: int, labels: Sequence[Label] = LABELS) -> bytes:
    """``glb`` with its first primitive's ``_FEATURE_ID_0`` (label ids; ``feature_count`` distinct ones)
    declared as ``EXT_mesh_features`` feature ids into an ``EXT_structural_metadata`` property table of
    ``labels``.

    The table's buffer views are appended to the BIN chunk, each 8-byte aligned. A GLB without that
    attribute (an empty mesh) is returned unchanged."""
    document, binary = glb_chunks(glb)
    primitives = [p for mesh in document.get("meshes", []) for p in mesh.get("primitives", [])]
    if not primitives or FEATURE_ID_ATTRIBUTE not in primitives[0].get("attributes", {}):
        return glb
    primitive = primitives[0]
    accessor = document["accessors"][primitive["attributes"][FEATURE_ID_ATTRIBUTE]]
    if accessor["type"] != "SCALAR" or accessor.get("normalized", False):
        raise ValueError(f"{FEATURE_ID_ATTRIBUTE} must be a SCALAR, not normalised")

    views = document.setdefault("bufferViews", [])
    blob = bytearray(binary)
    view_of: dict[str, int] = {}
    for name, column in _label_columns(labels).items():
        blob += b"\0" * (-len(blob) % _ALIGN)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(column)})
        view_of[name] = len(views) - 1
        blob += column
    document["buffers"] = [{"byteLength": len(blob)}]

    document.setdefault("extensions", {})[STRUCTURAL_METADATA] = {
        "schema": label_schema(),
        "propertyTables": [
            {
                "name": "labels",
                "class": LABEL_CLASS,
                "count": len(labels),
                "properties": {
                    "id": {"values": view_of["id"]},
                    "name": {
                        "values": view_of["name"],
                        "stringOffsets": view_of["name_offsets"],
                        "stringOffsetType": "UINT32",
                    },
                    "color": {"values": view_of["color"]},
                },
            }
        ],
    }
    primitive.setdefault("extensions", {})[MESH_FEATURES] = {
        "featureIds": [{"featureCount": max(feature_count, 1), "attribute": 0, "propertyTable": 0}]
    }
    used = document.setdefault("extensionsUsed", [])
    used += [name for name in (MESH_FEATURES, STRUCTURAL_METADATA) if name not in used]
    return pack_glb(document, bytes(blob))

