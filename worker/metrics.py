"""Prometheus metrics of a fusion worker, served by the worker itself (``fleetmap worker --metrics-port N``
or ``FLEETMAP_WORKER_METRICS_PORT``; 0: off). The API's ``GET /metrics`` is unchanged: it describes the
database (tiles by state, queue depth); these describe what the workers did.

Series (a scrape target is one worker host/process, so Prometheus' ``instance`` label tells workers apart):

- ``fleetmap_worker_job_duration_seconds{kind, outcome}`` (histogram): wall time of one run of a job,
  from its claim to its end. ``kind``: ``align`` or ``reconstruct``; ``outcome``: ``succeeded``,
  ``reused`` (inputs unchanged, no new version), ``failed``, ``lost`` (lease taken away),
  ``interrupted`` (worker shutdown) or ``transient`` (database/broker hiccup, retried).
- ``fleetmap_worker_queue_wait_seconds{kind}`` (histogram): from the job's ``enqueued_at`` (when it was
  last sent or put back to ``queued``; ``created_at`` if never sent) to its claim by this worker.
- ``fleetmap_worker_upload_to_fused_seconds`` (histogram): for every reconstruction that committed a new
  tile version, one sample per *newly included* submap: the commit time minus the submap's upload time
  (``created_at``). A submap is newly included when it was aligned (``refined_at``) after the tile's
  previous version was committed, or the tile had no version; a submap spanning two tiles gives one
  sample per tile.
- ``fleetmap_worker_job_failures_total{kind, code}`` (counter): jobs that ended ``failed``, by error
  code (the fusion library's code, e.g. ``fusion_failed``, ``invalid_mesh``; ``time_limit``,
  ``out_of_memory``, ``internal_error`` otherwise).
- ``fleetmap_worker_jobs_in_progress{kind}`` (gauge): jobs this worker runs right now.

Processes: the embedded worker and a Celery worker with the ``solo`` or ``threads`` pool record into
this process's registry and serve it. A Celery ``prefork`` pool runs jobs in child processes, so there
the exporter uses prometheus_client's multiprocess mode: :func:`enable_multiprocess` points
``PROMETHEUS_MULTIPROC_DIR`` at a fresh temporary folder of this worker before the pool forks, the
children write their samples there, and the parent serves the sum (the folder is removed at exit).
"""

from __future__ import annotations

import atexit
import logging
import os
import shutil
import tempfile
import threading
from dataclasses import dataclass
from datetime import datetime
from typing import Any

log = logging.getLogger(__name__)

MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"

DURATION_BUCKETS = (0.5, 1, 2, 5, 10, 30, 60, 120, 300, 600, 1200, 1800, 3600)
WAIT_BUCKETS = (0.1, 0.5, 1, 2, 5, 10, 30, 60, 120, 300, 600, 1800, 3600)
LATENCY_BUCKETS = (1, 5, 10, 30, 60, 120, 300, 600, 1200, 1800, 3600, 7200, 21600)


@dataclass
class _Metrics:
    registry: Any
    job_duration: Any
    queue_wait: Any
    upload_to_fused: Any
    failures: Any
    in_progress: Any


_lock = threading.Lock()
_metrics: _Metrics | None = None
_multiproc_dir: str | None = None


def _build() -> _Metrics:
    from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

    registry = CollectorRegistry(auto_describe=True)
    return _Metrics(
        registry=registry,
        job_duration=Histogram(
            "fleetmap_worker_job_duration_seconds",
            "Wall time of one run of a fusion job, by kind and outcome",
            ["kind", "outcome"],
            buckets=DURATION_BUCKETS,
            registry=registry,
        ),
        queue_wait=Histogram(
            "fleetmap_worker_queue_wait_seconds",
            "Time a fusion job waited queued (enqueued_at or created_at to claim), by kind",
            ["kind"],
            buckets=WAIT_BUCKETS,
            registry=registry,
        ),
        upload_to_fused=Histogram(
            "fleetmap_worker_upload_to_fused_seconds",
            "Upload (submap created_at) to the commit of the first tile version that includes it",
            buckets=LATENCY_BUCKETS,
            registry=registry,
        ),
        failures=Counter(
            "fleetmap_worker_job_failures",
            "Fusion jobs that ended failed, by kind and error code",
            ["kind", "code"],
            registry=registry,
        ),
        in_progress=Gauge(
            "fleetmap_worker_jobs_in_progress",
            "Fusion jobs running in this worker, by kind",
            ["kind"],
            multiprocess_mode="livesum",
            registry=registry,
        ),
    )


