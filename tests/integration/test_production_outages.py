"""Outages of the production stack's parts, with real servers: the API process crashes during
uploads, Redis restarts empty, PostgreSQL becomes unreachable. Each test uses its own database,
queue and (for Redis) its own redis-server; the shared servers are never touched.
"""

from __future__ import annotations

import hashlib
import json
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from service.store.models import Submap, Tile, TileState
from tests.production_support import (
    RedisServer,
    TcpProxy,
    deployment,
    free_port,
    post_submap,
    small_mesh,
    submap_meta,
    wait_until,
)

pytestmark = [pytest.mark.integration, pytest.mark.slow]

PROBLEM = "application/problem+json"


def _stored(dep: Any) -> dict[tuple[str, int], str]:
    """(session, seq) → mesh sha256 of every stored submap."""
    with dep.session() as db:
        return {(s.session_id, s.seq): s.mesh_sha256 for s in db.scalars(select(Submap))}


# ------------------------------------------------------------------------------------ API crash


class Uploader(threading.Thread):
    """One vehicle uploading ``count`` submaps in order; every 5th is invalid (must be rejected).

    Outcomes: ``acked`` (200/201), ``rejected`` (any other answer), ``unknown`` (no answer: the
    connection failed, so the submap may or may not be stored).
    """

    def __init__(self, base: str, headers: dict[str, str], vehicle: str, count: int, deadline: float) -> None:
        super().__init__(daemon=True)
        self.base, self.headers, self.session = base, headers, f"{vehicle}/restart"
        self.count, self.deadline = count, deadline
        self.sent: dict[int, tuple[dict[str, Any], bytes]] = {}
        self.acked: set[int] = set()
        self.rejected: set[int] = set()
        self.unknown: set[int] = set()

    def run(self) -> None:
        with httpx.Client(base_url=self.base, timeout=20) as client:
            for seq in range(self.count):
                if time.monotonic() > self.deadline:
                    return
                meta = submap_meta(self.session, seq, [20.0 + seq % 8, 20.0, 0.0])
                mesh = b"ply\nformat ascii 1.0\nend_header\n" if seq % 5 == 4 else small_mesh(seq)
                self.sent[seq] = (meta, mesh)
                try:
                    response = post_submap(client, self.headers, meta, mesh)
                except httpx.TransportError:
                    self.unknown.add(seq)
                    time.sleep(0.3)
                    continue
                (self.acked if response.status_code in (200, 201) else self.rejected).add(seq)


def test_api_crash_during_uploads_loses_no_acknowledged_submap(tmp_path: Path) -> None:
    with deployment(tmp_path) as dep:
        port = free_port()
        api, base = dep.api(port=port, name="api-1")
        deadline = time.monotonic() + 90
        uploaders = [Uploader(base, dep.headers, f"veh-{k}", 30, deadline) for k in range(4)]
        for uploader in uploaders:
            uploader.start()
        wait_until(lambda: sum(len(u.acked) for u in uploaders) >= 12, 60, "uploads before the crash")
        api.kill()  # SIGKILL: in-flight requests get no answer
        dep.api(port=port, name="api-2")
        for uploader in uploaders:
            uploader.join(timeout=max(1.0, deadline - time.monotonic() + 5))
            assert not uploader.is_alive()

        stored = _stored(dep)
        for u in uploaders:
            keys = {seq for (session, seq) in stored if session == u.session}
            assert u.acked <= keys, f"{u.session}: acknowledged but lost: {sorted(u.acked - keys)}"
            assert not (u.rejected & keys), f"{u.session}: rejected but stored: {sorted(u.rejected & keys)}"
            assert keys <= u.acked | u.unknown
            assert all(seq % 5 == 4 for seq in u.rejected), f"unexpected rejections {sorted(u.rejected)}"
        assert sum(len(u.acked) for u in uploaders) > 12, "no upload succeeded after the restart"

        # Every stored row names a complete blob (the blob is durable before the row commits).
        for (session, seq), sha in stored.items():
            blob = tmp_path / "blobs" / "sha256" / sha[:2] / sha[2:4] / sha
            uploader = next(u for u in uploaders if u.session == session)
            assert (
                hashlib.sha256(blob.read_bytes()).hexdigest()
                == sha
                == hashlib.sha256(uploader.sent[seq][1]).hexdigest()
            )

        # Retrying the unanswered uploads is safe: 200 if the crashed process had stored it, else 201.
        with httpx.Client(base_url=base, timeout=20) as client:
            for u in uploaders:
                for seq in sorted(u.unknown):
                    meta, mesh = u.sent[seq]
                    response = post_submap(client, dep.headers, meta, mesh)
                    if seq % 5 == 4:
                        assert response.status_code == 422
                    else:
                        expected = 200 if (u.session, seq) in stored else 201
                        assert response.status_code == expected, response.text


