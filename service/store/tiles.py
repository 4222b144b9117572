"""The tile state machine: every write of a tile row's state, lease and generations is a named
transition here; the scheduler, the ingest path and the job runner call them.

States (``../shared/API.md``): ``dirty`` → ``queued`` → ``fusing`` → ``fused`` (or back to ``dirty``
when uploads arrived meanwhile, ``queued`` when the worker stopped, ``failed`` on an error);
``failed`` and ``fused`` tiles become ``dirty`` again with new submaps. A tile holding unaligned
submaps goes through its region's align job first (``queued`` → ``fusing`` while it runs), which hands
it to the tile's reconstruct job (→ ``queued``) when the poses are written, or, a re-alignment that left
the tile's surface where its mesh has it, back to ``fused`` (:func:`settle`).

Each transition is ONE conditional ``UPDATE … WHERE <expected state>``: its rowcount says whether
*this* process made it, so several API processes and workers may act at once on PostgreSQL or SQLite
without double work. A fusion runs under a *lease* (``lease_owner``, ``lease_until``); every write
after the fusion started is conditional on the lease still being ours. Generations: an upload bumps
``dirty_generation``; a fusion records the generation it started from, and the tile is ``fused`` only
if no upload arrived since. The PostgreSQL upload statement (``service.store.submaps``) performs
:func:`mark_dirty` inline in its single round trip.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, case, false, func, literal, null, or_, tuple_, update
from sqlalchemy.orm import Session
from sqlalchemy.sql.elements import ColumnElement

from service.store.db import insert_ignore
from service.store.models import Tile, TileState, UTCDateTime

BUSY_STATES = (TileState.queued.value, TileState.fusing.value)


def _at(value: datetime) -> Any:
    """A datetime literal typed like the tiles' columns (UTC on every backend)."""
    return literal(value, UTCDateTime())


def _changed(result: Any) -> bool:
    return bool(result.rowcount == 1)


def _update(i: int, j: int, *where: ColumnElement[bool]) -> Any:
    return update(Tile).where(Tile.i == i, Tile.j == j, *where).execution_options(synchronize_session=False)


def lease_expired(now: datetime) -> ColumnElement[bool]:
    """``fusing`` tiles whose worker stopped renewing its lease."""
    return and_(Tile.state == TileState.fusing.value, or_(Tile.lease_until.is_(None), Tile.lease_until < now))


# ------------------------------------------------------------------------------------- transitions


def mark_dirty(db: Session, tiles: list[tuple[int, int]], now: datetime, *, upload: bool) -> None:
    """``tiles`` hold submaps no fusion has used yet: bump their dirty generation (one UPDATE).

    ``upload``: new submaps arrived (missing tile rows are created, the debounce clock restarts);
    otherwise the submaps' poses changed elsewhere. Queued or fusing tiles keep their state: the job
    runner compares generations when it finishes (:func:`finish`).
    """
    if not tiles:
        return
    values: dict[str, Any] = {
        "dirty_generation": Tile.dirty_generation + 1,
        "dirty_since": func.coalesce(Tile.dirty_since, _at(now)),
        "state": case((Tile.state.in_(BUSY_STATES), Tile.state), else_=TileState.dirty.value),
        "updated_at": now,
    }
    if upload:
        insert_ignore(db, Tile, [{"i": i, "j": j, "state": TileState.dirty.value, "updated_at": now} for i, j in tiles])
        values["last_upload_at"] = now
    db.execute(
        update(Tile).where(tuple_(Tile.i, Tile.j).in_(tiles)).values(**values)
        .execution_options(synchronize_session=False)
    )


def queue(db: Session, i: int, j: int, *, job_id: str, condition: ColumnElement[bool], now: datetime) -> bool:
    """→ ``queued`` for job ``job_id`` if ``condition`` still holds."""
    return _changed(db.execute(
        _update(i, j, condition).values(state=TileState.queued.value, job_id=job_id, progress=0.0, updated_at=now)
    ))


def unstick(db: Session, i: int, j: int, now: datetime) -> bool:
    """A busy tile without an active job (an inconsistent row) → ``dirty``, lease dropped."""
    return _changed(db.execute(
        _update(i, j, Tile.state.in_(BUSY_STATES))
        .values(state=TileState.dirty.value, lease_owner=None, lease_until=None, updated_at=now)
    ))


def reclaim(db: Session, i: int, j: int, *, job_id: str | None, now: datetime, error: str | None) -> bool:
    """A ``fusing`` tile whose lease expired (dead worker) → ``queued`` again, or ``failed`` with
    ``error`` when its job is given up."""
    return _changed(db.execute(
        _update(i, j, Tile.job_id == job_id, lease_expired(now)).values(
            state=TileState.failed.value if error else TileState.queued.value,
            lease_owner=None, lease_until=None, progress=0.0, last_error=error, updated_at=now,
        )
    ))


def take_lease(db: Session, i: int, j: int, *, job_id: str, owner: str, now: datetime, lease_s: float) -> bool:
    """The tile of job ``job_id`` → ``fusing`` under ``owner``'s lease, if no one else holds one."""
    free = or_(Tile.lease_until.is_(None), Tile.lease_until < now, Tile.lease_owner == owner)
    return _changed(db.execute(
        _update(i, j, Tile.job_id == job_id, free).values(
            state=TileState.fusing.value,
            lease_owner=owner,
            lease_until=now + timedelta(seconds=lease_s),
            progress=0.0,
            dirty_since=None,  # uploads from now on are not covered by this fusion
            updated_at=now,
        )
    ))


