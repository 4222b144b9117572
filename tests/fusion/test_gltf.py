"""fusion.gltf and write_glb(features=, centre=): per-face classes survive as glTF feature ids."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import trimesh

from fusion.gltf import FEATURE_ID_ATTRIBUTE, glb_chunks, pack_glb, split_by_label
from fusion.labels import LABELS
from fusion.meshio import MAP_TO_GLTF, write_glb
from fusion.types import FusedMesh


def _strip() -> FusedMesh:
    """Four triangles over five vertices; neighbouring faces differ in label and share vertices."""
    vertices = np.array([[0, 0, 0], [1, 0, 0.5], [0, 1, 0], [1, 1, 0.2], [2, 0, 1]], np.float32)
    faces = np.array([[0, 1, 2], [1, 3, 2], [1, 4, 3], [0, 1, 2]], np.int32)
    return FusedMesh(
        vertices=vertices,
        faces=faces,
        vertex_labels=np.array([1, 1, 1, 2, 5], np.uint8),
        vertex_confidence=np.linspace(0.5, 1, 5, dtype=np.float32),
        face_labels=np.array([1, 2, 5, 9], np.uint8),
    )


def test_split_by_label_keeps_triangles_and_never_shares_a_vertex_across_labels() -> None:
    mesh = _strip()
    split = split_by_label(mesh)
    np.testing.assert_array_equal(split.vertices[split.faces], mesh.vertices[mesh.faces])
    np.testing.assert_array_equal(split.face_labels, mesh.face_labels)
    # every corner of a face carries the face's label
    np.testing.assert_array_equal(split.vertex_labels[split.faces], np.repeat(mesh.face_labels[:, None], 3, 1))
    # faces 0 and 3 are the same triangle with different labels: no vertex in common
    assert not set(split.faces[0]) & set(split.faces[3])
    # faces of one label still share their vertices (no needless duplication)
    assert len(split.vertices) == len(np.unique(mesh.faces.astype(np.int64) * 256 + mesh.face_labels[:, None]))


def test_write_glb_with_features_has_feature_ids_and_the_label_table() -> None:
    data = write_glb(_strip(), features=True)
    document, binary = glb_chunks(data)
    primitive = document["meshes"][0]["primitives"][0]
    features = primitive["extensions"]["EXT_mesh_features"]["featureIds"]
    assert features == [{"featureCount": 4, "attribute": 0, "propertyTable": 0}]
    assert {"EXT_mesh_features", "EXT_structural_metadata"} <= set(document["extensionsUsed"])
    table = document["extensions"]["EXT_structural_metadata"]["propertyTables"][0]
    assert table["count"] == len(LABELS) and table["class"] == "label"
    for view in document["bufferViews"]:
        assert view["byteOffset"] % 4 == 0 and view["byteOffset"] + view["byteLength"] <= len(binary)
    # trimesh (an independent reader) sees the same triangles and the ids as a vertex attribute
    loaded = trimesh.load(io.BytesIO(data), file_type="glb", process=False)
    (geometry,) = loaded.geometry.values()
    ids = np.asarray(geometry.vertex_attributes[FEATURE_ID_ATTRIBUTE]).reshape(-1)
    np.testing.assert_array_equal(ids[geometry.faces], np.repeat([[1], [2], [5], [9]], 3, 1))


def test_write_glb_centre_moves_positions_into_the_node() -> None:
    mesh = _strip()
    far = dataclasses.replace(mesh, vertices=mesh.vertices + np.float32([25_000, -18_000, 3]))
    centre = np.array([25_032.0, -17_968.0, 0.0])
    document, _ = glb_chunks(write_glb(far, centre=centre))
    position = document["accessors"][document["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert max(map(abs, position["max"] + position["min"])) < 40  # tile-local, not 25 km
    node = np.array(document["nodes"][0]["matrix"]).reshape(4, 4).T
    placement = np.eye(4)
    placement[:3, 3] = centre
    np.testing.assert_allclose(node, MAP_TO_GLTF @ placement)
    # without a centre nothing changes: the stored meshes' GLB stays as it was
    plain, _ = glb_chunks(write_glb(mesh))
    np.testing.assert_allclose(np.array(plain["nodes"][0]["matrix"]).reshape(4, 4).T, MAP_TO_GLTF)
    assert "extensionsUsed" not in plain


def test_glb_chunks_round_trip_and_empty_mesh() -> None:
    document, binary = glb_chunks(write_glb(_strip(), features=True))
    again = pack_glb(document, binary)
    assert glb_chunks(again) == (document, binary)
    empty, empty_bin = glb_chunks(write_glb(FusedMesh.empty(), features=True))
    assert empty_bin == b"" and "extensionsUsed" not in empty
