"""GET /v1/sessions (trajectories by box, paginated) and /v1/sessions/{session_id}/poses with
URL-encoded slashes in the session id."""

from __future__ import annotations

from typing import Any
from urllib.parse import quote

from fastapi.testclient import TestClient
from sqlalchemy import select

from service.store.models import Submap
from tests.conftest import SESSION, make_meta, make_ply, upload, upload_at


def test_session_poses_ordered_by_seq(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    ids = {}
    for seq in (5, 2, 9):
        meta = make_meta(seq=seq, gps={"pose": {"t": [float(seq), 0.0, 0.0], "q": [1, 0, 0, 0]}})
        ids[seq] = upload(client, auth["vehicle"], meta, make_ply()).json()["id"]
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        row = db.get(Submap, ids[9])
        assert row is not None
        row.pose_refined = {"t": [9.5, 0.1, 0.0], "q": [1.0, 0.0, 0.0, 0.0]}
        db.commit()

    encoded = quote(SESSION, safe="")
    assert "%2F" in encoded
    resp = client.get(f"/v1/sessions/{encoded}/poses", headers=auth["reader"])
    assert resp.status_code == 200, resp.text
    poses = resp.json()
    assert [p["seq"] for p in poses] == [2, 5, 9]
    assert [p["id"] for p in poses] == [ids[2], ids[5], ids[9]]
    assert poses[0]["pose_gps"] == {"t": [2.0, 0.0, 0.0], "q": [1.0, 0.0, 0.0, 0.0]}
    assert poses[0]["pose_refined"] is None
    assert poses[2]["pose_refined"]["t"] == [9.5, 0.1, 0.0]

    submap = client.get(f"/v1/submaps/{ids[9]}", headers=auth["reader"]).json()
    assert submap["pose_refined"]["t"] == [9.5, 0.1, 0.0]


def test_session_poses_404_and_roles(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload(client, auth["vehicle"], make_meta(), make_ply())
    encoded = quote(SESSION, safe="")
    missing = client.get(f"/v1/sessions/{quote('veh-1/none', safe='')}/poses", headers=auth["reader"])
    assert missing.status_code == 404 and missing.json()["code"] == "session_not_found"
    assert client.get(f"/v1/sessions/{encoded}/poses", headers=auth["vehicle"]).status_code == 403
    assert client.get(f"/v1/sessions/{encoded}/poses").status_code == 401
    assert client.get(f"/v1/sessions/{encoded}/poses", headers=auth["operator"]).status_code == 200


def _tracks(client: TestClient, headers: dict[str, str], **params: Any) -> list[dict[str, Any]]:
    resp = client.get("/v1/sessions", params=params, headers=headers)
    assert resp.status_code == 200, resp.text
    return resp.json()["items"]  # type: ignore[no-any-return]


def test_sessions_with_trajectories_by_box(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    # session a drives from tile (0, 0) into (1, 0); b stays in (1, 0); c is far away in (5, 5)
    for session, seq, x, y in [
        ("veh-042/a", 2, 70.0, 10.0), ("veh-042/a", 0, 10.0, 10.0), ("veh-042/a", 1, 40.0, 12.0),
        ("veh-042/b", 0, 100.0, 20.0), ("veh-042/c", 0, 330.0, 330.0),
    ]:
        upload_at(client, auth["vehicle"], x, y, seq, session)
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        row = db.scalars(select(Submap).where(Submap.session_id == "veh-042/a", Submap.seq == 1)).one()
        row.pose_refined = {"t": [40.5, 11.5, 0.2], "q": [1.0, 0.0, 0.0, 0.0]}
        db.commit()
    h = auth["reader"]

    everything = _tracks(client, h)
    assert [s["session_id"] for s in everything] == ["veh-042/a", "veh-042/b", "veh-042/c"]
    a = everything[0]
    assert a["agent_id"] == "veh-042" and a["submaps"] == 3
    assert [p["seq"] for p in a["points"]] == [0, 1, 2]
    assert [p["pose_gps_t"] for p in a["points"]] == [[10.0, 10.0, 0.0], [40.0, 12.0, 0.0], [70.0, 10.0, 0.0]]
    assert [p["pose_refined_t"] for p in a["points"]] == [None, [40.5, 11.5, 0.2], None]

    # a box over tile (0, 0) only: session a, with its whole trajectory (also the part in (1, 0))
    in_box = _tracks(client, h, bbox="0,0,50,50")
    assert [s["session_id"] for s in in_box] == ["veh-042/a"] and len(in_box[0]["points"]) == 3
    assert [s["session_id"] for s in _tracks(client, h, bbox="64,0,127,63")] == ["veh-042/a", "veh-042/b"]
    assert [s["session_id"] for s in _tracks(client, h, bbox="300,300,400,400")] == ["veh-042/c"]
    assert _tracks(client, h, bbox="-500,-500,-400,-400") == []

    seen, cursor = [], None
    while True:
        params: dict[str, Any] = {"limit": 2, **({"cursor": cursor} if cursor else {})}
        page = client.get("/v1/sessions", params=params, headers=h).json()
        assert len(page["items"]) <= 2
        seen += [s["session_id"] for s in page["items"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ["veh-042/a", "veh-042/b", "veh-042/c"]
    assert client.get("/v1/sessions", headers=auth["operator"]).status_code == 200


def test_long_trajectories_are_subsampled(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    for seq in range(7):
        upload_at(client, auth["vehicle"], 5.0 + seq, 10.0, seq, "veh-042/long")
    (track,) = _tracks(client, auth["reader"], max_points=4)
    assert track["submaps"] == 7
    assert [p["seq"] for p in track["points"]] == [0, 2, 4, 6]  # even, first and last kept
    (full,) = _tracks(client, auth["reader"], max_points=7)
    assert [p["seq"] for p in full["points"]] == list(range(7))


def test_sessions_listing_bad_input_and_roles(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    upload(client, auth["vehicle"], make_meta(), make_ply())
    for params, code, name in [
        ({"bbox": "1,2"}, "invalid_bbox", "bbox"),
        ({"bbox": "0,0,inf,1"}, "invalid_bbox", "bbox"),
        ({"cursor": "!!"}, "invalid_cursor", "cursor"),
        ({"cursor": "WzFd"}, "invalid_cursor", "cursor"),  # [1]: not a session id
        ({"limit": 0}, "invalid_request", "limit"),
        ({"limit": 201}, "invalid_request", "limit"),
        ({"max_points": 1}, "invalid_request", "max_points"),
    ]:
        resp = client.get("/v1/sessions", params=params, headers=auth["reader"])
        assert resp.status_code == 422 and resp.headers["content-type"].startswith("application/problem+json")
        body = resp.json()
        assert body["code"] == code and body["errors"][0]["loc"] == ["query", name], params
    assert client.get("/v1/sessions", headers=auth["vehicle"]).status_code == 403
    assert client.get("/v1/sessions").status_code == 401
