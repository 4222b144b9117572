"""The one fusion job runner, used by the Celery task and by the embedded worker.

A job runs under a *lease* on its tile, taken with one conditional UPDATE (``lease_until IS NULL OR
lease_until < now``; rowcount 1 = ours) and renewed by a heartbeat thread and by progress callbacks,
so at most one fusion of a tile runs at a time and a dead worker's tile is reclaimed by the sweeper
(service/schedule.py). Every write after the fusion checks that the lease is still ours.

It is idempotent: a job that already finished is ignored, and a job whose inputs (submaps, their
initial poses, the fusion config) equal the latest version's finishes without a new version.
Results land in ONE transaction: the new tile version, the refined poses of the tile's home submaps,
the tile state (``fused``, or ``dirty`` when uploads arrived during the fusion) and the job.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timedelta
from functools import lru_cache
from typing import Any

from sqlalchemy import func, or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from fusion.errors import FusionLibraryError
from fusion.types import FusionResult, ProgressEvent
from service.settings import Settings, get_settings
from service.store.blobs import BlobStore, blob_store_from_url
from service.store.db import engine_from_settings, make_sessionmaker
from service.store.models import FusionJob, JobState, Tile, TileState, TileVersion, utcnow
from worker import results
from worker.inputs import TileInputs, load_meshes, plan_tile

log = logging.getLogger(__name__)

PROGRESS_INTERVAL_S = 0.5  # at most ~2 progress writes per second
TRAIN_SHARE = 0.9  # progress share of training; extraction gets the rest


class LeaseLost(Exception):
    """Another worker took this tile's lease (ours expired); this run must not write results."""


class WorkerShutdown(BaseException):
    """Raised in a worker that was asked to stop: the job goes back to ``queued``."""


class TransientJobError(Exception):
    """A database, broker or storage hiccup: the job was put back to ``queued`` and may be retried."""


def is_transient(exc: BaseException) -> bool:
    """Errors worth a retry with backoff (connections), as opposed to fusion errors (not retried)."""
    from sqlalchemy.exc import InterfaceError, OperationalError

    if isinstance(exc, OperationalError | InterfaceError | ConnectionError | TimeoutError):
        return True
    try:
        from redis.exceptions import ConnectionError as RedisConnectionError
        from redis.exceptions import TimeoutError as RedisTimeoutError
    except ImportError:
        return False
    return isinstance(exc, RedisConnectionError | RedisTimeoutError)


def worker_identity() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


@lru_cache(maxsize=4)
def _session_factory(database_url: str) -> sessionmaker[Session]:
    settings = get_settings().model_copy(update={"database_url": database_url})
    return make_sessionmaker(engine_from_settings(settings))


@dataclass
class Claim:
    """A job this process holds the tile lease for."""

    job_id: str
    i: int
    j: int
    owner: str
    generation: int  # the tile's dirty_generation when the lease was taken
    started_at: datetime
    lease_s: float


def _lease_free(now: datetime, owner: str) -> Any:
    return or_(Tile.lease_until.is_(None), Tile.lease_until < now, Tile.lease_owner == owner)


def claim_job(db: Session, job_id: str, owner: str, settings: Settings) -> Claim | None:
    """Take the lease of the job's tile and mark tile ``fusing`` / job ``running``. None: not ours to run."""
    job = db.get(FusionJob, job_id)
    if job is None:
        log.warning("fusion job %s does not exist; ignoring it", job_id)
        return None
    if job.state not in (JobState.queued.value, JobState.running.value):
        log.info("fusion job %s is already %s; nothing to do", job_id, job.state)
        return None
    now = utcnow()
    tile = db.get(Tile, (job.tile_i, job.tile_j))
    if tile is None or tile.job_id != job_id:
        job.state, job.finished_at = JobState.failed.value, now
        job.error = "superseded: the tile was scheduled again by another job"
        db.commit()
        return None
    result = db.execute(
        update(Tile)
        .where(Tile.i == job.tile_i, Tile.j == job.tile_j, Tile.job_id == job_id, _lease_free(now, owner))
        .values(
            state=TileState.fusing.value,
            lease_owner=owner,
            lease_until=now + timedelta(seconds=settings.lease_s),
            progress=0.0,
            dirty_since=None,  # uploads from now on are not covered by this fusion
            updated_at=now,
        )
        .execution_options(synchronize_session=False)
    )
    if result.rowcount != 1:  # type: ignore[attr-defined]
        db.rollback()
        log.info("tile (%d, %d) is leased by another worker; job %s waits", job.tile_i, job.tile_j, job_id)
        return None
    db.refresh(tile)
    job.state, job.progress, job.generation = JobState.running.value, 0.0, tile.dirty_generation
    job.started_at = job.started_at or now
    job.attempts += 1
    claim = Claim(job_id, job.tile_i, job.tile_j, owner, tile.dirty_generation, now, settings.lease_s)
    db.commit()
    return claim


