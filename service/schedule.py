"""Fusion scheduling: which tile is fused when, and the sweeper that repairs lost work.

The tiles table is the source of truth (DESIGN.md, "Semantics of state"). Every transition here is
one conditional ``UPDATE … WHERE <expected state>``: its rowcount says whether *this* process made it,
so several API processes may tick at once on PostgreSQL or SQLite without double-scheduling.

- A ``dirty`` tile (or a ``failed`` one that received uploads after its failed attempt started) is
  queued once it has been quiet for ``FLEETMAP_FUSE_DEBOUNCE_S`` since its last upload, or has waited
  ``FLEETMAP_FUSE_MAX_WAIT_S`` since it became dirty: a burst of uploads gives one fusion.
- The sweeper re-enqueues jobs that stayed ``queued`` too long (a lost broker message) and puts
  ``fusing`` tiles whose lease expired (a dead worker) back to ``queued``.

This module is torch-free: with a broker, jobs are sent by task *name*; without one (embedded
deployment) the embedded worker polls the database for queued jobs, so enqueueing is a no-op.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, or_, select, tuple_, update
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.sql.elements import ColumnElement

from fusion.config import FusionConfig
from fusion.regions import Region, needs_realignment, regions
from service.broker import enqueue
from service.settings import Settings, fusion_config, get_settings
from service.store import tiles
from service.store.models import (
    FusionJob,
    JobKind,
    JobState,
    JobTrigger,
    Submap,
    SubmapTile,
    Tile,
    TileState,
    new_id,
    utcnow,
)

log = logging.getLogger(__name__)

ACTIVE_JOB_STATES = (JobState.queued.value, JobState.running.value)
# A job whose worker died this many times is failed instead of being retried forever (poison input).
MAX_ATTEMPTS = 3
TICK_BATCH = 200


@dataclass
class TickReport:
    """What one scheduler tick did (for logs and tests)."""

    scheduled: list[tuple[int, int]] = field(default_factory=list)
    requeued_jobs: list[str] = field(default_factory=list)
    reclaimed_tiles: list[tuple[int, int]] = field(default_factory=list)
    failed_jobs: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------------------------- enqueue


# ------------------------------------------------------------------------------------------ scheduling


def _due(now: datetime, settings: Settings) -> ColumnElement[bool]:
    """Tiles that need a fusion and are quiet (debounce) or have waited long enough (max wait)."""
    failed_job_generation = select(FusionJob.generation).where(FusionJob.id == Tile.job_id).scalar_subquery()
    needs_fusion = or_(
        Tile.state == TileState.dirty.value,
        and_(
            Tile.state == TileState.failed.value,
            or_(Tile.job_id.is_(None), Tile.dirty_generation > failed_job_generation),
        ),
    )
    quiet = or_(
        Tile.last_upload_at.is_(None),
        Tile.last_upload_at <= now - timedelta(seconds=settings.fuse_debounce_s),
        Tile.dirty_since <= now - timedelta(seconds=settings.fuse_max_wait_s),
    )
    return and_(needs_fusion, quiet)


def _queue_tile(
    db: Session, i: int, j: int, condition: ColumnElement[bool], trigger: str, now: datetime
) -> FusionJob | None:
    """Move tile (i, j) to ``queued`` with a new reconstruct job if ``condition`` still holds; commit."""
    job_id = new_id()
    if not tiles.queue(db, i, j, job_id=job_id, condition=condition, now=now):
        db.rollback()
        return None
    generation = db.execute(select(Tile.dirty_generation).where(Tile.i == i, Tile.j == j)).scalar_one()
    job = FusionJob(id=job_id, tile_i=i, tile_j=j, kind=JobKind.reconstruct.value, state=JobState.queued.value,
                    trigger=trigger, generation=generation, created_at=now, enqueued_at=now)
    db.add(job)
    db.commit()
    return job


def _queue_alignment(
    db: Session, region: Region, condition: ColumnElement[bool], trigger: str, now: datetime, settings: Settings
) -> FusionJob | None:
    """Move every tile of ``region`` to ``queued`` under one new align job if ``condition`` holds for
    each; commit. None (nothing written) if one of them is not ready. A region grown incrementally past
    ``realign_share`` gets a joint re-alignment instead (:func:`alignment_scope`): its job covers every tile
    of the submaps touching the region, those not in ``region`` taken when idle."""
    keys, realign = alignment_scope(db, region, fusion_config(settings))
    db.rollback()  # end the read transaction before writing (SQLite: no stale snapshot)
    job_id = new_id()
    idle = Tile.state.not_in(tiles.BUSY_STATES)
    for i, j in keys:
        if not tiles.queue(db, i, j, job_id=job_id, condition=condition if (i, j) in region.tiles else idle, now=now):
            db.rollback()
            return None
    (i0, j0) = keys[0]
    job = FusionJob(id=job_id, tile_i=i0, tile_j=j0, kind=JobKind.align.value, tiles=[list(t) for t in keys],
                    realign=realign, state=JobState.queued.value, trigger=trigger, created_at=now, enqueued_at=now)
    db.add(job)
    db.commit()
    return job


def alignment_scope(db: Session, region: Region, config: FusionConfig) -> tuple[list[tuple[int, int]], bool]:
    """The tiles an alignment of ``region`` (a region of unaligned submaps) covers, and whether it re-aligns
    them jointly: when at least ``config.realign_share`` of the sessions with a submap in the region's
    tiles are new or were aligned incrementally (``fusion.regions.needs_realignment``), every tile of those
    submaps, else the region's own tiles."""
    own = sorted(region.tiles)
    rows = db.execute(
        select(Submap.id, Submap.session_id, Submap.pose_refined.is_not(None), Submap.aligned_incrementally)
        .join(SubmapTile, SubmapTile.submap_id == Submap.id)
        .where(tuple_(SubmapTile.i, SubmapTile.j).in_(own))
        .distinct()
    ).all()
    if not any(aligned for _, _, aligned, _ in rows):
        return own, False  # nothing held: the alignment is joint already
    sessions = {session for _, session, _, _ in rows}
    incremental = {session for _, session, aligned, inc in rows if not aligned or inc}
    if not needs_realignment(len(sessions), len(incremental), config.realign_share):
        return own, False
    ids = sorted({submap_id for submap_id, _, _, _ in rows})
    keys = db.execute(select(SubmapTile.i, SubmapTile.j).where(SubmapTile.submap_id.in_(ids)).distinct()).all()
    return sorted({(int(i), int(j)) for i, j in keys} | set(own)), True


