"""GET /v1/sessions/{session_id}/poses with URL-encoded slashes in the session id."""

from __future__ import annotations

from urllib.parse import quote

from fastapi.testclient import TestClient

from service.store.models import Submap
from tests.conftest import SESSION, make_meta, make_ply, upload


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