# ---------------------------------------------------------------------------------- Redis restart


def test_redis_restart_recovers_without_manual_steps(tmp_path: Path) -> None:
    redis_server = RedisServer(tmp_path)
    redis_server.start()
    try:
        with deployment(tmp_path, broker_url=redis_server.url, fuse_requeue_s="2") as dep:
            try:
                _, base = dep.api()
                dep.worker()
                with httpx.Client(base_url=base, timeout=20, headers=dep.headers) as client:
                    assert client.get("/readyz").status_code == 200
                    redis_server.stop()  # the broker is gone, with every message in it
                    ready = client.get("/readyz")
                    assert ready.status_code == 503 and ready.headers["content-type"].startswith(PROBLEM)
                    for seq in range(2):  # uploads do not need the broker
                        meta = submap_meta("veh-r/redis", seq, [20.0 + 4 * seq, 20.0, 0.0])
                        response = post_submap(client, dep.headers, meta, small_mesh(seq))
                        assert response.status_code == 201, response.text

                    def queued() -> bool:
                        with dep.session() as db:
                            tile = db.get(Tile, (0, 0))
                            return tile is not None and tile.state == TileState.queued.value

                    wait_until(queued, 60, "the tile queued while the broker is down")
                    redis_server.start()  # same port, empty: the job's message is lost
                    tile = wait_until(
                        lambda: (body := client.get("/v1/tiles/0/0").json())["state"] == "fused" and body,
                        180,
                        "the tile fused after the broker came back",
                        interval_s=0.5,
                    )
                    assert tile["version"] == 1
                    assert client.get("/readyz").status_code == 200
            except AssertionError as exc:
                raise AssertionError(f"{exc}\n{dep.logs()}") from None
    finally:
        redis_server.stop()


# ------------------------------------------------------------------------------ PostgreSQL outage


def test_postgres_outage_gives_fast_503s_and_recovers(tmp_path: Path) -> None:
    from sqlalchemy.engine import make_url

    with deployment(tmp_path) as dep:
        direct = make_url(dep.database_url)
        proxy = TcpProxy(direct.host or "127.0.0.1", direct.port or 5432).start()
        try:
            proxied = direct.set(port=proxy.port).render_as_string(hide_password=False)
            _, base = dep.api(
                FLEETMAP_DATABASE_URL=proxied,
                FLEETMAP_DB_CONNECT_TIMEOUT_S="2",
                FLEETMAP_DB_POOL_TIMEOUT_S="2",
            )
            # The client timeout is the "no hang" bound: a request stuck on the database fails it.
            with httpx.Client(base_url=base, timeout=15, headers=dep.headers) as client:
                response = post_submap(
                    client, dep.headers, submap_meta("veh-p/pg", 0, [20.0, 20.0, 0.0]), small_mesh()
                )
                assert response.status_code == 201, response.text
                assert client.get("/v1/tiles").status_code == 200

                proxy.cut()
                for attempt in range(3):  # pooled connections are dead, new ones are refused
                    for response in (
                        client.get("/v1/tiles"),
                        client.get("/v1/tiles/0/0"),
                        post_submap(
                            client, dep.headers, submap_meta("veh-p/pg", 1, [24.0, 20.0, 0.0]), small_mesh(1)
                        ),
                        client.get("/readyz"),
                    ):
                        assert response.status_code == 503, (attempt, response.request.url, response.text)
                        assert response.headers["content-type"].startswith(PROBLEM)
                        body = json.loads(response.text)
                        assert body["status"] == 503 and "Traceback" not in response.text
                assert client.get("/healthz").status_code == 200  # alive, just not ready

                proxy.restore()
                wait_until(
                    lambda: client.get("/v1/tiles").status_code == 200, 30, "recovery after the outage"
                )
                response = post_submap(
                    client, dep.headers, submap_meta("veh-p/pg", 1, [24.0, 20.0, 0.0]), small_mesh(1)
                )
                assert response.status_code == 201, response.text
                assert client.get("/readyz").status_code == 200
                assert client.get("/v1/tiles/0/0").json()["submaps"] == 2
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{dep.logs()}") from None
        finally:
            proxy.stop()