class LeaseKeeper:
    """Renews the lease every third of its length and records throttled progress.

    Runs a heartbeat thread (so long stages without progress callbacks keep the lease) and is the
    fusion's progress callback; raises :class:`LeaseLost` in the fusion when the lease was taken away.
    """

    def __init__(self, factory: sessionmaker[Session], claim: Claim) -> None:
        self.factory, self.claim = factory, claim
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._last_write = 0.0
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._beat, name="fleetmap-lease", daemon=True)

    def __enter__(self) -> LeaseKeeper:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def _beat(self) -> None:
        interval = max(0.5, self.claim.lease_s / 3)
        while not self._stop.wait(interval):
            try:
                self.renew()
            except Exception as exc:  # a DB hiccup: try again next beat, the lease has slack
                log.warning("lease renewal of tile (%d, %d) failed: %s", self.claim.i, self.claim.j, exc)

    def renew(self, progress: float | None = None) -> None:
        """Extend the lease (and record ``progress`` in [0, 1]); sets ``lost`` if it is not ours."""
        c = self.claim
        now = utcnow()
        values: dict[str, Any] = {"lease_until": now + timedelta(seconds=c.lease_s)}
        if progress is not None:
            values["progress"] = progress
        with self._lock, self.factory() as db:
            result = db.execute(
                update(Tile)
                .where(Tile.i == c.i, Tile.j == c.j, Tile.lease_owner == c.owner)
                .values(**values)
                .execution_options(synchronize_session=False)
            )
            if result.rowcount != 1:  # type: ignore[attr-defined]
                self.lost.set()
            elif progress is not None:
                db.execute(update(FusionJob).where(FusionJob.id == c.job_id).values(progress=progress))
            db.commit()

    def __call__(self, event: ProgressEvent) -> None:
        if self.lost.is_set():
            raise LeaseLost(f"lease of tile ({self.claim.i}, {self.claim.j}) lost")
        now = time.monotonic()
        if now - self._last_write < PROGRESS_INTERVAL_S:
            return
        self._last_write = now
        fraction = event.iteration / max(1, event.total)
        if event.stage == "train":
            progress = TRAIN_SHARE * fraction
        else:
            progress = TRAIN_SHARE + (1 - TRAIN_SHARE) * fraction
        self.renew(min(1.0, max(0.0, progress)))


def _error_message(exc: BaseException) -> str:
    from celery.exceptions import SoftTimeLimitExceeded

    if isinstance(exc, SoftTimeLimitExceeded):
        return "fusion exceeded its time limit"
    if isinstance(exc, FusionLibraryError):
        return f"{exc.code}: {exc.message}"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def _release(factory: sessionmaker[Session], claim: Claim, *, error: str | None) -> None:
    """Give the lease back: job ``failed`` and tile ``failed`` with ``error``, or both back to ``queued``."""
    now = utcnow()
    tile_state = TileState.failed.value if error else TileState.queued.value
    with factory() as db:
        result = db.execute(
            update(Tile)
            .where(Tile.i == claim.i, Tile.j == claim.j, Tile.lease_owner == claim.owner)
            .values(
                state=tile_state,
                lease_owner=None,
                lease_until=None,
                progress=0.0,
                dirty_since=func.coalesce(Tile.dirty_since, results._at(claim.started_at)),
                updated_at=now,
                **({"last_error": error} if error else {}),
            )
            .execution_options(synchronize_session=False)
        )
        if result.rowcount != 1:  # type: ignore[attr-defined]
            db.rollback()
            return
        values: dict[str, Any] = {"progress": 0.0}
        if error:
            values.update(state=JobState.failed.value, error=error, finished_at=now)
        else:
            values.update(state=JobState.queued.value, enqueued_at=now)
        db.execute(update(FusionJob).where(FusionJob.id == claim.job_id).values(**values))
        db.commit()


