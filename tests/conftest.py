"""Fixtures for the HTTP API tests: an app on a tmp data dir, per-role tokens, PLY/meta builders,
uploads at a map position and fused tile versions stored without running a fusion.

The database URL is parametrised over SQLite (a file in tmp_path) and PostgreSQL (a fresh schema
per test in ``FLEETMAP_TEST_DATABASE_URL``, default ``postgresql+psycopg://postgres@127.0.0.1:5432/test``;
skipped when unreachable).
"""

from __future__ import annotations

import io
import json
import os
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import plyfile
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text

from fusion.meshio import write_fused_ply, write_glb
from fusion.types import FusedMesh
from service.api.app import create_app
from service.api.auth import create_token
from service.settings import Settings
from service.store.models import Tile, TileVersion, utcnow

PG_URL = os.environ.get("FLEETMAP_TEST_DATABASE_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
VEHICLE = "veh-042"
SESSION = "veh-042/2026-11-24T08:00:00Z"


def _pg_reachable() -> bool:
    try:
        engine = create_engine(PG_URL, connect_args={"connect_timeout": 2})
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
        engine.dispose()
        return True
    except Exception:
        return False


_PG_OK: bool | None = None


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request: pytest.FixtureRequest, tmp_path: Any) -> Iterator[str]:
    """A fresh, empty database: a SQLite file, or a new PostgreSQL schema dropped afterwards."""
    global _PG_OK
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'fleetmap.db'}"
        return
    if _PG_OK is None:
        _PG_OK = _pg_reachable()
    if not _PG_OK:
        pytest.skip(f"PostgreSQL not reachable at {PG_URL}")
    schema = f"fleetmap_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(PG_URL)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    sep = "&" if "?" in PG_URL else "?"
    yield f"{PG_URL}{sep}options=-csearch_path%3D{schema}"
    with admin.begin() as conn:
        conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
    admin.dispose()


@pytest.fixture
def make_settings(tmp_path: Any, database_url: str) -> Callable[..., Settings]:
    def make(**overrides: Any) -> Settings:
        values: dict[str, Any] = {
            "data_dir": tmp_path / "data",
            "database_url": database_url,
            "broker_url": "",
            "auth": "on",
            "db_statement_timeout_ms": 0,  # keep the URL's search_path option on PostgreSQL
        }
        values.update(overrides)
        return Settings(**values)

    return make


@pytest.fixture
def make_client(make_settings: Callable[..., Settings]) -> Iterator[Callable[..., TestClient]]:
    """Build (and later close) clients on apps with settings overrides; same data dir and DB."""
    opened: list[TestClient] = []

    def make(**overrides: Any) -> TestClient:
        app = create_app(make_settings(**overrides), migrate=True, background=False)
        client = TestClient(app, raise_server_exceptions=False)
        client.__enter__()
        opened.append(client)
        return client

    yield make
    for client in reversed(opened):
        client.__exit__(None, None, None)


@pytest.fixture
def client(make_client: Callable[..., TestClient]) -> TestClient:
    return make_client()


def issue_token(client: TestClient, role: str, name: str) -> dict[str, str]:
    """Create a token directly in the app's database; returns the Authorization header."""
    factory = client.app.state.session_factory  # type: ignore[attr-defined]
    with factory() as db:
        _, secret = create_token(db, role, name)
        db.commit()
    return {"Authorization": f"Bearer {secret}"}


@pytest.fixture
def auth(client: TestClient) -> dict[str, dict[str, str]]:
    """Authorization headers per role; the vehicle's name is its agent_id ``veh-042``."""
    return {
        "vehicle": issue_token(client, "vehicle", VEHICLE),
        "operator": issue_token(client, "operator", "ops"),
        "reader": issue_token(client, "reader", "viewer"),
    }


