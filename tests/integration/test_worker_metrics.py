"""A real ``fleetmap worker --metrics-port N`` (Celery, prefork: the multiprocess exporter) fuses a tile
with the tiny config; its own ``/metrics`` endpoint, scraped over HTTP on 127.0.0.1 while and after the
jobs run, shows the job durations, queue waits and upload → fused latency of what it did.

Needs the local Redis and PostgreSQL like ``test_worker_celery.py`` (a shared SQLite file when
PostgreSQL is down); skipped only when Redis is unreachable.
"""

from __future__ import annotations

import socket
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

# the same helpers as test_worker_celery (a shared import list, not a repeat; duplicates)
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
from tests.worker_support import api, make_settings, upload, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of a scrape: (name, sorted labels) → value."""
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def _value(samples: dict[tuple[str, tuple[tuple[str, str], ...]], float], name: str, **labels: str) -> float:
    """Sum of the samples of ``name`` whose labels include ``labels``."""
    return sum(v for (n, ls), v in samples.items() if n == name and set(labels.items()) <= set(ls))


@pytest.fixture
def worker_env(tmp_path: Path) -> Iterator[dict[str, Any]]:
    """The API (in process; it migrates first) and a Celery worker process with a metrics port."""
    redis_client = redis_or_skip(REDIS_URL)
    queue = f"fleetmap-test-{uuid.uuid4().hex[:10]}"
    port = _free_port()
    with database_or_sqlite(tmp_path) as database_url:
        settings = make_settings(tmp_path, broker_url=REDIS_URL, fusion_queue=queue, database_url=database_url)
        env = celery_worker_env(settings, REDIS_URL, drop=("FLEETMAP_", "PROMETHEUS_"), FLEETMAP_TORCH_THREADS="1")
        log_path = tmp_path / "worker.log"
        with api(settings) as client:
            worker = spawn_celery_worker(env, log_path, "--metrics-port", str(port))
            try:
                yield {"client": client, "proc": worker, "log": log_path,
                       "metrics_url": f"http://127.0.0.1:{port}/metrics"}
            finally:
                stop_group(worker)
                redis_client.delete(queue, f"_kombu.binding.{queue}")


def test_worker_exports_job_metrics_over_http(worker_env: dict[str, Any]) -> None:
    client, url = worker_env["client"], worker_env["metrics_url"]

    def log_tail() -> str:
        return worker_env["log"].read_text()[-4000:]

    def scrape() -> str | None:
        assert worker_env["proc"].poll() is None, log_tail()
        try:
            response = httpx.get(url, timeout=5)
        except httpx.HTTPError:
            return None
        return response.text if response.status_code == 200 else None

    # An idle prefork worker has no samples yet: an empty 200 answer.
    wait_for(lambda: scrape() is not None or None, 60, "the worker's metrics endpoint", interval_s=0.3)
    for seq in range(2):
        upload(client, "veh-9/metrics", seq, [10.0 + 2 * seq, 10.0, 0.0], agent="veh-9")
    accepted = client.post("/v1/tiles/0/0/fuse")
    assert accepted.status_code == 202
    first = accepted.json()["job_id"]

    scrapes_during_fusion = 0

    def fused() -> dict[str, Any] | None:
        nonlocal scrapes_during_fusion
        scrapes_during_fusion += scrape() is not None  # the exporter answers while jobs run
        tile = client.get("/v1/tiles/0/0").json()
        if tile["state"] == "failed":
            raise AssertionError((tile, log_tail()))
        return tile if tile["state"] == "fused" and tile["version"] >= 1 else None

    try:
        wait_for(fused, 300, "tile (0, 0) fused", interval_s=0.5)
    except AssertionError:
        raise AssertionError(log_tail()) from None
    assert scrapes_during_fusion >= 1
    kind = client.get(f"/v1/jobs/{first}").json()["kind"]

    text = scrape()
    assert text is not None
    samples = _samples(text)
    for job_kind in {kind, "reconstruct"}:  # the triggered job (align first when unaligned) and the tile's
        assert _value(samples, "fleetmap_worker_job_duration_seconds_count", kind=job_kind) >= 1, text
        assert _value(samples, "fleetmap_worker_queue_wait_seconds_count", kind=job_kind) >= 1, text
    assert _value(samples, "fleetmap_worker_job_duration_seconds_count", kind="reconstruct",
                  outcome="succeeded") >= 1, text
    # Both submaps entered the map with the tile's first version.
    assert _value(samples, "fleetmap_worker_upload_to_fused_seconds_count") == 2, text
    assert _value(samples, "fleetmap_worker_jobs_in_progress") == 0, text
    assert _value(samples, "fleetmap_worker_job_failures_total") == 0, text
