"""Celery tasks of the fusion worker: ``fleetmap.fuse_tile(job_id)`` runs :func:`run_fusion_job`.

Transient errors (database or broker connections) are retried with exponential backoff; fusion
errors are not retried: the job runner already recorded them (job and tile ``failed``).
"""

from __future__ import annotations

import logging

from celery import Task

from service.broker import TASK_FUSE_TILE
from service.settings import get_settings
from worker.celery_app import app
from worker.runner import TransientJobError, run_fusion_job

log = logging.getLogger(__name__)

MAX_RETRIES = 6
RETRY_BASE_S = 2.0
RETRY_MAX_S = 120.0


def retry_countdown(retries: int) -> float:
    """Seconds before retry number ``retries + 1``: 2, 4, 8, … capped at two minutes."""
    return min(RETRY_MAX_S, RETRY_BASE_S * 2.0**retries)


@app.task(name=TASK_FUSE_TILE, bind=True, max_retries=MAX_RETRIES, acks_late=True, reject_on_worker_lost=True)
def fuse_tile(self: Task, job_id: str) -> str:
    """Fuse the tile of fusion job ``job_id``; returns the job runner's outcome."""
    try:
        return run_fusion_job(job_id, get_settings())
    except TransientJobError as exc:
        countdown = retry_countdown(self.request.retries)
        log.warning("job %s: transient error (%s); retry in %.0f s", job_id, exc, countdown)
        raise self.retry(exc=exc, countdown=countdown) from exc
