"""Labels, capabilities, health/readiness/metrics/viewer, problem documents, auth modes, OpenAPI,
restart durability, migrations vs models, and the token CLI."""

from __future__ import annotations

import time
from typing import Any

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, update
from sqlalchemy.orm import sessionmaker

from service import cli
from service.api.app import create_app
from service.api.auth import revoke_tokens
from service.settings import Settings, get_settings
from service.store.db import make_engine
from service.store.migrate import upgrade
from service.store.models import Base, Token, utcnow
from tests.conftest import issue_token, make_meta, make_ply, upload

PROBLEM = "application/problem+json"


def test_labels_for_every_role(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    for role in ("vehicle", "operator", "reader"):
        resp = client.get("/v1/labels", headers=auth[role])
        assert resp.status_code == 200
    labels = resp.json()
    assert labels[0] == {"id": 0, "name": "unlabeled", "color": [0, 0, 0]}
    assert [label["name"] for label in labels][1:4] == ["road", "sidewalk", "lane_marking"]
    assert labels[11]["name"] == "obstacle"
    unauth = client.get("/v1/labels")
    assert unauth.status_code == 401 and unauth.headers["content-type"].startswith(PROBLEM)
    assert unauth.headers["www-authenticate"] == "Bearer"


def test_capabilities(make_client: Any) -> None:
    client = make_client(max_faces=1234, tile_size=32.0, origin="48.0,11.0,500.0")
    from tests.conftest import issue_token

    resp = client.get("/v1/capabilities", headers=issue_token(client, "vehicle", "veh-1"))
    assert resp.status_code == 200, resp.text
    body = resp.json()
    assert body["max_upload_bytes"] == 64 * 1024 * 1024
    assert body["max_faces"] == 1234 and body["max_coordinate_m"] == 1000.0 and body["tile_size_m"] == 32.0
    assert body["origin"] == {"lat": 48.0, "lon": 11.0, "alt": 500.0}
    assert body["labels_url"].endswith("/v1/labels")


def test_health_ready_viewer_need_no_token(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["checks"] == {"database": "ok", "blob_store": "ok", "broker": "skipped"}
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert 'type="importmap"' in page.text and '<script type="module"' in page.text  # tests/service/test_api_viewer.py


def test_readyz_503_when_blob_store_or_database_down(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken() -> None:
        raise OSError("disk gone")

    monkeypatch.setattr(client.app.state.blobs, "ping", broken)  # type: ignore[attr-defined]
    resp = client.get("/readyz")
    assert resp.status_code == 503 and resp.headers["content-type"].startswith(PROBLEM)
    assert [e["component"] for e in resp.json()["errors"]] == ["blob_store"]
    state = client.app.state  # type: ignore[attr-defined]
    engine, state.engine = state.engine, create_engine("sqlite:////proc/no/such/dir/x.db")
    try:
        assert [e["component"] for e in client.get("/readyz").json()["errors"]] == ["database", "blob_store"]
    finally:
        state.engine = engine


def test_readyz_checks_broker_when_configured(make_client: Any) -> None:
    client = make_client(broker_url="redis://127.0.0.1:1/0")
    resp = client.get("/readyz")
    assert resp.status_code == 503
    assert [e["component"] for e in resp.json()["errors"]] == ["broker"]


def test_database_unavailable_is_503_problem(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    dead = create_engine("sqlite:////proc/no/such/dir/x.db")
    client.app.state.session_factory = sessionmaker(bind=dead)  # type: ignore[attr-defined]
    resp = client.get("/v1/tiles", headers=auth["reader"])
    assert resp.status_code == 503 and resp.headers["content-type"].startswith(PROBLEM)
    assert resp.json()["code"] == "database_unavailable" and "Traceback" not in resp.text


def test_unexpected_error_is_500_problem_without_stack_trace(client: TestClient) -> None:
    def boom() -> None:
        raise RuntimeError("secret internals")

    client.app.add_api_route("/boom", boom)  # type: ignore[attr-defined]
    resp = client.get("/boom")
    assert resp.status_code == 500 and resp.headers["content-type"].startswith(PROBLEM)
    assert "secret internals" not in resp.text and "Traceback" not in resp.text
    assert resp.json()["code"] == "internal_error"


def test_unknown_route_and_method_are_problems(client: TestClient) -> None:
    for resp, status in ((client.get("/v1/nothing"), 404), (client.delete("/v1/labels"), 405)):
        assert resp.status_code == status and resp.headers["content-type"].startswith(PROBLEM)
        assert resp.json()["status"] == status


def test_metrics(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    assert upload(client, auth["vehicle"], make_meta(), make_ply()).status_code == 201
    assert upload(client, auth["vehicle"], "{broken", make_ply()).status_code == 422
    resp = client.get("/metrics")
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/plain")
    text = resp.text
    assert 'fleetmap_uploads_total{outcome="created"}' in text
    assert 'fleetmap_upload_rejections_total{reason="invalid_meta"}' in text
    assert "fleetmap_upload_bytes_total" in text
    assert 'fleetmap_tiles{state="dirty"} 1.0' in text and 'fleetmap_tiles{state="fused"} 0.0' in text
    assert "fleetmap_fusion_queue_depth 0.0" in text
    assert "fleetmap_fusion_duration_seconds_bucket" in text or "fleetmap_fusion_duration_seconds" in text


def test_request_id_is_echoed(client: TestClient) -> None:
    assert client.get("/healthz", headers={"X-Request-ID": "abc-123"}).headers["x-request-id"] == "abc-123"
    assert len(client.get("/healthz").headers["x-request-id"]) == 32


def test_revoked_token_is_401(client: TestClient, auth: dict[str, dict[str, str]]) -> None:
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        assert revoke_tokens(db, "viewer") == 1
        db.commit()
    assert client.get("/v1/tiles", headers=auth["reader"]).status_code == 401


def test_token_cache_honours_revocation(make_client: Any) -> None:
    client = make_client(auth_cache_s=0.5)
    headers = issue_token(client, "reader", "viewer")
    assert client.get("/v1/tiles", headers=headers).status_code == 200  # now cached
    # revoked by another process (the CLI): honoured once the cache entry expires
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        db.execute(update(Token).where(Token.name == "viewer").values(revoked_at=utcnow()))
        db.commit()
    deadline = time.monotonic() + 5
    while client.get("/v1/tiles", headers=headers).status_code == 200:
        assert time.monotonic() < deadline, "revocation not honoured after the cache TTL"
        time.sleep(0.1)
    assert client.get("/v1/tiles", headers=headers).status_code == 401
    # revoked in this process: at once
    other = issue_token(client, "reader", "viewer-2")
    assert client.get("/v1/tiles", headers=other).status_code == 200
    with client.app.state.session_factory() as db:  # type: ignore[attr-defined]
        assert revoke_tokens(db, "viewer-2") == 1
        db.commit()
    assert client.get("/v1/tiles", headers=other).status_code == 401


def test_auth_off(make_client: Any) -> None:
    client = make_client(auth="off")
    assert upload(client, {}, make_meta(), make_ply()).status_code == 201
    assert len(client.get("/v1/tiles").json()["items"]) == 1


def test_restart_loses_nothing(make_client: Any) -> None:
    from tests.conftest import issue_token

    first = make_client()
    headers = issue_token(first, "operator", "ops")
    created = upload(first, headers, make_meta(), make_ply()).json()
    first.__exit__(None, None, None)

    second = make_client()
    assert second.get(f"/v1/submaps/{created['id']}", headers=headers).json()["sha256"] == created["sha256"]
    assert second.get("/v1/tiles/0/-1", headers=headers).json()["submaps"] == 1
    assert upload(second, headers, make_meta(), make_ply()).status_code == 200
    assert second.app.state.blobs.exists(created["sha256"])  # type: ignore[attr-defined]


def test_openapi_is_complete(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    ops = {(m, p): op for p, item in spec["paths"].items() for m, op in item.items()}
    expected = {
        ("get", "/v1/labels"),
        ("get", "/v1/capabilities"),
        ("post", "/v1/submaps"),
        ("get", "/v1/submaps/{submap_id}"),
        ("get", "/v1/tiles"),
        ("get", "/v1/tiles/{i}/{j}"),
        ("post", "/v1/tiles/{i}/{j}/fuse"),
        ("get", "/v1/tiles/{i}/{j}/mesh"),
        ("get", "/v1/jobs/{job_id}"),
        ("get", "/v1/sessions/{session_id}/poses"),
        ("get", "/v1/sessions"),
        ("get", "/v1/tiles/{i}/{j}/versions"),
        ("get", "/v1/tiles/{i}/{j}/submaps"),
        ("get", "/v1/tiles/{i}/{j}/jobs"),
        ("get", "/healthz"),
        ("get", "/readyz"),
        ("get", "/metrics"),
        ("get", "/"),
    }
    assert expected <= set(ops)
    assert len({op["operationId"] for op in ops.values()}) == len(ops)
    for key, op in ops.items():
        for status, response in op["responses"].items():
            if status.startswith(("4", "5")):
                assert list(response["content"]) == [PROBLEM], (key, status)
        if key[1].startswith("/v1/"):
            assert {"401", "403"} <= set(op["responses"]), key
    upload_op = ops[("post", "/v1/submaps")]
    assert {"200", "201", "409", "413", "422"} <= set(upload_op["responses"])
    assert "multipart/form-data" in upload_op["requestBody"]["content"]
    assert {"Problem", "SubmapMeta", "TilePublic", "JobPublic"} <= set(spec["components"]["schemas"])
    assert {"TileVersionPage", "TileSubmapPage", "JobList", "SessionTrackPage"} <= set(spec["components"]["schemas"])
    for path in ("/v1/tiles/{i}/{j}/versions", "/v1/tiles/{i}/{j}/submaps", "/v1/tiles/{i}/{j}/jobs"):
        assert {"401", "403", "404", "422"} <= set(ops[("get", path)]["responses"]), path
    assert "HTTPValidationError" not in spec["components"]["schemas"]
    errors = spec["components"]["schemas"]["Problem"]["properties"]["errors"]
    assert {"$ref": "#/components/schemas/ValidationErrorItem"} in [
        option.get("items") for option in errors.get("anyOf", [errors])
    ]
    item = spec["components"]["schemas"]["ValidationErrorItem"]
    assert {"loc", "msg", "type"} <= set(item["required"])


def test_migrations_match_models(database_url: str) -> None:
    engine = make_engine(database_url, Settings(database_url=database_url, db_statement_timeout_ms=0))
    upgrade(engine)
    upgrade(engine)  # idempotent
    with engine.connect() as conn:
        assert (
            compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata)
            == []
        )
    engine.dispose()


def test_token_cli(
    tmp_path: Any, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("FLEETMAP_DATA_DIR", str(tmp_path))
    for name in ("FLEETMAP_DATABASE_URL", "FLEETMAP_BROKER_URL", "FLEETMAP_AUTH"):
        monkeypatch.delenv(name, raising=False)
    get_settings.cache_clear()
    try:
        assert cli.main(["token", "create", "--role", "vehicle", "--name", "veh-9"]) == 0
        secret = capsys.readouterr().out.strip()
        assert secret.startswith("fm_")
        assert cli.main(["token", "list"]) == 0
        listing = capsys.readouterr().out
        assert "veh-9" in listing and secret not in listing

        app = create_app(get_settings(), migrate=True, background=False)
        with TestClient(app) as client:
            headers = {"Authorization": f"Bearer {secret}"}
            assert client.get("/v1/labels", headers=headers).status_code == 200
            assert cli.main(["token", "revoke", "veh-9"]) == 0
            assert client.get("/v1/labels", headers=headers).status_code == 401
        assert cli.main(["token", "revoke", "veh-9"]) == 2
        assert "error" in capsys.readouterr().err
        with pytest.raises(SystemExit):
            cli.main(["token", "create", "--role", "admin", "--name", "x"])
    finally:
        get_settings.cache_clear()
