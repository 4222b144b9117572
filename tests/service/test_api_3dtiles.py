"""/v1/3dtiles: the tileset validates, puts each tile where FLEETMAP_ORIGIN says, and its glTF content
carries the stored face labels; ETags, auth, bad input, CORS; the Khronos glTF validator on the content.

The y-up convention is checked from the spec, not from the code: 3D Tiles 1.1 rotates glTF content by
+90° about x (y-up → z-up) before the tile transforms, so a served vertex must land, through
node matrix → Y_UP_TO_Z_UP → root transform, at the ECEF point of its stored map-frame position.
"""

from __future__ import annotations

import itertools
import json
import struct
import subprocess
from pathlib import Path
from typing import Any
from urllib.parse import urljoin

import jsonschema
import numpy as np
import pymap3d
import pytest
from fastapi.testclient import TestClient

from fusion.labels import LABELS
from fusion.types import FusedMesh
from tests.conftest import publish_version, upload_at
from tests.js_support import JS_DIR, require_package

PROBLEM = "application/problem+json"
TILESET = "/v1/3dtiles/tileset.json"
ORIGIN = (-33.8688, 151.2093, 30.0)  # southern and eastern hemisphere: sign mistakes show
SIZE = 32.0
Y_UP_TO_Z_UP = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)

# The parts of the 3D Tiles 1.1 tileset schema this service uses (tileset, tile, boundingVolume,
# content; written from the specification), strict about what it emits.
_NUMBERS = {"type": "array", "items": {"type": "number"}}
TILESET_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "required": ["asset", "geometricError", "root"],
    "additionalProperties": False,
    "properties": {
        "asset": {
            "type": "object",
            "required": ["version"],
            "properties": {"version": {"const": "1.1"}, "generator": {"type": "string"}},
            "additionalProperties": False,
        },
        "geometricError": {"type": "number", "minimum": 0},
        "root": {"allOf": [{"$ref": "#/$defs/tile"}, {"required": ["refine", "transform"]}]},
    },
    "$defs": {
        "boundingVolume": {
            "type": "object",
            "minProperties": 1,
            "additionalProperties": False,
            "properties": {
                "box": {**_NUMBERS, "minItems": 12, "maxItems": 12},
                "region": {**_NUMBERS, "minItems": 6, "maxItems": 6},
                "sphere": {**_NUMBERS, "minItems": 4, "maxItems": 4},
            },
        },
        "tile": {
            "type": "object",
            "required": ["boundingVolume", "geometricError"],
            "additionalProperties": False,
            "properties": {
                "boundingVolume": {"$ref": "#/$defs/boundingVolume"},
                "geometricError": {"type": "number", "minimum": 0},
                "refine": {"enum": ["ADD", "REPLACE"]},
                "transform": {**_NUMBERS, "minItems": 16, "maxItems": 16},
                "content": {
                    "type": "object",
                    "required": ["uri"],
                    "additionalProperties": False,
                    "properties": {"uri": {"type": "string", "minLength": 1}},
                },
                "children": {"type": "array", "minItems": 1, "items": {"$ref": "#/$defs/tile"}},
                "extras": {"type": "object"},
            },
        },
    },
}


@pytest.fixture
def client(make_client: Any) -> TestClient:
    return make_client(origin=",".join(map(str, ORIGIN)), tile_size=SIZE)


def _tile_mesh(i: int, j: int, *, lift: float = 0.0, n: int = 4) -> FusedMesh:
    """A wavy grid inside tile (i, j) (map frame), faces labelled 1, 2, 5, 9 in turn."""
    xs = np.linspace(i * SIZE + 2, (i + 1) * SIZE - 2, n + 1)
    ys = np.linspace(j * SIZE + 3, (j + 1) * SIZE - 1, n + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    gz = 1.5 + lift + 0.8 * np.sin(gx / 5) * np.cos(gy / 7)
    vertices = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1).astype(np.float32)
    faces = []
    for a in range(n):
        for b in range(n):
            k = a * (n + 1) + b
            faces += [[k, k + n + 1, k + 1], [k + 1, k + n + 1, k + n + 2]]
    face_labels = np.array([(1, 2, 5, 9)[f % 4] for f in range(len(faces))], np.uint8)
    return FusedMesh(
        vertices=vertices,
        faces=np.array(faces, np.int32),
        vertex_labels=np.full(len(vertices), 4, np.uint8),
        vertex_confidence=np.ones(len(vertices), np.float32),
        face_labels=face_labels,
    )


_SEQ = itertools.count()