def unaligned_regions(db: Session) -> list[Region]:
    """The regions of the submaps no alignment has placed yet (``pose_refined`` null): tiles linked by
    those submaps (``fusion.regions``). Aligned submaps only join an alignment as its fixed map."""
    rows = db.execute(
        select(SubmapTile.submap_id, SubmapTile.i, SubmapTile.j)
        .join(Submap, Submap.id == SubmapTile.submap_id)
        .where(Submap.pose_refined.is_(None))
    ).all()
    tile_sets: dict[str, list[tuple[int, int]]] = {}
    for submap_id, i, j in rows:
        tile_sets.setdefault(submap_id, []).append((i, j))
    return regions(tile_sets)


def schedule_due_tiles(db: Session, now: datetime, settings: Settings) -> list[FusionJob]:
    """Queue due work; returns the jobs this process created. A region of unaligned submaps gets one
    align job once every tile of it is due (a burst over several tiles settles first); due tiles
    holding only aligned submaps get a reconstruct job each."""
    condition = _due(now, settings)
    candidates = db.execute(
        select(Tile.i, Tile.j).where(condition).order_by(Tile.dirty_since).limit(TICK_BATCH)
    ).all()
    pending = unaligned_regions(db) if candidates else []
    db.rollback()  # end the read transaction before writing (SQLite: no stale snapshot)
    due = {(int(i), int(j)) for i, j in candidates}
    jobs = []
    for region in pending:
        if due.issuperset(region.tiles):
            job = _queue_alignment(db, region, condition, JobTrigger.auto.value, now, settings)
            if job is not None:
                log.info("region %s queued for %salignment, job %s", job.tiles, "joint re-" if job.realign else "",
                         job.id)
                jobs.append(job)
        due.difference_update(region.tiles)  # waits for its alignment
    for i, j in candidates:
        if (i, j) in due and (job := _queue_tile(db, i, j, condition, JobTrigger.auto.value, now)) is not None:
            log.info("tile (%d, %d) queued for reconstruction, job %s", i, j, job.id)
            jobs.append(job)
    return jobs


