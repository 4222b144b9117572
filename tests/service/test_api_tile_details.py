"""/v1/tiles/{i}/{j}/versions, /submaps and /jobs: the viewer's tile panel."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from fusion.types import FusedMesh
from service.store.models import FusionJob, Submap, utcnow
from tests.conftest import publish_version, upload_at

PROBLEM = "application/problem+json"
ROUTES = ("versions", "submaps", "jobs")


def _mesh(faces: int) -> FusedMesh:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    tris = np.array([[0, 1, 2], [1, 3, 2]] * faces, np.int32)[:faces]
    return FusedMesh(
        vertices=vertices,
        faces=tris,
        vertex_labels=np.ones(4, np.uint8),
        vertex_confidence=np.ones(4, np.float32),
        face_labels=np.ones(faces, np.uint8),
    )


def _page(client: TestClient, url: str, headers: dict[str, str], limit: int) -> list[dict[str, Any]]:
    """Every item of a paginated listing, following ``next_cursor``."""
    items: list[dict[str, Any]] = []
    cursor = None
    while True:
        params: dict[str, Any] = {"limit": limit, **({"cursor": cursor} if cursor else {})}
        resp = client.get(url, params=params, headers=headers)
        assert resp.status_code == 200, resp.text
        body = resp.json()
        assert len(body["items"]) <= limit
        items += body["items"]
        cursor = body["next_cursor"]
        if cursor is None:
            return items


def test_versions_newest_first_with_links(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload_at(client, auth["vehicle"], 10, 10, 0)
    assert client.get("/v1/tiles/0/0/versions", headers=auth["reader"]).json() == {
        "items": [],
        "next_cursor": None,
    }
    for version in (1, 2, 3):
        publish_version(client.app, 0, 0, version, _mesh(version), metrics={"faces": version, "vertices": 4})
    h = auth["reader"]
    items = _page(client, "/v1/tiles/0/0/versions", h, limit=2)
    assert [v["version"] for v in items] == [3, 2, 1]
    newest = items[0]
    assert newest["faces"] == 3 and newest["vertices"] == 4 and newest["job_id"] is None
    assert len(newest["mesh_sha256"]) == 64 and len(newest["glb_sha256"]) == 64
    assert newest["fused_at"] is not None
    assert newest["links"]["ply"].endswith("/v1/tiles/0/0/mesh?format=ply&version=3")
    # the links are the immutable downloads of exactly that version
    old = client.get(items[2]["links"]["ply"], headers=h)
    assert old.status_code == 200 and "immutable" in old.headers["cache-control"]
    assert old.headers["x-tile-version"] == "1"
    assert client.get(items[2]["links"]["glb"], headers=h).content[:4] == b"glTF"
    assert client.get("/v1/tiles/0/0/versions", headers=auth["operator"]).status_code == 200


def test_versions_without_recorded_size(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload_at(client, auth["vehicle"], 10, 10, 0)
    publish_version(client.app, 0, 0, 1, _mesh(2), metrics={})
    (item,) = client.get("/v1/tiles/0/0/versions", headers=auth["reader"]).json()["items"]
    assert item["faces"] is None and item["vertices"] is None


def test_submaps_of_a_tile_paginated(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    created = [
        upload_at(client, auth["vehicle"], 10, 10, seq, session)
        for session, seq in [("veh-042/b", 1), ("veh-042/a", 7), ("veh-042/a", 3), ("veh-042/b", 0)]
    ]
    upload_at(client, auth["vehicle"], 74, 10, 9, "veh-042/c")  # tile (1, 0) only
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        row = db.get(Submap, created[1]["id"])
        assert row is not None
        row.pose_refined = {"t": [10.0, 10.0, 0.0], "q": [1.0, 0.0, 0.0, 0.0]}
        db.commit()
    items = _page(client, "/v1/tiles/0/0/submaps", auth["reader"], limit=3)
    assert [(s["session_id"], s["seq"]) for s in items] == [
        ("veh-042/a", 3), ("veh-042/a", 7), ("veh-042/b", 0), ("veh-042/b", 1)
    ]
    assert {s["id"] for s in items} == {c["id"] for c in created}
    assert [s["refined"] for s in items] == [False, True, False, False]
    assert items[0]["agent_id"] == "veh-042" and items[0]["captured_at"].startswith("2026-11-24T08:03:10")
    (other,) = client.get("/v1/tiles/1/0/submaps", headers=auth["reader"]).json()["items"]
    assert other["session_id"] == "veh-042/c"


def _job(db: Any, *, tile: tuple[int, int], age_s: int, kind: str = "reconstruct",
         tiles: list[list[int]] | None = None) -> str:
    job = FusionJob(
        tile_i=tile[0], tile_j=tile[1], kind=kind, tiles=tiles, created_at=utcnow() - timedelta(seconds=age_s)
    )
    db.add(job)
    db.flush()
    return job.id


def test_jobs_touching_a_tile(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    for seq, (x, y) in enumerate([(10, 10), (74, 10), (138, 10), (-54, 10), (10, 74)]):
        upload_at(client, auth["vehicle"], x, y, seq)  # tiles (0, 0), (1, 0), (2, 0), (-1, 0), (0, 1)
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        oldest = _job(db, tile=(0, 0), age_s=50)
        region = _job(db, tile=(1, 0), age_s=40, kind="align", tiles=[[1, 0], [0, 0]])
        _job(db, tile=(1, 0), age_s=30, kind="align", tiles=[[1, 0], [2, 0], [-1, 0]])  # not (0, 0)
        # holds the numbers of (0, 0) and (1, 0), not the pairs (jsonb's @> would say it contains both)
        _job(db, tile=(0, 1), age_s=25, kind="align", tiles=[[0, 1], [1, 1]])
        _job(db, tile=(1, 0), age_s=20)
        newest = _job(db, tile=(0, 0), age_s=10)
        db.commit()
    h = auth["operator"]
    resp = client.get("/v1/tiles/0/0/jobs", headers=h)
    assert resp.status_code == 200, resp.text
    items = resp.json()["items"]
    assert [job["id"] for job in items] == [newest, region, oldest]
    assert items[1]["kind"] == "align" and items[1]["tiles"] == [[1, 0], [0, 0]] and items[1]["tile"] == [1, 0]
    assert items[0]["kind"] == "reconstruct" and items[0]["tiles"] == [[0, 0]]
    limited = client.get("/v1/tiles/0/0/jobs", params={"limit": 2}, headers=h).json()["items"]
    assert [job["id"] for job in limited] == [newest, region]
    assert len(client.get("/v1/tiles/1/0/jobs", headers=h).json()["items"]) == 3
    assert len(client.get("/v1/tiles/-1/0/jobs", headers=h).json()["items"]) == 1
    assert client.get("/v1/tiles/2/0/jobs", headers=h).json()["items"][0]["tiles"] == [[1, 0], [2, 0], [-1, 0]]


def test_jobs_need_an_operator(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload_at(client, auth["vehicle"], 10, 10, 0)
    resp = client.get("/v1/tiles/0/0/jobs", headers=auth["reader"])
    assert resp.status_code == 403 and resp.headers["content-type"].startswith(PROBLEM)
    assert "operator" in resp.json()["detail"]


@pytest.mark.parametrize("route", ROUTES)
def test_roles_404_and_bad_input_are_problems(
    client: TestClient, auth: dict[str, dict[str, str]], route: str
) -> None:
    upload_at(client, auth["vehicle"], 10, 10, 0)
    h = auth["operator"]
    assert client.get(f"/v1/tiles/0/0/{route}").status_code == 401
    assert client.get(f"/v1/tiles/0/0/{route}", headers=auth["vehicle"]).status_code == 403
    missing = client.get(f"/v1/tiles/5/-7/{route}", headers=h)
    assert missing.status_code == 404 and missing.headers["content-type"].startswith(PROBLEM)
    assert missing.json()["code"] == "tile_not_found"
    for params in ({"limit": 0}, {"limit": "many"}, {"limit": 100_000}):
        bad = client.get(f"/v1/tiles/0/0/{route}", params=params, headers=h)
        assert bad.status_code == 422 and bad.json()["errors"][0]["loc"] == ["query", "limit"], (route, params)
    assert client.get(f"/v1/tiles/x/0/{route}", headers=h).status_code == 422


@pytest.mark.parametrize("route", ["versions", "submaps"])
@pytest.mark.parametrize("cursor", ["!!garbage", "WzEsMl0", "WyJhIl0", "eyJhIjogMX0"])
def test_bad_cursors_are_422(
    client: TestClient, auth: dict[str, dict[str, str]], route: str, cursor: str
) -> None:
    # "WzEsMl0" = [1,2] and "WyJhIl0" = ["a"] are cursors of other shapes, "eyJhIjogMX0" = {"a": 1}
    upload_at(client, auth["vehicle"], 10, 10, 0)
    resp = client.get(f"/v1/tiles/0/0/{route}", params={"cursor": cursor}, headers=auth["reader"])
    assert resp.status_code == 422 and resp.headers["content-type"].startswith(PROBLEM)
    body = resp.json()
    assert body["code"] == "invalid_cursor" and body["errors"][0]["loc"] == ["query", "cursor"]
