"""The embedded fusion worker (``python -m worker.main --embedded``), the child process that
``service.embedded`` starts: it polls the database for queued fusion jobs and runs them with the same
job runner as the Celery task, until SIGTERM/SIGINT (the running job goes back to ``queued``) or its
parent dies.
"""

from __future__ import annotations

import logging
import os
import signal
import time
from types import FrameType

from sqlalchemy import select

from service.settings import Settings
from service.store.models import FusionJob, JobKind, JobState
from worker.runner import Outcome, TransientJobError, WorkerShutdown, factory_for, run_fusion_job

log = logging.getLogger(__name__)

POLL_INTERVAL_S = 1.0
SKIP_S = 30.0  # a job whose tile is leased elsewhere is not retried for this long


def _raise_shutdown(_signum: int, _frame: FrameType | None) -> None:
    raise WorkerShutdown()


def next_queued_job(settings: Settings, skip: dict[str, float]) -> str | None:
    """The next queued job not skipped recently: alignments first (their tiles wait), then the oldest."""
    now = time.monotonic()
    with factory_for(settings.resolved_database_url)() as db:
        ids = db.execute(
            select(FusionJob.id)
            .where(FusionJob.state == JobState.queued.value)
            .order_by((FusionJob.kind == JobKind.align.value).desc(), FusionJob.created_at)
            .limit(len(skip) + 1)
        ).scalars()
        return next((job_id for job_id in ids if skip.get(job_id, 0.0) < now), None)


def run_embedded(settings: Settings, max_jobs: int | None = None) -> int:
    """Poll for queued jobs and run them until SIGTERM/SIGINT or the parent dies; returns an exit code."""
    parent = os.getppid()
    signal.signal(signal.SIGTERM, _raise_shutdown)
    signal.signal(signal.SIGINT, _raise_shutdown)
    skip: dict[str, float] = {}
    done = 0
    backoff = POLL_INTERVAL_S
    log.info("embedded fusion worker polling %s", settings.resolved_database_url.split("@")[-1])
    try:
        while max_jobs is None or done < max_jobs:
            if os.getppid() != parent:
                log.warning("parent process gone; embedded worker exits")
                return 0
            try:
                job_id = next_queued_job(settings, skip)
                if job_id is None:
                    time.sleep(POLL_INTERVAL_S)
                    continue
                outcome = run_fusion_job(job_id, settings)
                backoff = POLL_INTERVAL_S
            except TransientJobError as exc:
                log.warning("transient error (%s); retrying in %.0f s", exc, backoff)
                time.sleep(backoff)
                backoff = min(60.0, backoff * 2)
                continue
            if outcome is Outcome.skipped:
                skip[job_id] = time.monotonic() + SKIP_S
            else:
                done += 1
            skip = {k: v for k, v in skip.items() if v > time.monotonic()}
    except WorkerShutdown:
        log.info("embedded fusion worker stopping")
    return 0
