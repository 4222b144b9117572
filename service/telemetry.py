"""Telemetry of the service processes: structured logs and Prometheus metrics.

Logs: plain or JSON lines, every record tagged with the current request id.
Metrics: one registry, served at ``GET /metrics``. Gauges that describe the database (tiles by state,
queue depth) are refreshed at scrape time; the job runner reports fusion durations through
:func:`observe_fusion_duration`.
"""

from __future__ import annotations

import json
import logging
import sys
from contextvars import ContextVar
from datetime import UTC, datetime

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.store.models import FusionJob, JobState, Tile, TileState

request_id_var: ContextVar[str | None] = ContextVar("fleetmap_request_id", default=None)

_STANDARD = set(vars(logging.makeLogRecord({}))) | {"message", "asctime", "request_id", "color_message"}


class RequestIdFilter(logging.Filter):
    """Adds ``record.request_id`` (or ``-``) to every record."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = request_id_var.get() or "-"
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message, request_id, extras, exception."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "request_id": getattr(record, "request_id", "-"),
        }
        for key, value in vars(record).items():
            if key not in _STANDARD and not key.startswith("_"):
                entry[key] = value
        if record.exc_info:
            entry["exc_info"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


def configure_logging(level: str = "INFO", json_lines: bool = False) -> None:
    """Configure the root logger once (idempotent: replaces the handler it installed before)."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        if getattr(handler, "_fleetmap", False):
            root.removeHandler(handler)
    handler = logging.StreamHandler(sys.stderr)
    handler._fleetmap = True  # type: ignore[attr-defined]
    handler.addFilter(RequestIdFilter())
    if json_lines:
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)s %(name)s [%(request_id)s] %(message)s")
        )
    root.addHandler(handler)
    root.setLevel(level.upper())


# ------------------------------------------------------------------------------------------- metrics

REGISTRY = CollectorRegistry(auto_describe=True)

UPLOADS = Counter(
    "fleetmap_uploads_total",
    "Submap uploads by outcome (created, retry, rejected)",
    ["outcome"],
    registry=REGISTRY,
)
UPLOAD_BYTES = Counter("fleetmap_upload_bytes_total", "Bytes of accepted submap meshes", registry=REGISTRY)
REJECTIONS = Counter(
    "fleetmap_upload_rejections_total", "Rejected uploads by reason code", ["reason"], registry=REGISTRY
)
HTTP_REQUESTS = Counter(
    "fleetmap_http_requests_total",
    "HTTP requests by route and status",
    ["method", "route", "status"],
    registry=REGISTRY,
)
TILES = Gauge("fleetmap_tiles", "Tiles by state", ["state"], registry=REGISTRY)
QUEUE_DEPTH = Gauge("fleetmap_fusion_queue_depth", "Fusion jobs queued, not yet running", registry=REGISTRY)
JOBS_RUNNING = Gauge("fleetmap_fusion_jobs_running", "Fusion jobs running", registry=REGISTRY)
FUSION_DURATION = Histogram(
    "fleetmap_fusion_duration_seconds",
    "Wall time of one tile fusion",
    ["outcome"],
    buckets=(1, 5, 10, 30, 60, 120, 300, 600, 1200, 1800, 3600),
    registry=REGISTRY,
)


def observe_fusion_duration(seconds: float, outcome: str = "succeeded") -> None:
    """Record one fusion's wall time (seconds); ``outcome`` is ``succeeded`` or ``failed``."""
    FUSION_DURATION.labels(outcome=outcome).observe(seconds)


def record_rejection(reason: str) -> None:
    """Count a rejected upload under its problem code."""
    REJECTIONS.labels(reason=reason).inc()
    UPLOADS.labels(outcome="rejected").inc()


def refresh_from_db(db: Session) -> None:
    """Set the database-derived gauges."""
    counts = dict(db.execute(select(Tile.state, func.count()).group_by(Tile.state)).all())
    for state in TileState:
        TILES.labels(state=state.value).set(counts.get(state.value, 0))
    jobs = dict(
        db.execute(
            select(FusionJob.state, func.count())
            .where(FusionJob.state.in_([JobState.queued.value, JobState.running.value]))
            .group_by(FusionJob.state)
        ).all()
    )
    QUEUE_DEPTH.set(jobs.get(JobState.queued.value, 0))
    JOBS_RUNNING.set(jobs.get(JobState.running.value, 0))


def render() -> bytes:
    """The registry in the Prometheus text format."""
    return generate_latest(REGISTRY)