def renew_lease(
    db: Session, i: int, j: int, *, owner: str, now: datetime, lease_s: float, progress: float | None = None
) -> bool:
    """Extend ``owner``'s lease (and record ``progress`` in [0, 1]); False if it is not ours any more."""
    values: dict[str, Any] = {"lease_until": now + timedelta(seconds=lease_s)}
    if progress is not None:
        values["progress"] = progress
    return _changed(db.execute(_update(i, j, Tile.lease_owner == owner).values(**values)))


def release_lease(
    db: Session, i: int, j: int, *, owner: str, started_at: datetime, now: datetime, error: str | None
) -> bool:
    """Give ``owner``'s lease back: → ``failed`` with ``error``, else → ``queued`` (run again). The
    uploads the stopped fusion would have covered stay pending (``dirty_since``)."""
    values: dict[str, Any] = {
        "state": TileState.failed.value if error else TileState.queued.value,
        "lease_owner": None,
        "lease_until": None,
        "progress": 0.0,
        "dirty_since": func.coalesce(Tile.dirty_since, _at(started_at)),
        "updated_at": now,
    }
    if error:
        values["last_error"] = error
    return _changed(db.execute(_update(i, j, Tile.lease_owner == owner).values(**values)))


def hand_over(
    db: Session, i: int, j: int, *, owner: str, job_id: str, now: datetime, field_sha256: str | None = None,
    recon_field_sha256: str | None = None, quiet: bool = False,
) -> bool:
    """An alignment finished: the tile goes from ``owner``'s lease to its reconstruct job ``job_id``
    (→ ``queued``), recording the field the alignment trained there if any (then the reconstruction field
    of the tile's earlier poses no longer is the warm start; where none was trained, e.g. a re-alignment
    by registration only, it stays the start: the poses moved by cm to dm), or ``recon_field_sha256``: that
    field carried along with the tile's surface (``fusion.field.moved_state``), ``quiet`` where the
    re-alignment brought the tile no new submap (``Tile.recon_field_carried``: its re-fusion needs fewer
    steps); False if the lease is no longer ours."""
    values: dict[str, Any] = {
        "state": TileState.queued.value, "job_id": job_id, "lease_owner": None, "lease_until": None,
        "progress": 0.0, "updated_at": now, "recon_field_carried": False,
    }
    if field_sha256 is not None:
        values.update(align_field_sha256=field_sha256, recon_field_sha256=None)
    elif recon_field_sha256 is not None:
        values.update(recon_field_sha256=recon_field_sha256, recon_field_carried=quiet)
    return _changed(db.execute(_update(i, j, Tile.lease_owner == owner).values(**values)))


def settle(db: Session, i: int, j: int, *, owner: str, now: datetime) -> bool:
    """A re-alignment left the tile's surface where its mesh has it (``fusion.placement``): from ``owner``'s
    lease back to ``fused`` with its current version, if it has one and nothing marked the tile since that
    fusion (no upload, no submap's pose changed elsewhere: the mesh was made from the poses the
    re-alignment started from); False otherwise (or when the lease is no longer ours): nothing written."""
    return _changed(db.execute(
        _update(i, j, Tile.lease_owner == owner, Tile.version > 0, Tile.dirty_generation == Tile.fused_generation)
        .values(state=TileState.fused.value, lease_owner=None, lease_until=None, progress=1.0, dirty_since=None,
                last_error=None, updated_at=now)
    ))


def finish(
    db: Session, i: int, j: int, *, owner: str, generation: int, started_at: datetime, now: datetime,
    new_version: bool, pending: bool = False, field_sha256: str | None = None,
) -> tuple[int, str] | None:
    """Release ``owner``'s lease after a successful fusion from ``generation``: → ``fused``, or
    ``dirty`` when uploads arrived since or ``pending`` submaps (still unaligned) were left out;
    ``field_sha256``: the field the reconstruction trained (the tile's next re-fusion starts from it).
    Returns ``(version, state)``; None when the lease is no longer ours (nothing written)."""
    unchanged = false() if pending else Tile.dirty_generation == generation
    values: dict[str, Any] = {
        "state": case((unchanged, TileState.fused.value), else_=TileState.dirty.value),
        "dirty_since": case((unchanged, null()), else_=func.coalesce(Tile.dirty_since, _at(started_at))),
        "fused_generation": generation,
        "lease_owner": None,
        "lease_until": None,
        "progress": 1.0,
        "last_error": None,
        "updated_at": now,
        "recon_field_carried": False,  # the carried field's re-fusion is done
    }
    if new_version:
        values.update(version=Tile.version + 1, fused_at=now)
    if field_sha256 is not None:
        values["recon_field_sha256"] = field_sha256
    row = db.execute(
        _update(i, j, Tile.lease_owner == owner).values(**values).returning(Tile.version, Tile.state)
    ).one_or_none()
    return None if row is None else (int(row[0]), str(row[1]))
