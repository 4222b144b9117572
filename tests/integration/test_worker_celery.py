"""Production path: the API enqueues by task name on Redis, a real ``fleetmap worker`` (Celery, prefork)
fuses with the tiny config, both share PostgreSQL and a blob folder. Also: a lost broker message is
re-sent by the scheduler's sweeper.

Needs the local Redis (``FLEETMAP_TEST_REDIS_URL``) and PostgreSQL (``FLEETMAP_TEST_DATABASE_URL``); skipped
only when Redis is unreachable (CI starts both). Each run uses its own queue and database.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest

from service import schedule as scheduler
from service.store.models import FusionJob
from tests.production_support import (
    TEST_REDIS_URL as REDIS_URL,
)
from tests.production_support import (
    celery_worker_env,
    database_or_sqlite,
    redis_or_skip,
    spawn_celery_worker,
    stop_group,
)
from tests.worker_support import api, make_settings, session_factory, tile_fused, upload, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.fixture
def database_url(tmp_path: Path) -> Iterator[str]:
    """A fresh PostgreSQL database (a shared SQLite file when PostgreSQL is down)."""
    with database_or_sqlite(tmp_path) as url:
        yield url


@pytest.fixture
def celery_env(tmp_path: Path, database_url: str) -> Iterator[dict[str, Any]]:
    redis_client = redis_or_skip(REDIS_URL)
    queue = f"fleetmap-test-{uuid.uuid4().hex[:10]}"
    settings = make_settings(
        tmp_path, broker_url=REDIS_URL, fusion_queue=queue, database_url=database_url, fuse_debounce_s=1.0
    )
    log_path = tmp_path / "worker.log"
    with api(settings) as client:  # migrates the database before the worker starts
        worker = spawn_celery_worker(celery_worker_env(settings, REDIS_URL), log_path)
        try:
            yield {"client": client, "settings": settings, "worker": worker, "log": log_path}
        finally:
            stop_group(worker)
            redis_client.delete(queue, f"_kombu.binding.{queue}")


def _wait_job(env: dict[str, Any], job_id: str) -> dict[str, Any]:
    client = env["client"]

    def finished() -> dict[str, Any] | None:
        assert env["worker"].poll() is None, env["log"].read_text()[-4000:]
        body = client.get(f"/v1/jobs/{job_id}").json()
        return body if body["state"] in ("succeeded", "failed") else None

    try:
        job = wait_for(finished, 300, f"job {job_id}", interval_s=0.5)
    except AssertionError:
        raise AssertionError(env["log"].read_text()[-4000:]) from None
    assert job["state"] == "succeeded", (job, env["log"].read_text()[-4000:])
    return job


def test_celery_worker_fuses_jobs_sent_by_task_name(celery_env: dict[str, Any]) -> None:
    client = celery_env["client"]
    for seq in range(2):
        upload(client, "veh-7/celery", seq, [10.0 + 2 * seq, 10.0, 0.0], agent="veh-7")
    accepted = client.post("/v1/tiles/0/0/fuse")
    assert accepted.status_code == 202
    job = _wait_job(celery_env, accepted.json()["job_id"])
    assert job["kind"] == "align" and job["metrics"]["submaps"] == 2
    tile = wait_for(tile_fused(client, 0, 0, 1), 300, "tile (0, 0) reconstructed", interval_s=0.5)
    assert tile["version"] == 1 and client.get(f"/v1/jobs/{tile['job_id']}").json()["kind"] == "reconstruct"
    assert client.get("/v1/tiles/0/0/mesh", params={"format": "glb"}).status_code == 200

    # A job whose broker message was lost is sent again by the sweeper and then fused.
    upload(client, "veh-7/celery", 2, [14.0, 10.0, 0.0], agent="veh-7")
    factory = session_factory(client.app)
    settings = celery_env["settings"]
    original = scheduler.enqueue
    scheduler.enqueue = lambda *_: False  # type: ignore[assignment]
    try:
        with factory() as db:
            lost = scheduler.request_fusion(db, 0, 0, settings=settings)
    finally:
        scheduler.enqueue = original  # type: ignore[assignment]
    with factory() as db:
        enqueued_at = db.get(FusionJob, lost.id).enqueued_at
        later = enqueued_at + timedelta(seconds=settings.fuse_requeue_s + 1)
        assert scheduler.tick(db, later, settings).requeued_jobs == [lost.id]
    job = _wait_job(celery_env, lost.id)
    assert job["metrics"]["submaps"] == 3
    tile = wait_for(tile_fused(client, 0, 0, 2), 300, "tile (0, 0) fused again", interval_s=0.5)
    assert tile["version"] == 2
