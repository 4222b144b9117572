"""The lease a job runs under: taken on the job's tile with one conditional UPDATE, renewed by a
heartbeat thread and by progress callbacks, given back on success, failure or shutdown. At most one
fusion of a tile runs at a time; a dead worker's tile is reclaimed by the sweeper (service.schedule).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import update
from sqlalchemy.orm import Session, sessionmaker

from fusion.types import ProgressEvent
from service.settings import Settings
from service.store import tiles
from service.store.models import FusionJob, JobState, Tile, utcnow

log = logging.getLogger(__name__)

PROGRESS_INTERVAL_S = 0.5  # at most ~2 progress writes per second
TRAIN_SHARE = 0.9  # progress share of training; extraction gets the rest


class LeaseLost(Exception):
    """Another worker took this tile's lease (ours expired); this run must not write results."""


@dataclass
class Claim:
    """A job this process holds the tile leases for: its tile (reconstruct) or its region's (align)."""

    job_id: str
    kind: str
    tiles: list[tuple[int, int]]
    owner: str
    generation: int  # the (first) tile's dirty_generation when the lease was taken
    started_at: datetime
    lease_s: float
    queued_since: datetime | None = None  # the job's enqueued_at (else created_at) when it was claimed
    realign: bool = False  # align: a joint re-alignment of the region (``FusionJob.realign``)

    @property
    def i(self) -> int:
        return self.tiles[0][0]

    @property
    def j(self) -> int:
        return self.tiles[0][1]


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
    queued_since = job.enqueued_at or job.created_at
    keys = [(int(i), int(j)) for i, j in (job.tiles or [[job.tile_i, job.tile_j]])]
    rows = [db.get(Tile, key) for key in keys]
    if any(tile is None or tile.job_id != job_id for tile in rows):
        job.state, job.finished_at = JobState.failed.value, now
        job.error = "superseded: the tile was scheduled again by another job"
        db.commit()
        return None
    for i, j in keys:
        if not tiles.take_lease(db, i, j, job_id=job_id, owner=owner, now=now, lease_s=settings.lease_s):
            db.rollback()
            log.info("tile (%d, %d) is leased by another worker; job %s waits", i, j, job_id)
            return None
    first = rows[0]
    assert first is not None
    db.refresh(first)
    job.state, job.progress, job.generation = JobState.running.value, 0.0, first.dirty_generation
    job.started_at = job.started_at or now
    job.attempts += 1
    claim = Claim(job_id, job.kind, keys, owner, first.dirty_generation, now, settings.lease_s, queued_since,
                  bool(job.realign))
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
                log.warning("lease renewal of job %s failed: %s", self.claim.job_id, exc)

    def renew(self, progress: float | None = None) -> None:
        """Extend the lease (and record ``progress`` in [0, 1]); sets ``lost`` if it is not ours."""
        c = self.claim
        with self._lock, self.factory() as db:
            now = utcnow()
            renewed = [
                tiles.renew_lease(db, i, j, owner=c.owner, now=now, lease_s=c.lease_s, progress=progress)
                for i, j in c.tiles
            ]
            if not all(renewed):
                self.lost.set()
            elif progress is not None:
                db.execute(update(FusionJob).where(FusionJob.id == c.job_id).values(progress=progress))
            db.commit()

    def __call__(self, event: ProgressEvent) -> None:
        if self.lost.is_set():
            raise LeaseLost(f"lease of job {self.claim.job_id} on tile(s) {self.claim.tiles} lost")
        now = time.monotonic()
        if now - self._last_write < PROGRESS_INTERVAL_S:
            return
        self._last_write = now
        fraction = event.iteration / max(1, event.total)
        if event.stage == "align":  # an alignment job has no extraction
            progress = fraction
        elif event.stage == "train":
            progress = TRAIN_SHARE * fraction
        else:
            progress = TRAIN_SHARE + (1 - TRAIN_SHARE) * fraction
        self.renew(min(1.0, max(0.0, progress)))


def release(factory: sessionmaker[Session], claim: Claim, *, error: str | None) -> None:
    """Give the lease back: job ``failed`` and tile ``failed`` with ``error``, or both back to ``queued``.

    A job handed back without an error (worker shutdown, transient outage) gets its attempt back:
    ``attempts`` counts the runs that failed or whose worker died, which the sweeper caps.
    """
    now = utcnow()
    with factory() as db:
        released = [
            tiles.release_lease(db, i, j, owner=claim.owner, started_at=claim.started_at, now=now, error=error)
            for i, j in claim.tiles
        ]
        if not any(released):
            db.rollback()
            return
        values: dict[str, Any] = {"progress": 0.0}
        if error:
            values.update(state=JobState.failed.value, error=error, finished_at=now)
        else:
            values.update(state=JobState.queued.value, enqueued_at=now, attempts=FusionJob.attempts - 1)
        db.execute(update(FusionJob).where(FusionJob.id == claim.job_id).values(**values))
        db.commit()