def _fuse(client: TestClient, auth: dict[str, dict[str, str]], i: int, j: int, version: int, mesh: FusedMesh) -> None:
    if version == 1:
        upload_at(client, auth["vehicle"], (i + 0.5) * SIZE, (j + 0.5) * SIZE, seq=next(_SEQ))
    publish_version(client.app, i, j, version, mesh)


# ----------------------------------------------------------------------------------------- glTF reading


def _glb(data: bytes) -> tuple[dict[str, Any], bytes]:
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_length, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON"
    bin_length, bin_type = struct.unpack_from("<I4s", data, 20 + json_length)
    assert bin_type == b"BIN\0"
    start = 28 + json_length
    return json.loads(data[20 : 20 + json_length]), data[start : start + bin_length]


_COMPONENTS = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _accessor(document: dict[str, Any], binary: bytes, index: int) -> np.ndarray:
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    assert "byteStride" not in view
    width = _WIDTH[accessor["type"]]
    values = np.frombuffer(
        binary,
        dtype=np.dtype(_COMPONENTS[accessor["componentType"]]).newbyteorder("<"),
        count=accessor["count"] * width,
        offset=view.get("byteOffset", 0) + accessor.get("byteOffset", 0),
    )
    return values.reshape(-1, width) if width > 1 else values


def _view(document: dict[str, Any], binary: bytes, index: int) -> bytes:
    view = document["bufferViews"][index]
    return binary[view["byteOffset"] : view["byteOffset"] + view["byteLength"]]


def _label_table(document: dict[str, Any], binary: bytes) -> list[dict[str, Any]]:
    """The EXT_structural_metadata property table decoded (binary table format of 3D Metadata)."""
    metadata = document["extensions"]["EXT_structural_metadata"]
    (table,) = metadata["propertyTables"]
    cls = metadata["schema"]["classes"][table["class"]]["properties"]
    assert cls["id"] == {"type": "SCALAR", "componentType": "UINT8", "required": True}
    assert cls["name"]["type"] == "STRING" and cls["color"]["type"] == "VEC3"
    props, count = table["properties"], table["count"]
    ids = np.frombuffer(_view(document, binary, props["id"]["values"]), np.uint8)[:count]
    assert props["name"].get("stringOffsetType", "UINT32") == "UINT32"
    offsets = np.frombuffer(_view(document, binary, props["name"]["stringOffsets"]), "<u4")[: count + 1]
    names = _view(document, binary, props["name"]["values"])
    colours = np.frombuffer(_view(document, binary, props["color"]["values"]), np.uint8)[: 3 * count]
    for index in props.values():  # each buffer view aligned to its component size (8 bytes here)
        for key in ("values", "stringOffsets"):
            if key in index:
                assert document["bufferViews"][index[key]]["byteOffset"] % 8 == 0
    return [
        {"id": int(ids[k]), "name": names[offsets[k] : offsets[k + 1]].decode(), "color": colours[3 * k : 3 * k + 3].tolist()}
        for k in range(count)
    ]


def _world(document: dict[str, Any], positions: np.ndarray, root_transform: list[float]) -> np.ndarray:
    """ECEF of glTF positions: node matrix, then 3D Tiles' y-up → z-up, then the root transform."""
    (node,) = document["nodes"]
    matrix = np.array(node.get("matrix", np.eye(4).ravel()), dtype=np.float64).reshape(4, 4).T
    root = np.array(root_transform, dtype=np.float64).reshape(4, 4).T  # column-major
    homogeneous = np.c_[positions.astype(np.float64), np.ones(len(positions))]
    return (root @ Y_UP_TO_Z_UP @ matrix @ homogeneous.T).T[:, :3]


# ----------------------------------------------------------------------------------------- tileset


def _check_tileset(tileset: dict[str, Any]) -> None:
    """Schema plus what the schema cannot say: sane regions and boxes, errors shrinking downwards."""
    jsonschema.validate(tileset, TILESET_SCHEMA)
    root = tileset["root"]
    assert tileset["geometricError"] >= root["geometricError"]
    transform = np.array(root["transform"]).reshape(4, 4).T
    np.testing.assert_allclose(transform[3], [0, 0, 0, 1])
    np.testing.assert_allclose(transform[:3, :3].T @ transform[:3, :3], np.eye(3), atol=1e-12)  # rigid
    for tile in [root, *root.get("children", [])]:
        west, south, east, north, low, high = tile["boundingVolume"]["region"]
        assert -np.pi <= west <= np.pi and -np.pi <= east <= np.pi and west <= east
        assert -np.pi / 2 <= south <= north <= np.pi / 2 and low <= high
        box = np.array(tile["boundingVolume"]["box"])
        assert np.all(np.diag(box[3:].reshape(3, 3)) > 0)
        for child in tile.get("children", []):
            assert child["geometricError"] <= tile["geometricError"]