def _active_job(db: Session, i: int, j: int) -> FusionJob | None:
    """The queued or running job covering tile (i, j): its tile's current job."""
    tile = db.get(Tile, (i, j))
    if tile is None or tile.job_id is None:
        return None
    job = db.get(FusionJob, tile.job_id)
    return job if job is not None and job.state in ACTIVE_JOB_STATES else None


def request_fusion(
    db: Session,
    i: int,
    j: int,
    trigger: str = JobTrigger.operator.value,
    *,
    settings: Settings | None = None,
    now: datetime | None = None,
) -> FusionJob:
    """Queue a (re-)fusion of tile (i, j) and return its job, or the job already queued or running.
    A tile holding unaligned submaps gets its region's alignment (which then reconstructs it).

    Raises ``LookupError`` if the tile does not exist. Commits.
    """
    settings = settings or get_settings()
    now = now or utcnow()
    idle = Tile.state.not_in(tiles.BUSY_STATES)
    for _ in range(3):
        if db.get(Tile, (i, j)) is None:
            raise LookupError(f"tile ({i}, {j}) does not exist")
        region = next((r for r in unaligned_regions(db) if (i, j) in r.tiles), None)
        db.rollback()
        if region is not None:
            job = _queue_alignment(db, region, idle, trigger, now, settings)
            keys = alignment_scope(db, region, fusion_config(settings))[0] if job is None else []
        else:
            job = _queue_tile(db, i, j, idle, trigger, now)
            keys = [(i, j)]
        if job is not None:
            enqueue(job.id, settings, job.kind)
            return job
        busy = [t for t in keys if _active_job(db, *t) is not None]
        active = _active_job(db, *(busy[0] if busy else (i, j)))
        if active is not None:
            db.commit()
            return active
        # Busy tile without an active job (inconsistent row): release it and try again.
        for key in keys:
            tiles.unstick(db, *key, now)
        db.commit()
    raise RuntimeError(f"could not queue tile ({i}, {j}): it keeps changing state")


# --------------------------------------------------------------------------------------------- sweeper


def _requeue_lost_messages(db: Session, now: datetime, settings: Settings) -> list[str]:
    """Jobs queued for longer than the requeue interval are sent again (broker deployments only)."""
    if settings.embedded:
        return []
    cutoff = now - timedelta(seconds=settings.fuse_requeue_s)
    stale = or_(FusionJob.enqueued_at.is_(None), FusionJob.enqueued_at < cutoff)
    waiting = and_(FusionJob.state == JobState.queued.value, stale)
    found = db.execute(select(FusionJob.id, FusionJob.kind).where(waiting).limit(TICK_BATCH)).all()
    db.rollback()
    sent = []
    for job_id, kind in found:
        result = db.execute(update(FusionJob).where(FusionJob.id == job_id, waiting).values(enqueued_at=now))
        db.commit()
        if result.rowcount == 1:  # type: ignore[attr-defined]
            log.warning("fusion job %s was not picked up in time; enqueueing it again", job_id)
            enqueue(job_id, settings, kind)
            sent.append(job_id)
    return sent