def make_ply(
    n: int = 4,
    *,
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    labels: list[int] | None = None,
    encoding: str = "binary_little_endian",
    scale: float = 1.0,
) -> bytes:
    """A small labelled triangle-strip ground patch (local frame, metres) as PLY bytes."""
    xs = np.arange(n + 1, dtype=np.float32) * scale
    verts = [(x + offset[0], y + offset[1], offset[2]) for y in (0.0, scale) for x in xs]
    faces = []
    for k in range(n):
        a, b, c, d = k, k + 1, n + 1 + k, n + 2 + k
        faces.append([a, b, c])
        faces.append([b, d, c])
    face_labels = labels if labels is not None else [1 + (f % 3) for f in range(len(faces))]
    vertex = np.array(verts, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,)), ("label", "u1")])
    face["vertex_indices"] = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
    face["label"] = face_labels
    ply = plyfile.PlyData(
        [plyfile.PlyElement.describe(vertex, "vertex"), plyfile.PlyElement.describe(face, "face")],
        text=encoding == "ascii",
        byte_order=">" if encoding == "binary_big_endian" else "<",
    )
    buf = io.BytesIO()
    ply.write(buf)
    return buf.getvalue()


def make_meta(**overrides: Any) -> dict[str, Any]:
    meta: dict[str, Any] = {
        "agent_id": VEHICLE,
        "session_id": SESSION,
        "seq": 17,
        "captured_at": "2026-11-24T08:03:10Z",
        "gps": {"pose": {"t": [12.3, -40.1, 0.8], "q": [1, 0, 0, 0]}},
        "gps_sigma": {"trans_m": 2.0, "rot_deg": 2.0},
        "odometry": {"t": [0.0, 0.0, 0.0], "q": [1, 0, 0, 0]},
        "odometry_sigma": {"trans_m": 0.05, "rot_deg": 0.5},
    }
    meta.update(overrides)
    return meta


def upload(
    client: TestClient,
    headers: dict[str, str],
    meta: dict[str, Any] | str | None = None,
    mesh: bytes | None = None,
) -> Any:
    """POST /v1/submaps with ``meta`` (dict → JSON) and ``mesh`` parts; None omits a part."""
    files: dict[str, Any] = {}
    if meta is not None:
        files["meta"] = (None, meta if isinstance(meta, str) else json.dumps(meta), "application/json")
    if mesh is not None:
        files["mesh"] = ("submap.ply", mesh, "application/octet-stream")
    return client.post("/v1/submaps", headers=headers, files=files or {"other": (None, "x")})


def upload_at(
    client: TestClient, headers: dict[str, str], x: float, y: float, seq: int, session: str = "veh-042/s"
) -> Any:
    """Upload a one-metre patch GPS-posed at map-frame ``(x, y)`` (so it touches one tile); 201 asserted."""
    meta = make_meta(
        session_id=session,
        seq=seq,
        gps={"pose": {"t": [x, y, 0.0], "q": [1, 0, 0, 0]}},
        gps_sigma={"trans_m": 0.5, "rot_deg": 0.01},
    )
    resp = upload(client, headers, meta, make_ply(n=1))
    assert resp.status_code == 201, resp.text
    return resp.json()


def publish_version(
    app: Any,
    i: int,
    j: int,
    version: int,
    mesh: FusedMesh,
    *,
    job_id: str | None = None,
    metrics: dict[str, Any] | None = None,
) -> None:
    """What a successful fusion leaves behind in ``app``'s stores: the PLY and GLB blobs, a
    tile_versions row, the tile ``fused`` at that version (no torch, no worker)."""
    blobs = app.state.blobs
    ply_sha, glb_sha = blobs.put(write_fused_ply(mesh)), blobs.put(write_glb(mesh))
    with app.state.session_factory() as db:
        db.add(
            TileVersion(
                tile_i=i,
                tile_j=j,
                version=version,
                job_id=job_id,
                mesh_sha256=ply_sha,
                glb_sha256=glb_sha,
                metrics=metrics if metrics is not None else {},
            )
        )
        tile = db.get(Tile, (i, j))
        assert tile is not None
        tile.version, tile.state, tile.fused_at = version, "fused", utcnow()
        db.commit()