def _geodetic(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lat, lon, alt = pymap3d.enu2geodetic(points[:, 0], points[:, 1], points[:, 2], *ORIGIN)
    return np.radians(lat), np.radians(lon), np.asarray(alt)


def test_empty_map_is_a_valid_tileset_at_the_origin(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    resp = client.get(TILESET, headers=auth["reader"])
    assert resp.status_code == 200 and resp.headers["content-type"] == "application/json"
    tileset = resp.json()
    _check_tileset(tileset)
    assert "children" not in tileset["root"] and "content" not in tileset["root"]
    ecef = np.array(tileset["root"]["transform"]).reshape(4, 4).T[:3, 3]
    np.testing.assert_allclose(pymap3d.ecef2geodetic(*ecef), ORIGIN, atol=1e-6)


def test_tileset_places_every_fused_tile_where_the_origin_says(
    client: TestClient, auth: dict[str, dict[str, str]]
) -> None:
    meshes = {(0, 0): _tile_mesh(0, 0), (-3, 2): _tile_mesh(-3, 2, lift=-4.0), (700, -450): _tile_mesh(700, -450)}
    for (i, j), mesh in meshes.items():
        _fuse(client, auth, i, j, 1, mesh)
    upload_at(client, auth["vehicle"], 5 * SIZE + 1, 1, seq=next(_SEQ))  # a tile never fused: not in the tileset
    tileset = client.get(TILESET, headers=auth["reader"]).json()
    _check_tileset(tileset)
    root = tileset["root"]
    assert root["refine"] == "REPLACE" and tileset["asset"]["version"] == "1.1"
    children = {tuple(c["extras"]["tile"]): c for c in root["children"]}
    assert set(children) == set(meshes)
    transform = np.array(root["transform"]).reshape(4, 4).T
    for (i, j), mesh in meshes.items():
        child = children[(i, j)]
        assert child["content"]["uri"] == f"tiles/{i}/{j}/1.glb" and child["geometricError"] == 0
        # the root transform takes the tile's centre to the ECEF point of its geodetic position
        centre = np.array([(i + 0.5) * SIZE, (j + 0.5) * SIZE, 2.0])
        ecef = transform @ np.r_[centre, 1.0]
        np.testing.assert_allclose(
            pymap3d.ecef2geodetic(*ecef[:3]), pymap3d.enu2geodetic(*centre, *ORIGIN), rtol=0, atol=1e-9
        )
        # the region (radians, metres) and the box (map frame) hold the mesh, and not much more
        lat, lon, alt = _geodetic(mesh.vertices.astype(np.float64))
        west, south, east, north, low, high = child["boundingVolume"]["region"]
        assert np.all((west <= lon) & (lon <= east) & (south <= lat) & (lat <= north) & (low <= alt) & (alt <= high))
        assert max(lon.min() - west, east - lon.max(), lat.min() - south, north - lat.max()) < 1e-6
        assert max(alt.min() - low, high - alt.max()) < 0.5  # the box's corners: the Earth curves away
        box = np.array(child["boundingVolume"]["box"])
        half = np.diag(box[3:].reshape(3, 3))
        assert np.all(np.abs(mesh.vertices - box[:3]) <= half)
        assert np.all(half - (mesh.vertices.max(0) - mesh.vertices.min(0)) / 2 < 0.1)
        # the root's volumes hold each child's
        r_west, r_south, r_east, r_north, r_low, r_high = root["boundingVolume"]["region"]
        assert r_west <= west and east <= r_east and r_south <= south and north <= r_north
        assert r_low <= low and high <= r_high
        r_box = np.array(root["boundingVolume"]["box"])
        assert np.all(np.abs(box[:3] - r_box[:3]) + half <= np.diag(r_box[3:].reshape(3, 3)) + 1e-9)
    assert root["geometricError"] >= np.linalg.norm([703 * SIZE, 452 * SIZE])


def test_content_carries_the_stored_face_labels_in_place(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    meshes = {(2, -1): _tile_mesh(2, -1), (700, -450): _tile_mesh(700, -450, lift=3.0)}
    for (i, j), mesh in meshes.items():
        _fuse(client, auth, i, j, 1, mesh)
    tileset = client.get(TILESET, headers=auth["reader"]).json()
    labels = client.get("/v1/labels", headers=auth["reader"]).json()
    for child in tileset["root"]["children"]:
        i, j = child["extras"]["tile"]
        mesh = meshes[(i, j)]
        resp = client.get(urljoin(f"http://testserver{TILESET}", child["content"]["uri"]), headers=auth["reader"])
        assert resp.status_code == 200 and resp.headers["content-type"] == "model/gltf-binary"
        document, binary = _glb(resp.content)
        assert set(document["extensionsUsed"]) >= {"EXT_mesh_features", "EXT_structural_metadata"}
        (primitive,) = document["meshes"][0]["primitives"]
        attributes = primitive["attributes"]
        (feature_ids,) = primitive["extensions"]["EXT_mesh_features"]["featureIds"]
        assert feature_ids["attribute"] == 0 and feature_ids["propertyTable"] == 0
        assert feature_ids["featureCount"] == len(np.unique(mesh.face_labels))
        faces = _accessor(document, binary, primitive["indices"]).reshape(-1, 3)
        ids = _accessor(document, binary, attributes["_FEATURE_ID_0"])
        assert document["accessors"][attributes["_FEATURE_ID_0"]]["type"] == "SCALAR"
        # every corner of every face carries that face's stored label: no vertex shared across labels
        np.testing.assert_array_equal(ids[faces], np.repeat(mesh.face_labels[:, None], 3, axis=1))
        # the feature ids index the label table: the names and colours of GET /v1/labels
        assert _label_table(document, binary) == labels
        colours = _accessor(document, binary, attributes["COLOR_0"])[:, :3]
        np.testing.assert_array_equal(colours[faces[:, 0]], [LABELS[k].color for k in mesh.face_labels])
        # positions are tile-local (float32 keeps sub-millimetre precision 20 km out) ...
        positions = _accessor(document, binary, attributes["POSITION"])
        assert np.abs(positions).max() < SIZE
        # ... and every triangle lands, y-up → z-up and root transform applied, on its stored corners
        ecef = _world(document, positions, tileset["root"]["transform"])[faces]
        expected = np.stack(pymap3d.enu2ecef(*mesh.vertices[mesh.faces].astype(np.float64).T, *ORIGIN), -1)
        np.testing.assert_allclose(ecef, np.transpose(expected, (1, 0, 2)).reshape(ecef.shape), atol=1e-3)


def test_etags_new_versions_and_immutable_content(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    reader = auth["reader"]
    _fuse(client, auth, 1, 1, 1, _tile_mesh(1, 1))
    first = client.get(TILESET, headers=reader)
    etag = first.headers["etag"]
    assert first.headers["cache-control"] == "no-cache"
    again = client.get(TILESET, headers={**reader, "If-None-Match": etag})
    assert again.status_code == 304 and again.headers["etag"] == etag and again.content == b""

    _fuse(client, auth, 1, 1, 2, _tile_mesh(1, 1, lift=10.0))
    changed = client.get(TILESET, headers={**reader, "If-None-Match": etag})
    assert changed.status_code == 200 and changed.headers["etag"] != etag
    (child,) = changed.json()["root"]["children"]
    assert child["content"]["uri"] == "tiles/1/1/2.glb"
    assert child["boundingVolume"]["region"][4] > first.json()["root"]["children"][0]["boundingVolume"]["region"][5]

    for version in (1, 2):  # the old version stays available, each cached forever
        content = client.get(f"/v1/3dtiles/tiles/1/1/{version}.glb", headers=reader)
        assert content.status_code == 200 and content.headers["x-tile-version"] == str(version)
        assert content.headers["cache-control"] == "public, max-age=31536000, immutable"
        cached = client.get(f"/v1/3dtiles/tiles/1/1/{version}.glb", headers={**reader, "If-None-Match": content.headers["etag"]})
        assert cached.status_code == 304
    v1 = client.get("/v1/3dtiles/tiles/1/1/1.glb", headers=reader)
    assert v1.headers["etag"] != content.headers["etag"]


def test_auth_and_bad_input_are_problems_never_500(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    _fuse(client, auth, 0, 0, 1, _tile_mesh(0, 0))
    upload_at(client, auth["vehicle"], 3 * SIZE + 1, 1, seq=next(_SEQ))
    assert client.get(TILESET, headers=auth["operator"]).status_code == 200
    for path in (TILESET, "/v1/3dtiles/tiles/0/0/1.glb"):
        assert client.get(path).status_code == 401
        assert client.get(path, headers={"Authorization": "Bearer nope"}).status_code == 401
        assert client.get(path, headers=auth["vehicle"]).status_code == 403
    for path, status, code in [
        ("/v1/3dtiles/tiles/9/9/1.glb", 404, "mesh_not_found"),  # no such tile
        ("/v1/3dtiles/tiles/3/0/1.glb", 404, "mesh_not_found"),  # a tile never fused
        ("/v1/3dtiles/tiles/0/0/2.glb", 404, "version_not_found"),
        ("/v1/3dtiles/tiles/0/0/0.glb", 422, "invalid_request"),
        ("/v1/3dtiles/tiles/0/0/-1.glb", 422, "invalid_request"),
        ("/v1/3dtiles/tiles/0/0/latest.glb", 422, "invalid_request"),
        ("/v1/3dtiles/tiles/a/0/1.glb", 422, "invalid_request"),
        ("/v1/3dtiles/tiles/0/0/99999999999999999999999.glb", 422, "invalid_request"),
        ("/v1/3dtiles/tiles/99999999999999999999/0/1.glb", 422, "invalid_request"),
        ("/v1/3dtiles/tiles/0/0/2147483647.glb", 404, "version_not_found"),
    ]:
        resp = client.get(path, headers=auth["reader"])
        assert resp.status_code == status, (path, resp.text)
        assert resp.headers["content-type"].startswith(PROBLEM) and resp.json()["code"] == code, path
    assert client.get("/v1/3dtiles/tiles/0/0/1", headers=auth["reader"]).status_code == 404


def test_cors_lets_a_viewer_on_another_origin_load_the_tiles(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    viewer = {"Origin": "http://viewer.example:8080"}
    preflight = client.options(
        TILESET,
        headers={**viewer, "Access-Control-Request-Method": "GET", "Access-Control-Request-Headers": "authorization"},
    )
    assert preflight.status_code == 200
    assert preflight.headers["access-control-allow-origin"] == "*"
    assert "authorization" in preflight.headers["access-control-allow-headers"].lower()
    resp = client.get(TILESET, headers={**auth["reader"], **viewer})
    assert resp.headers["access-control-allow-origin"] == "*" and "etag" in resp.headers["access-control-expose-headers"].lower()
    denied = client.get(TILESET, headers=viewer)  # a problem the page's script can read
    assert denied.status_code == 401 and denied.headers["access-control-allow-origin"] == "*"
    # only the 3D Tiles: the rest of the API stays same-origin
    assert "access-control-allow-origin" not in client.get("/v1/tiles", headers={**auth["reader"], **viewer}).headers


def test_openapi_documents_the_3dtiles_routes(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    tileset = paths["/v1/3dtiles/tileset.json"]["get"]
    content = paths["/v1/3dtiles/tiles/{i}/{j}/{version}.glb"]["get"]
    assert tileset["operationId"] == "get3dTileset" and content["operationId"] == "get3dTileContent"
    assert {"200", "304", "401", "403", "503"} <= set(tileset["responses"])
    assert {"200", "304", "401", "403", "404", "422", "503"} <= set(content["responses"])
    assert "model/gltf-binary" in content["responses"]["200"]["content"]
    assert PROBLEM in content["responses"]["404"]["content"]


def test_khronos_gltf_validator_accepts_the_content(
    client: TestClient, auth: dict[str, dict[str, str]], tmp_path: Path
) -> None:
    require_package("gltf-validator")
    files = []
    for i, j in [(0, 0), (-1, 700)]:
        _fuse(client, auth, i, j, 1, _tile_mesh(i, j))
        path = tmp_path / f"tile_{i}_{j}.glb"
        path.write_bytes(client.get(f"/v1/3dtiles/tiles/{i}/{j}/1.glb", headers=auth["reader"]).content)
        files.append(str(path))
    run = subprocess.run(
        ["node", str(JS_DIR / "validate_gltf.mjs"), *files], capture_output=True, text=True, timeout=120, check=False
    )
    reports = [json.loads(line) for line in run.stdout.splitlines()]
    assert run.returncode == 0 and len(reports) == len(files), run.stdout + run.stderr
    for report in reports:
        assert report["numErrors"] == 0 and report["numWarnings"] == 0, report
        # the validator knows neither extension (it says so as an info), hence the checks above
        unsupported = {m["message"].split("'")[1] for m in report["messages"] if m["code"] == "UNSUPPORTED_EXTENSION"}
        assert unsupported <= {"EXT_mesh_features", "EXT_structural_metadata"}
