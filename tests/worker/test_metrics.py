"""The worker's exporter in one process (the embedded worker, Celery solo/threads): served over HTTP on
127.0.0.1, and a port already taken leaves the worker running without it."""

from __future__ import annotations

import socket
from datetime import timedelta

import httpx

from fusion.errors import MeshValidationError
from service.store.models import utcnow
from worker import metrics


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def test_the_exporter_serves_the_worker_series_and_survives_a_taken_port() -> None:
    now = utcnow()
    metrics.job_started("align", now - timedelta(seconds=3), now)
    metrics.job_finished("align", "failed", 1.5, metrics.error_code(MeshValidationError("bad", code="bad_ply")))
    metrics.submaps_fused([now - timedelta(seconds=40)], now)
    port = _free_port()
    assert metrics.serve(port, addr="127.0.0.1")
    text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5).text
    assert 'fleetmap_worker_job_duration_seconds_count{kind="align",outcome="failed"}' in text
    assert 'fleetmap_worker_queue_wait_seconds_count{kind="align"}' in text
    assert 'fleetmap_worker_job_failures_total{code="bad_ply",kind="align"}' in text
    assert "fleetmap_worker_upload_to_fused_seconds_count" in text
    assert not metrics.serve(port, addr="127.0.0.1")  # taken: logged, no exception


def test_error_codes_are_bounded() -> None:
    assert metrics.error_code(ValueError("the tile holds no aligned submap")) == "internal_error"
    assert metrics.error_code(MemoryError()) == "out_of_memory"
    assert metrics.error_code(MeshValidationError("x")) == "invalid_mesh"
