"""POST /v1/submaps and GET /v1/submaps/{id}: validation, idempotency, auth, limits, durability."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from service.store.models import Submap, SubmapTile, Tile
from tests.conftest import SESSION, VEHICLE, issue_token, make_meta, make_ply, upload

PROBLEM = "application/problem+json"

_ASCII_HEAD = (
    b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    b"element face 1\nproperty list uchar int vertex_indices\n"
)
BAD_MESHES = {
    "malformed_ply": b"this is not a ply file",
    "truncated_ply": make_ply()[:-10],
    "non_finite_coordinates": make_ply(offset=(float("nan"), 0.0, 0.0)),
    "coordinate_limit": make_ply(offset=(2000.0, 0.0, 0.0)),
    "unknown_label": make_ply(labels=[200] * 8),
    "no_labelled_face": make_ply(labels=[0] * 8),
    "empty_mesh": make_ply(n=0),
    "missing_property": (
        _ASCII_HEAD + b"property uchar label\nend_header\n0 0\n1 0\n0 1\n3 0 1 2 1\n"
    ).replace(b"property float z\n", b""),
    "bad_vertex_index": _ASCII_HEAD + b"property uchar label\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 9 1\n",
    "count_mismatch": (
        _ASCII_HEAD + b"property uchar label\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2 1\n"
    ).replace(b"element vertex 3", b"element vertex 5"),
}


def _counts(client: TestClient) -> tuple[int, int, int]:
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        return (
            db.scalar(select(func.count()).select_from(Submap)) or 0,
            db.scalar(select(func.count()).select_from(SubmapTile)) or 0,
            db.scalar(select(func.count()).select_from(Tile)) or 0,
        )


def _blob_files(client: TestClient) -> list[Path]:
    root = Path(client.app.state.settings.resolved_blob_url.removeprefix("file://"))  # type: ignore[attr-defined]
    return [p for p in root.rglob("*") if p.is_file()] if root.exists() else []


def _assert_problem(resp: Any, status: int, code: str | None = None) -> dict[str, Any]:
    assert resp.status_code == status, resp.text
    assert resp.headers["content-type"].startswith(PROBLEM)
    body = resp.json()
    assert {"type", "title", "status", "detail"} <= body.keys()
    assert body["status"] == status
    assert "Traceback" not in resp.text
    if code is not None:
        assert body["code"] == code
    return body


def test_upload_created_then_idempotent_retry(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    mesh = make_ply()
    first = upload(client, auth["vehicle"], make_meta(), mesh)
    assert first.status_code == 201, first.text
    body = first.json()
    assert body["session_id"] == SESSION and body["seq"] == 17
    assert body["tiles"] == [[0, -1]]
    assert len(body["sha256"]) == 64
    retry = upload(client, auth["vehicle"], make_meta(), mesh)
    assert retry.status_code == 200
    assert retry.json() == body
    assert _counts(client)[0] == 1
    assert len(_blob_files(client)) == 1


def test_conflicting_retry_is_409(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    assert upload(client, auth["vehicle"], make_meta(), make_ply()).status_code == 201
    _assert_problem(upload(client, auth["vehicle"], make_meta(), make_ply(n=5)), 409, "submap_conflict")
    moved = make_meta(gps={"pose": {"t": [13.0, -40.1, 0.8], "q": [1, 0, 0, 0]}})
    _assert_problem(upload(client, auth["vehicle"], moved, make_ply()), 409, "submap_conflict")


def test_upload_marks_tiles_dirty_and_bumps_generation(
    client: TestClient, auth: dict[str, dict[str, str]]
) -> None:
    assert upload(client, auth["vehicle"], make_meta(seq=1), make_ply()).status_code == 201
    assert upload(client, auth["vehicle"], make_meta(seq=2), make_ply()).status_code == 201
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        tile = db.get(Tile, (0, -1))
        assert tile is not None
        assert tile.state == "dirty" and tile.dirty_generation == 2 and tile.version == 0
        assert tile.dirty_since is not None and tile.last_upload_at is not None


def test_upload_into_fusing_tile_keeps_state(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    assert upload(client, auth["vehicle"], make_meta(seq=1), make_ply()).status_code == 201
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        db.get(Tile, (0, -1)).state = "fusing"  # type: ignore[union-attr]
        db.commit()
    assert upload(client, auth["vehicle"], make_meta(seq=2), make_ply()).status_code == 201
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        tile = db.get(Tile, (0, -1))
        assert tile is not None and tile.state == "fusing" and tile.dirty_generation == 2


def test_tiles_follow_gps_box_grown_by_sigma(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    meta = make_meta(
        gps={"pose": {"t": [62.0, 10.0, 0.0], "q": [1, 0, 0, 0]}}, gps_sigma={"trans_m": 3.0, "rot_deg": 0.1}
    )
    resp = upload(client, auth["vehicle"], meta, make_ply(n=1))
    assert resp.status_code == 201
    assert resp.json()["tiles"] == [[0, 0], [1, 0]]


def test_geodetic_gps_is_converted_into_the_map_frame(
    client: TestClient, auth: dict[str, dict[str, str]]
) -> None:
    meta = make_meta(gps={"lat": 48.2620, "lon": 11.6670, "alt": 480.0, "q": [1, 0, 0, 0]})
    created = upload(client, auth["vehicle"], meta, make_ply())
    assert created.status_code == 201, created.text
    stored = client.get(f"/v1/submaps/{created.json()['id']}", headers=auth["reader"]).json()
    assert stored["pose_gps"]["t"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert stored["gps"] == {"lat": 48.262, "lon": 11.667, "alt": 480.0, "q": [1.0, 0.0, 0.0, 0.0]}


def test_nearly_unit_quaternion_is_normalised(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    meta = make_meta(gps={"pose": {"t": [1.0, 2.0, 3.0], "q": [1.0005, 0, 0, 0]}})
    created = upload(client, auth["vehicle"], meta, make_ply())
    assert created.status_code == 201
    stored = client.get(f"/v1/submaps/{created.json()['id']}", headers=auth["operator"]).json()
    assert stored["pose_gps"] == {"t": [1.0, 2.0, 3.0], "q": [1.0, 0.0, 0.0, 0.0]}
    assert stored["pose_refined"] is None
    assert stored["tiles"] == created.json()["tiles"]
    assert stored["agent_id"] == VEHICLE and stored["seq"] == 17


@pytest.mark.parametrize(
    "meta",
    [
        make_meta(gps={"pose": {"t": [0, 0, 0], "q": [1.1, 0, 0, 0]}}),
        make_meta(odometry={"t": [0, 0, 0], "q": [0.5, 0, 0, 0]}),
        make_meta(gps={"lat": 48.0, "lon": 11.0, "alt": 0.0, "q": [0, 0, 0, 0]}),
    ],
    ids=["gps", "odometry", "geodetic"],
)
def test_non_unit_quaternion_is_422(
    client: TestClient, auth: dict[str, dict[str, str]], meta: dict[str, Any]
) -> None:
    body = _assert_problem(upload(client, auth["vehicle"], meta, make_ply()), 422, "invalid_meta")
    assert body["errors"] and all(err["loc"][0] == "meta" for err in body["errors"])
    assert any("unit length" in err["msg"] for err in body["errors"])


@pytest.mark.parametrize(
    "meta",
    [
        "{not json",
        "[1, 2]",
        json.dumps(make_meta(seq=-1)),
        json.dumps({"agent_id": VEHICLE}),
        json.dumps(make_meta(captured_at="yesterday")),
        json.dumps(make_meta(extra_field=1)),
    ],
    ids=["syntax", "array", "negative-seq", "missing-fields", "bad-time", "unknown-field"],
)
def test_bad_meta_is_422(client: TestClient, auth: dict[str, dict[str, str]], meta: str) -> None:
    body = _assert_problem(upload(client, auth["vehicle"], meta, make_ply()), 422, "invalid_meta")
    assert body["errors"] and all(e["loc"][0] == "meta" and e["msg"] and e["type"] for e in body["errors"])


@pytest.mark.parametrize("missing", ["meta", "mesh", "both"])
def test_missing_part_is_422(client: TestClient, auth: dict[str, dict[str, str]], missing: str) -> None:
    meta = None if missing in ("meta", "both") else make_meta()
    mesh = None if missing in ("mesh", "both") else make_ply()
    body = _assert_problem(upload(client, auth["vehicle"], meta, mesh), 422, "missing_part")
    expected = ["meta", "mesh"] if missing == "both" else [missing]
    assert [e["loc"] for e in body["errors"]] == [["body", name] for name in expected]


# where each of BAD_MESHES is broken: the start of its errors[0].loc
BAD_MESH_LOCS: dict[str, list[Any]] = {
    "malformed_ply": ["mesh", "header"],
    "truncated_ply": ["mesh", "face"],  # the last face's bytes are cut
    "non_finite_coordinates": ["mesh", "vertex", 0],
    "coordinate_limit": ["mesh", "vertex", 0],
    "unknown_label": ["mesh", "face", 0],
    "no_labelled_face": ["mesh", "face"],
    "empty_mesh": ["mesh", "header"],
    "missing_property": ["mesh", "header"],
    "bad_vertex_index": ["mesh", "face", 0],
    "count_mismatch": ["mesh", "vertex", 4],  # the header says 5 vertices, the data stops at 4 rows
}


@pytest.mark.parametrize("code", sorted(BAD_MESHES))
def test_each_mesh_error_is_422_with_code(
    client: TestClient, auth: dict[str, dict[str, str]], code: str
) -> None:
    body = _assert_problem(upload(client, auth["vehicle"], make_meta(), BAD_MESHES[code]), 422, code)
    assert body["type"] == f"urn:fleetmap:problem:{code}"
    assert len(body["errors"]) == 1, body
    (error,) = body["errors"]
    expected = BAD_MESH_LOCS[code]
    assert error["loc"][: len(expected)] == expected, error
    assert error["type"] == code and error["msg"] == body["detail"]


def test_mesh_error_loc_names_the_corrupted_face(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    mesh = make_ply(n=40, labels=[1] * 57 + [99] + [1] * 22)
    body = _assert_problem(upload(client, auth["vehicle"], make_meta(), mesh), 422, "unknown_label")
    assert body["errors"][0]["loc"] == ["mesh", "face", 57]


def test_meta_errors_carry_json_paths(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    bad_q = make_meta(gps={"pose": {"t": [0, 0, 0], "q": [1.1, 0, 0, 0]}})
    body = _assert_problem(upload(client, auth["vehicle"], bad_q, make_ply()), 422, "invalid_meta")
    assert [e["loc"] for e in body["errors"]] == [["meta", "gps", "pose", "q"]]
    assert body["errors"][0]["type"] == "value_error"
    geodetic = make_meta(gps={"lat": 95.0, "lon": 11.0, "alt": 0.0, "q": [1, 0, 0, 0]})
    body = _assert_problem(upload(client, auth["vehicle"], geodetic, make_ply()), 422, "invalid_meta")
    assert [e["loc"] for e in body["errors"]] == [["meta", "gps", "lat"]]
    body = _assert_problem(upload(client, auth["vehicle"], make_meta(gps=3), make_ply()), 422, "invalid_meta")
    assert [e["loc"] for e in body["errors"]] == [["meta", "gps"]]
    body = _assert_problem(upload(client, auth["vehicle"], make_meta(seq=-1), make_ply()), 422, "invalid_meta")
    assert [(e["loc"], e["type"]) for e in body["errors"]] == [(["meta", "seq"], "greater_than_equal")]


def test_malformed_multipart_is_400_with_errors(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    resp = client.post(
        "/v1/submaps",
        content=b"--b\r\nContent-Disposition: form-data\r\n\r\nx\r\n--b--\r\n",
        headers={**auth["vehicle"], "Content-Type": "multipart/form-data; boundary=b"},
    )
    body = _assert_problem(resp, 400)
    assert body["errors"] and body["errors"][0]["loc"] == ["body"]
    assert _counts(client) == (0, 0, 0)
    assert _blob_files(client) == []


def test_too_many_faces_uses_configured_limit(make_client: Any) -> None:
    client = make_client(max_faces=4)
    headers = issue_token(client, "vehicle", VEHICLE)
    _assert_problem(upload(client, headers, make_meta(), make_ply(n=4)), 422, "too_many_faces")
    assert upload(client, headers, make_meta(), make_ply(n=2)).status_code == 201


@pytest.mark.parametrize("encoding", ["ascii", "binary_big_endian"])
def test_other_ply_encodings_accepted(
    client: TestClient, auth: dict[str, dict[str, str]], encoding: str
) -> None:
    assert upload(client, auth["vehicle"], make_meta(), make_ply(encoding=encoding)).status_code == 201


def _multipart(meta: dict[str, Any], mesh: bytes, boundary: str = "fleetmapboundary") -> bytes:
    return (
        (
            f'--{boundary}\r\nContent-Disposition: form-data; name="meta"\r\nContent-Type: application/json\r\n\r\n'
            f"{json.dumps(meta)}\r\n--{boundary}\r\n"
            'Content-Disposition: form-data; name="mesh"; filename="m.ply"\r\nContent-Type: application/octet-stream\r\n\r\n'
        ).encode()
        + mesh
        + f"\r\n--{boundary}--\r\n".encode()
    )


def test_oversize_body_by_content_length_is_413(make_client: Any) -> None:
    client = make_client(max_upload_bytes=20_000)
    headers = issue_token(client, "vehicle", VEHICLE)
    body = _multipart(make_meta(), make_ply(n=2000))
    assert len(body) > 20_000
    resp = client.post(
        "/v1/submaps",
        content=body,
        headers={**headers, "Content-Type": "multipart/form-data; boundary=fleetmapboundary"},
    )
    _assert_problem(resp, 413, "body_too_large")
    assert _counts(client) == (0, 0, 0) and _blob_files(client) == []


def test_oversize_streamed_body_is_413(make_client: Any) -> None:
    client = make_client(max_upload_bytes=20_000)
    headers = issue_token(client, "vehicle", VEHICLE)
    body = _multipart(make_meta(), make_ply(n=2000))
    sent: list[int] = []

    def chunks() -> Any:
        for start in range(0, len(body), 4096):
            sent.append(start)
            yield body[start : start + 4096]

    resp = client.post(
        "/v1/submaps",
        content=chunks(),
        headers={**headers, "Content-Type": "multipart/form-data; boundary=fleetmapboundary"},
    )
    _assert_problem(resp, 413, "body_too_large")
    assert "content-length" not in {k.lower() for k in resp.request.headers}
    assert _counts(client) == (0, 0, 0) and _blob_files(client) == []
    # a body within the limit still goes through the same path
    small = _multipart(make_meta(), make_ply())
    ok = client.post(
        "/v1/submaps",
        content=iter([small[:100], small[100:]]),
        headers={**headers, "Content-Type": "multipart/form-data; boundary=fleetmapboundary"},
    )
    assert ok.status_code == 201, ok.text


def test_auth_roles_for_upload(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    _assert_problem(upload(client, {}, make_meta(), make_ply()), 401, "unauthenticated")
    resp = upload(client, {"Authorization": "Bearer nope"}, make_meta(), make_ply())
    _assert_problem(resp, 401, "invalid_token")
    assert resp.headers["www-authenticate"].startswith("Bearer")
    _assert_problem(upload(client, auth["reader"], make_meta(), make_ply()), 403, "forbidden")
    other = make_meta(agent_id="veh-007", session_id="veh-007/s1")
    _assert_problem(upload(client, auth["vehicle"], other, make_ply()), 403, "agent_mismatch")
    assert upload(client, auth["operator"], other, make_ply()).status_code == 201
    assert _counts(client)[0] == 1


def test_session_belongs_to_one_agent(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    assert upload(client, auth["vehicle"], make_meta(seq=1), make_ply()).status_code == 201
    hijack = make_meta(agent_id="veh-007", seq=2)
    _assert_problem(upload(client, auth["operator"], hijack, make_ply()), 409, "session_agent_mismatch")


def test_concurrent_identical_uploads_never_500(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    mesh, statuses = make_ply(), []
    lock = threading.Lock()

    def send() -> None:
        resp = upload(client, auth["vehicle"], make_meta(), mesh)
        with lock:
            statuses.append(resp.status_code)

    threads = [threading.Thread(target=send) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(statuses) == [200] * 5 + [201]
    assert _counts(client)[0] == 1


def test_get_submap_404_and_roles(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    created = upload(client, auth["vehicle"], make_meta(), make_ply()).json()
    _assert_problem(client.get("/v1/submaps/nope", headers=auth["reader"]), 404, "submap_not_found")
    _assert_problem(client.get(f"/v1/submaps/{created['id']}", headers=auth["vehicle"]), 403)
    _assert_problem(client.get(f"/v1/submaps/{created['id']}"), 401)
    assert client.get(f"/v1/submaps/{created['id']}", headers=auth["reader"]).status_code == 200


def _precheck_misses_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make the first pre-check see nothing, as if a concurrent upload committed right after it."""
    from service.store import submaps

    real, calls = submaps._precheck, []

    def precheck(db: Any, prepared: Any) -> Any:
        calls.append(1)
        return None if len(calls) == 1 else real(db, prepared)

    monkeypatch.setattr(submaps, "_precheck", precheck)


def test_upload_racing_an_identical_one_is_200(
    client: TestClient, auth: dict[str, dict[str, str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    first = upload(client, auth["vehicle"], make_meta(), make_ply())
    assert first.status_code == 201
    before = _counts(client)
    _precheck_misses_once(monkeypatch)
    retry = upload(client, auth["vehicle"], make_meta(), make_ply())
    assert retry.status_code == 200, retry.text
    assert retry.json() == first.json()
    assert _counts(client) == before
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        assert db.get(Tile, (0, -1)).dirty_generation == 1  # type: ignore[union-attr]


def test_upload_racing_a_session_of_another_agent_is_409(
    client: TestClient, auth: dict[str, dict[str, str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    assert upload(client, auth["vehicle"], make_meta(seq=1), make_ply()).status_code == 201
    before = _counts(client)
    _precheck_misses_once(monkeypatch)
    hijack = make_meta(agent_id="veh-007", seq=2)
    _assert_problem(upload(client, auth["operator"], hijack, make_ply()), 409, "session_agent_mismatch")
    assert _counts(client) == before
