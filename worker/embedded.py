"""The embedded fusion worker: ``fleetmap serve`` without a broker is a complete service.

The API process spawns ``python -m worker.main --embedded`` (:class:`EmbeddedWorkerProcess`), a child
that polls the database for queued fusion jobs and runs them with the same job runner as the Celery
task. Fusion (torch) therefore never runs in the API process. The child exits when asked to
(SIGTERM: the running job goes back to ``queued``) or when its parent dies.

This module is torch-free at import time.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from types import FrameType

from sqlalchemy import select

from service.settings import Settings

log = logging.getLogger(__name__)

POLL_INTERVAL_S = 1.0
SKIP_S = 30.0  # a job whose tile is leased elsewhere is not retried for this long
RESTART_BACKOFF_S = 5.0


def settings_env(settings: Settings) -> dict[str, str]:
    """``FLEETMAP_*`` variables that reproduce ``settings`` in a child process."""
    env = {}
    for name, value in settings.model_dump().items():
        if value is None:
            continue
        text = str(value).lower() if isinstance(value, bool) else str(value)
        env[f"FLEETMAP_{name.upper()}"] = text
    return env


class EmbeddedWorkerProcess:
    """Owns the embedded worker child process of one API process."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.process: subprocess.Popen[bytes] | None = None
        self._started_at = 0.0
        self._lock = threading.Lock()
        self._stopping = False

    def start(self) -> None:
        with self._lock:
            env = {**os.environ, **settings_env(self.settings)}
            self.process = subprocess.Popen([sys.executable, "-m", "worker.main", "--embedded"], env=env)
            self._started_at = time.monotonic()
            log.info("embedded fusion worker started (pid %d)", self.process.pid)

    def ensure_running(self) -> None:
        """Restart the child if it died (e.g. killed for memory); its job is reclaimed by the sweeper."""
        if self._stopping or self.process is None or self.process.poll() is None:
            return
        if time.monotonic() - self._started_at < RESTART_BACKOFF_S:
            return
        log.error("embedded fusion worker exited with %s; restarting it", self.process.returncode)
        self.start()

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM the child (its running job goes back to queued), SIGKILL after ``timeout``."""
        self._stopping = True
        with self._lock:
            process = self.process
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            log.warning("embedded fusion worker did not stop in %.0f s; killing it", timeout)
            process.kill()
            process.wait(10)


# ----------------------------------------------------------------------------------- the child process


def _raise_shutdown(_signum: int, _frame: FrameType | None) -> None:
    from worker.jobs import WorkerShutdown

    raise WorkerShutdown()


def next_queued_job(settings: Settings, skip: dict[str, float]) -> str | None:
    """The next queued job not skipped recently: home tiles of submaps first, then the oldest."""
    from service.models import FusionJob, JobState
    from service.scheduler import owns_submaps
    from worker.jobs import _session_factory

    now = time.monotonic()
    with _session_factory(settings.resolved_database_url)() as db:
        ids = db.execute(
            select(FusionJob.id)
            .where(FusionJob.state == JobState.queued.value)
            .order_by(owns_submaps(FusionJob.tile_i, FusionJob.tile_j).desc(), FusionJob.created_at)
            .limit(len(skip) + 1)
        ).scalars()
        return next((job_id for job_id in ids if skip.get(job_id, 0.0) < now), None)


def run_embedded(settings: Settings, max_jobs: int | None = None) -> int:
    """Poll for queued jobs and run them until SIGTERM/SIGINT or the parent dies; returns an exit code."""
    from worker.jobs import TransientJobError, WorkerShutdown, run_fusion_job

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
            if outcome == "skipped":
                skip[job_id] = time.monotonic() + SKIP_S
            else:
                done += 1
            skip = {k: v for k, v in skip.items() if v > time.monotonic()}
    except WorkerShutdown:
        log.info("embedded fusion worker stopping")
    return 0