def _observe(seconds: float, outcome: str) -> None:
    try:
        from service.telemetry import observe_fusion_duration
    except ImportError:
        return
    observe_fusion_duration(seconds, outcome)


def _fuse(inputs: TileInputs, keeper: LeaseKeeper) -> FusionResult:
    from fusion.reconstruct import fuse_tile  # torch: imported in the worker process only

    threads = get_settings().torch_threads  # FLEETMAP_TORCH_THREADS: leave cores to a co-located API
    if threads:
        import torch

        torch.set_num_threads(threads)
    return fuse_tile(
        inputs.submaps, inputs.tile, inputs.config, progress=keeper, border_pins=inputs.border_pins or None
    )


def run_fusion_job(
    job_id: str,
    settings: Settings | None = None,
    *,
    session_factory: sessionmaker[Session] | None = None,
    blob_store: BlobStore | None = None,
) -> str:
    """Run fusion job ``job_id`` to its end; returns the outcome.

    Outcomes: ``succeeded`` (new tile version), ``reused`` (inputs unchanged since the latest
    version), ``failed`` (job and tile failed, previous version still served), ``skipped`` (finished
    already, or the tile is leased by another worker), ``lost`` (the lease was taken away).
    Raises :class:`TransientJobError` after putting the job back to ``queued`` on a transient error,
    and re-raises :class:`WorkerShutdown` likewise.
    """
    settings = settings or get_settings()
    factory = session_factory or _session_factory(settings.resolved_database_url)
    blobs = blob_store or blob_store_from_url(settings.resolved_blob_url)
    owner = f"{worker_identity()}:{job_id}"
    with factory() as db:
        claim = claim_job(db, job_id, owner, settings)
    if claim is None:
        return "skipped"
    started = time.monotonic()
    try:
        with LeaseKeeper(factory, claim) as keeper:
            with factory() as db:
                inputs = plan_tile(db, settings, claim.i, claim.j)
                latest = db.execute(
                    select(TileVersion.input_fingerprint)
                    .where(TileVersion.tile_i == claim.i, TileVersion.tile_j == claim.j)
                    .order_by(TileVersion.version.desc())
                    .limit(1)
                ).scalar_one_or_none()
                unchanged = latest == inputs.fingerprint
                if not unchanged:
                    if not inputs.rows:
                        raise ValueError("the tile holds no submap")
                    load_meshes(db, blobs, settings, inputs)
            if unchanged:
                return results.commit_reused(factory, claim, inputs)
            log.info("fusing tile (%d, %d): %d submaps, job %s", claim.i, claim.j, len(inputs.rows), job_id)
            result = _fuse(inputs, keeper)
            if keeper.lost.is_set():
                raise LeaseLost(f"lease of tile ({claim.i}, {claim.j}) lost")
            blob_ids = results.store_blobs(blobs, result)
            outcome = results.commit_success(
                factory, claim, inputs, result, blob_ids, time.monotonic() - started
            )
    except LeaseLost as exc:
        log.warning("job %s: %s; another worker re-runs it", job_id, exc)
        return "lost"
    except WorkerShutdown:
        log.warning("job %s interrupted by shutdown; back to queued", job_id)
        _release(factory, claim, error=None)
        raise
    except Exception as exc:
        if is_transient(exc):
            log.warning("job %s: transient error %s; back to queued", job_id, exc)
            try:
                _release(factory, claim, error=None)
            except Exception as release_exc:  # the sweeper reclaims the lease when it expires
                log.warning("job %s: could not release the lease: %s", job_id, release_exc)
            raise TransientJobError(str(exc)) from exc
        message = _error_message(exc)
        log.error(
            "fusion job %s of tile (%d, %d) failed: %s", job_id, claim.i, claim.j, message, exc_info=exc
        )
        _release(factory, claim, error=message)
        _observe(time.monotonic() - started, "failed")
        return "failed"
    if outcome == "succeeded":
        _observe(time.monotonic() - started, "succeeded")
    return outcome