def _reclaim_expired_leases(db: Session, now: datetime, settings: Settings, report: TickReport) -> None:
    """``fusing`` tiles whose lease expired (dead worker) go back to ``queued``; their job is re-run.

    A job whose worker died ``MAX_ATTEMPTS`` times is failed instead (the tile keeps serving its
    previous version).
    """
    expired = db.execute(
        select(Tile.i, Tile.j, Tile.job_id).where(tiles.lease_expired(now)).limit(TICK_BATCH)
    ).all()
    db.rollback()
    for i, j, job_id in expired:
        job = db.get(FusionJob, job_id) if job_id else None
        give_up = job is None or job.attempts >= MAX_ATTEMPTS
        error = f"fusion worker lost {job.attempts if job else 0} time(s); giving up" if give_up else None
        if not tiles.reclaim(db, i, j, job_id=job_id, now=now, error=error):
            db.rollback()
            continue
        if job is not None:
            if give_up:
                job.state, job.error, job.finished_at = JobState.failed.value, error, now
            else:
                job.state, job.progress, job.enqueued_at = JobState.queued.value, 0.0, now
        db.commit()
        report.reclaimed_tiles.append((i, j))
        if give_up:
            log.error("tile (%d, %d): %s", i, j, error)
            if job is not None:
                report.failed_jobs.append(job.id)
        else:
            assert job is not None
            log.warning("tile (%d, %d): lease of job %s expired; re-running it", i, j, job.id)
            enqueue(job.id, settings, job.kind)
            report.requeued_jobs.append(job.id)


def tick(db: Session, now: datetime | None = None, settings: Settings | None = None) -> TickReport:
    """One scheduler pass: queue due tiles, then sweep lost messages and expired leases. Commits."""
    settings = settings or get_settings()
    now = now or utcnow()
    report = TickReport()
    _reclaim_expired_leases(db, now, settings, report)
    report.requeued_jobs.extend(_requeue_lost_messages(db, now, settings))
    for job in schedule_due_tiles(db, now, settings):
        enqueue(job.id, settings, job.kind)
        report.scheduled.extend([tuple(t) for t in job.tiles] if job.tiles else [(job.tile_i, job.tile_j)])
    return report


# ------------------------------------------------------------------------------------------ background


class BackgroundScheduler:
    """Runs :func:`tick` every ``FLEETMAP_SCHEDULER_INTERVAL_S`` in a daemon thread.

    In the embedded deployment it also owns the embedded worker child process (which imports torch,
    so the API process never does).
    """

    def __init__(self, session_factory: sessionmaker[Session], settings: Settings, spawn_worker: bool):
        self.session_factory = session_factory
        self.settings = settings
        self.spawn_worker = spawn_worker and settings.embedded
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._worker: Any = None

    def start(self) -> BackgroundScheduler:
        if self.spawn_worker:
            from service.embedded import EmbeddedWorkerProcess

            self._worker = EmbeddedWorkerProcess(self.settings)
            self._worker.start()
        self._thread = threading.Thread(target=self._run, name="fleetmap-scheduler", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                with self.session_factory() as db:
                    tick(db, utcnow(), self.settings)
            except Exception:  # keep ticking: the next pass repairs whatever this one missed
                log.exception("scheduler tick failed")
            if self._worker is not None:
                self._worker.ensure_running()
            self._stop.wait(self.settings.scheduler_interval_s)

    def stop(self, timeout: float = 30.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        if self._worker is not None:
            self._worker.stop(timeout)


def start_background(
    app: Any = None,
    *,
    settings: Settings | None = None,
    session_factory: sessionmaker[Session] | None = None,
    spawn_worker: bool = True,
) -> BackgroundScheduler:
    """Start the scheduler thread (and the embedded worker when there is no broker).

    Settings and the session factory come from the arguments, else from ``app.state.settings`` /
    ``app.state.session_factory``, else from the environment. :func:`stop_background` (called by the
    app's lifespan on shutdown) stops it.
    """
    state = getattr(app, "state", None)
    settings = settings or getattr(state, "settings", None) or get_settings()
    if session_factory is None:
        session_factory = getattr(state, "session_factory", None)
    if session_factory is None:
        from service.store.db import engine_from_settings, make_sessionmaker

        session_factory = make_sessionmaker(engine_from_settings(settings))
    background = BackgroundScheduler(session_factory, settings, spawn_worker).start()
    if state is not None:
        state.scheduler = background
    return background


def stop_background(app: Any) -> None:
    """Stop what :func:`start_background` started for ``app`` (the embedded worker's job is requeued)."""
    background = getattr(getattr(app, "state", None), "scheduler", None)
    if background is not None:
        background.stop()
        app.state.scheduler = None