def _get() -> _Metrics:
    global _metrics
    with _lock:
        if _metrics is None:
            _metrics = _build()
        return _metrics


def enable_multiprocess() -> str:
    """Switch this process (and the pool children it forks later) to prometheus_client's multiprocess
    mode with a fresh, private ``PROMETHEUS_MULTIPROC_DIR``; returns the folder. Call before the pool
    forks and before any metric of this module was used."""
    global _multiproc_dir, _metrics
    path = tempfile.mkdtemp(prefix="fleetmap-worker-metrics-")
    os.environ[MULTIPROC_ENV] = path
    from prometheus_client import values

    # The value class is chosen when prometheus_client is first imported; re-choose it now that the
    # folder is set (another module may have imported prometheus_client already).
    values.ValueClass = values.get_value_class()
    with _lock:
        _metrics = None
    _multiproc_dir = path
    atexit.register(shutil.rmtree, path, True)
    return path


def process_exited(pid: int | None = None) -> None:
    """A pool child exits: drop its live gauge samples (multiprocess mode only)."""
    if _multiproc_dir is None:
        return
    from prometheus_client import multiprocess

    multiprocess.mark_process_dead(pid or os.getpid(), _multiproc_dir)


def serve(port: int, addr: str = "0.0.0.0") -> bool:
    """Serve the metrics over HTTP on ``addr:port`` from a daemon thread; False if the port is taken
    (logged: the worker keeps running without its exporter)."""
    from prometheus_client import CollectorRegistry, start_http_server

    if _multiproc_dir is not None:
        from prometheus_client import multiprocess

        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry, path=_multiproc_dir)
    else:
        registry = _get().registry
    try:
        start_http_server(port, addr=addr, registry=registry)
    except OSError as exc:
        log.error("worker metrics exporter could not listen on %s:%d: %s", addr, port, exc)
        return False
    mode = "multiprocess" if _multiproc_dir else "single process"
    log.info("worker metrics on http://%s:%d/metrics (%s)", addr, port, mode)
    return True


def error_code(exc: BaseException) -> str:
    """A short, bounded code for a job failure (the label of ``fleetmap_worker_job_failures_total``)."""
    from fusion.errors import FusionLibraryError

    if isinstance(exc, FusionLibraryError):
        return str(exc.code)
    if type(exc).__name__ == "SoftTimeLimitExceeded":
        return "time_limit"
    if isinstance(exc, MemoryError) or type(exc).__name__ == "OutOfMemoryError":
        return "out_of_memory"
    return "internal_error"


# ------------------------------------------------------------------------------- what the runner calls


def job_started(kind: str, queued_since: datetime | None, claimed_at: datetime) -> None:
    """A job was claimed: count it in progress and record its queue wait."""
    metrics = _get()
    metrics.in_progress.labels(kind=kind).inc()
    if queued_since is not None:
        metrics.queue_wait.labels(kind=kind).observe(max(0.0, (claimed_at - queued_since).total_seconds()))


def job_finished(kind: str, outcome: str, seconds: float, code: str | None = None) -> None:
    """A job's run ended with ``outcome`` after ``seconds``; ``code`` for a failed job."""
    metrics = _get()
    metrics.in_progress.labels(kind=kind).dec()
    metrics.job_duration.labels(kind=kind, outcome=outcome).observe(seconds)
    if outcome == "failed":
        metrics.failures.labels(kind=kind, code=code or "internal_error").inc()


def submaps_fused(uploaded_at: list[datetime], fused_at: datetime) -> None:
    """A new tile version includes submaps uploaded at ``uploaded_at`` for the first time."""
    histogram = _get().upload_to_fused
    for created in uploaded_at:
        histogram.observe(max(0.0, (fused_at - created).total_seconds()))
