"""/v1/tiles, /v1/tiles/{i}/{j}, fuse, mesh downloads (ETag/304), /v1/jobs/{id}."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from fusion.meshio import read_fused_ply, write_fused_ply
from fusion.types import FusedMesh
from tests.conftest import publish_version, upload_at

PROBLEM = "application/problem+json"


def _fused_mesh() -> FusedMesh:
    return FusedMesh(
        vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32),
        faces=np.array([[0, 1, 2], [1, 3, 2]], np.int32),
        vertex_labels=np.array([1, 1, 1, 2], np.uint8),
        vertex_confidence=np.array([0.9, 0.9, 0.9, 0.1], np.float32),
        face_labels=np.array([1, 2], np.uint8),
    )


def test_list_tiles_filters_and_pagination(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    for seq, (x, y) in enumerate([(10, 10), (74, 10), (10, 74), (-54, -54), (138, 10)]):
        upload_at(client, auth["vehicle"], x, y, seq)
    resp = client.get("/v1/tiles", headers=auth["reader"])
    assert resp.status_code == 200
    items = resp.json()["items"]
    assert [(t["i"], t["j"]) for t in items] == [(-1, -1), (0, 0), (0, 1), (1, 0), (2, 0)]
    first = items[1]
    assert first["state"] == "dirty" and first["submaps"] == 1 and first["sessions"] == 1
    assert first["version"] == 0 and first["progress"] == 0.0 and first["job_id"] is None
    assert first["links"]["self"].endswith("/v1/tiles/0/0")
    assert first["links"]["mesh"].endswith("/v1/tiles/0/0/mesh")

    seen, cursor = [], None
    while True:
        params: dict[str, Any] = {"limit": 2}
        if cursor:
            params["cursor"] = cursor
        page = client.get("/v1/tiles", params=params, headers=auth["reader"]).json()
        seen += [(t["i"], t["j"]) for t in page["items"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == [(t["i"], t["j"]) for t in items]

    box = client.get("/v1/tiles", params={"bbox": "0,0,100,63"}, headers=auth["reader"]).json()
    assert [(t["i"], t["j"]) for t in box["items"]] == [(0, 0), (1, 0)]
    assert client.get("/v1/tiles", params={"state": "fused"}, headers=auth["reader"]).json()["items"] == []
    assert (
        len(client.get("/v1/tiles", params={"state": "dirty"}, headers=auth["reader"]).json()["items"]) == 5
    )


def test_list_tiles_bad_parameters(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    for params, code in [
        ({"cursor": "!!garbage"}, "invalid_cursor"),
        ({"bbox": "1,2,3"}, "invalid_bbox"),
        ({"bbox": "5,0,1,1"}, "invalid_bbox"),
        ({"bbox": "0,0,nan,1"}, "invalid_bbox"),
        ({"state": "sleeping"}, "invalid_request"),
        ({"limit": 0}, "invalid_request"),
    ]:
        resp = client.get("/v1/tiles", params=params, headers=auth["reader"])
        assert resp.status_code == 422 and resp.headers["content-type"].startswith(PROBLEM), params
        body = resp.json()
        assert body["code"] == code
        (name,) = params
        assert body["errors"] and [e["loc"] for e in body["errors"]] == [["query", name]], body
        assert all(e["msg"] and e["type"] for e in body["errors"])
    assert client.get("/v1/tiles", params={"state": "x"}, headers=auth["reader"]).json()["errors"]


def test_tile_roles_and_404(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload_at(client, auth["vehicle"], 10, 10, 0)
    assert client.get("/v1/tiles/0/0", headers=auth["reader"]).json()["submaps"] == 1
    assert client.get("/v1/tiles/0/0", headers=auth["operator"]).status_code == 200
    assert client.get("/v1/tiles/0/0", headers=auth["vehicle"]).status_code == 403
    assert client.get("/v1/tiles/0/0").status_code == 401
    resp = client.get("/v1/tiles/5/-7", headers=auth["reader"])
    assert resp.status_code == 404 and resp.json()["code"] == "tile_not_found"
    assert client.get("/v1/tiles/a/b", headers=auth["reader"]).status_code == 422


@pytest.mark.parametrize("path", ["/v1/tiles/99999999999999999999/0", "/v1/tiles/0/-2147483649/mesh",
                                  "/v1/tiles/2147483648/0/versions", "/v1/tiles/0/99999999999/submaps"])
def test_a_tile_index_beyond_32_bits_is_a_422_not_a_500(client: TestClient, auth: dict[str, dict[str, str]],
                                                        path: str) -> None:
    resp = client.get(path, headers=auth["operator"])
    assert resp.status_code == 422 and resp.headers["content-type"].startswith("application/problem+json")
    resp = client.post("/v1/tiles/99999999999999999999/0/fuse", headers=auth["operator"])
    assert resp.status_code == 422


def test_fuse_returns_the_active_job(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload_at(client, auth["vehicle"], 10, 10, 0)
    assert client.post("/v1/tiles/0/0/fuse", headers=auth["reader"]).status_code == 403
    assert client.post("/v1/tiles/9/9/fuse", headers=auth["operator"]).status_code == 404
    first = client.post("/v1/tiles/0/0/fuse", headers=auth["operator"])
    assert first.status_code == 202, first.text
    assert first.json()["tile"] == [0, 0]
    job_id = first.json()["job_id"]
    again = client.post("/v1/tiles/0/0/fuse", headers=auth["operator"])
    assert again.status_code == 202 and again.json()["job_id"] == job_id

    tile = client.get("/v1/tiles/0/0", headers=auth["reader"]).json()
    assert tile["state"] == "queued" and tile["job_id"] == job_id
    job = client.get(f"/v1/jobs/{job_id}", headers=auth["operator"])
    assert job.status_code == 200
    body = job.json()
    assert body["id"] == job_id and body["tile"] == [0, 0] and body["state"] == "queued"
    assert body["trigger"] == "operator" and body["progress"] == 0.0 and body["finished_at"] is None
    assert client.get(f"/v1/jobs/{job_id}", headers=auth["reader"]).status_code == 403
    missing = client.get("/v1/jobs/does-not-exist", headers=auth["operator"])
    assert missing.status_code == 404 and missing.headers["content-type"].startswith(PROBLEM)


def test_mesh_404_until_fused(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload_at(client, auth["vehicle"], 10, 10, 0)
    resp = client.get("/v1/tiles/0/0/mesh", headers=auth["reader"])
    assert resp.status_code == 404 and resp.json()["code"] == "mesh_not_found"
    assert client.get("/v1/tiles/3/3/mesh", headers=auth["reader"]).status_code == 404


def test_mesh_download_etag_and_versions(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload_at(client, auth["vehicle"], 10, 10, 0)
    mesh = _fused_mesh()
    publish_version(client.app, 0, 0, 1, mesh)
    h = auth["reader"]

    latest = client.get("/v1/tiles/0/0/mesh", headers=h)
    assert latest.status_code == 200
    assert latest.content == write_fused_ply(mesh)
    etag = latest.headers["etag"]
    assert etag.startswith('"') and "immutable" not in latest.headers["cache-control"]
    assert read_fused_ply(latest.content).faces.shape == (2, 3)

    cached = client.get("/v1/tiles/0/0/mesh", headers={**h, "If-None-Match": etag})
    assert cached.status_code == 304 and cached.content == b"" and cached.headers["etag"] == etag
    assert client.get("/v1/tiles/0/0/mesh", headers={**h, "If-None-Match": '"other"'}).status_code == 200

    pinned = client.get("/v1/tiles/0/0/mesh", params={"version": 1}, headers=h)
    assert pinned.status_code == 200 and "immutable" in pinned.headers["cache-control"]
    assert pinned.headers["etag"] == etag
    assert client.get("/v1/tiles/0/0/mesh", params={"version": 2}, headers=h).status_code == 404

    glb = client.get("/v1/tiles/0/0/mesh", params={"format": "glb"}, headers=h)
    assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    assert glb.headers["content-type"] == "model/gltf-binary" and glb.headers["etag"] != etag

    filtered = client.get("/v1/tiles/0/0/mesh", params={"min_confidence": 0.5}, headers=h)
    assert filtered.status_code == 200 and filtered.headers["etag"] not in (etag, glb.headers["etag"])
    assert read_fused_ply(filtered.content).faces.shape == (1, 3)
    glb_filtered = client.get(
        "/v1/tiles/0/0/mesh", params={"format": "glb", "min_confidence": 0.5}, headers=h
    )
    assert glb_filtered.status_code == 200 and glb_filtered.content[:4] == b"glTF"

    assert client.get("/v1/tiles/0/0/mesh", params={"format": "obj"}, headers=h).status_code == 422
    bad = client.get("/v1/tiles/0/0/mesh", params={"min_confidence": 2}, headers=h)
    assert bad.status_code == 422 and bad.json()["errors"][0]["loc"] == ["query", "min_confidence"]
    assert client.get("/v1/tiles/0/0/mesh", headers=auth["vehicle"]).status_code == 403

    # a second version: the latest moves on, version 1 stays what it was
    mesh2 = _fused_mesh()
    mesh2.vertices = mesh2.vertices + 1
    publish_version(client.app, 0, 0, 2, mesh2)
    newest = client.get("/v1/tiles/0/0/mesh", headers={**h, "If-None-Match": etag})
    assert newest.status_code == 200 and newest.headers["etag"] != etag
    assert client.get("/v1/tiles/0/0/mesh", params={"version": 1}, headers=h).content == write_fused_ply(mesh)
    tile = client.get("/v1/tiles/0/0", headers=h).json()
    assert tile["version"] == 2 and tile["state"] == "fused" and tile["fused_at"] is not None
