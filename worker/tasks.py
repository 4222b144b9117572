"""Celery tasks of the fusion worker: ``fleetmap.align_region(job_id)`` and ``fleetmap.fuse_tile(job_id)``
both run :func:`run_fusion_job` (the job row says what to do; the task names let deployments route
the two kinds to different queues).

Transient errors (database or broker connections) are retried with exponential backoff; fusion
errors are not retried: the job runner already recorded them (job and tile ``failed``).
"""

from __future__ import annotations

import logging

from celery import Task

from service.broker import TASK_ALIGN_REGION, TASK_FUSE_TILE
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


def _run(task: Task, job_id: str) -> str:
    try:
        return run_fusion_job(job_id, get_settings())
    except TransientJobError as exc:
        countdown = retry_countdown(task.request.retries)
        log.warning("job %s: transient error (%s); retry in %.0f s", job_id, exc, countdown)
        raise task.retry(exc=exc, countdown=countdown) from exc


@app.task(name=TASK_FUSE_TILE, bind=True, max_retries=MAX_RETRIES, acks_late=True, reject_on_worker_lost=True)
def reconstruct_tile(self: Task, job_id: str) -> str:
    """Reconstruct the tile of fusion job ``job_id`` (poses held); returns the job runner's outcome."""
    return _run(self, job_id)


@app.task(name=TASK_ALIGN_REGION, bind=True, max_retries=MAX_RETRIES, acks_late=True, reject_on_worker_lost=True)
def align_region(self: Task, job_id: str) -> str:
    """Align the region of fusion job ``job_id``; returns the job runner's outcome."""
    return _run(self, job_id)
