"""Storing a submap: its mesh blob, its row, its session, its tile memberships and the tiles' dirty
mark, durably and at most once per ``(session_id, seq)``.

Order matters for durability and for "a rejected upload leaves nothing behind": the upload is
validated before it gets here (``service.api.ingest``), then the blob is written and fsynced, then
one transaction inserts the session, the submap, its tile memberships and bumps the tiles' dirty
generation.

Cost per upload on PostgreSQL: one transaction of three round trips (BEGIN + a pre-check SELECT, one
data-modifying CTE statement, COMMIT); the blob is written and fsynced between the pre-check and the
CTE, while the transaction holds no lock. Other backends (SQLite) take the portable path with the
same semantics.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import bindparam, select, text
from sqlalchemy.exc import DBAPIError, IntegrityError
from sqlalchemy.orm import Session

from fusion.types import Pose, Sigma
from service.store import tiles
from service.store.blobs import BlobStore
from service.store.db import insert_ignore, is_postgres, table_of
from service.store.models import DrivingSession, Submap, SubmapTile, UTCDateTime, new_id, utcnow

_INSERT_ATTEMPTS = 3


class SubmapConflict(Exception):
    """``(session_id, seq)`` is stored with other content, or the session belongs to another agent."""

    def __init__(self, message: str, code: str) -> None:
        super().__init__(message)
        self.message, self.code = message, code


@dataclass(frozen=True)
class NewSubmap:
    """A validated upload, ready to store. ``bbox_*``: local frame, metres; ``pose_gps``: map frame;
    ``odometry``: the submap's pose in its session's odometry frame (pose JSON); ``home``: the tile of its posed
    centroid."""

    session_id: str
    seq: int
    agent_id: str
    captured_at: datetime | None
    meta_json: dict[str, Any]
    mesh_data: bytes
    mesh_sha256: str
    content_sha256: str
    face_count: int
    bbox_min: list[float]
    bbox_max: list[float]
    pose_gps: Pose
    gps_sigma: Sigma
    odometry: dict[str, Any]  # pose JSON
    odometry_sigma: Sigma
    tiles: list[tuple[int, int]]
    home: tuple[int, int]


@dataclass(frozen=True)
class StoredSubmap:
    """What the uploader is told: the submap's id, its tiles and its mesh's sha256."""

    id: str
    session_id: str
    seq: int
    tiles: list[list[int]]
    sha256: str


def submap_tile_list(db: Session, submap_id: str) -> list[list[int]]:
    rows = db.execute(
        select(SubmapTile.i, SubmapTile.j)
        .where(SubmapTile.submap_id == submap_id)
        .order_by(SubmapTile.i, SubmapTile.j)
    ).all()
    return [[i, j] for i, j in rows]


def _created(new: NewSubmap, submap_id: str) -> StoredSubmap:
    return StoredSubmap(submap_id, new.session_id, new.seq, [[i, j] for i, j in new.tiles], new.mesh_sha256)


# Session owner and the stored (session_id, seq) row, if any, in one round trip (every backend).
_PRECHECK = text(
    """
    SELECT s.agent_id, m.id, m.content_sha256, m.mesh_sha256
    FROM (SELECT :sid AS sid) AS k
    LEFT JOIN sessions AS s ON s.session_id = k.sid
    LEFT JOIN submaps AS m ON m.session_id = k.sid AND m.seq = :seq
    """
)


def _precheck(db: Session, new: NewSubmap) -> StoredSubmap | None:
    """The stored submap for an identical retry, None if new; :class:`SubmapConflict` if the content or
    the session's agent differs (a session belongs to one agent)."""
    owner, submap_id, content_sha, mesh_sha = db.execute(
        _PRECHECK, {"sid": new.session_id, "seq": new.seq}
    ).one()
    if submap_id is not None:
        if content_sha != new.content_sha256:
            raise SubmapConflict(
                f"submap seq {new.seq} of session {new.session_id!r} is already stored with different content",
                "submap_conflict",
            )
        return StoredSubmap(submap_id, new.session_id, new.seq, submap_tile_list(db, submap_id), mesh_sha)
    _raise_if_other_owner(owner, new)
    return None


def _raise_if_other_owner(owner: str | None, new: NewSubmap) -> None:
    if owner is not None and owner != new.agent_id:
        raise SubmapConflict(f"session {new.session_id!r} belongs to agent {owner!r}", "session_agent_mismatch")


def _submap_row(new: NewSubmap, submap_id: str, now: datetime) -> dict[str, Any]:
    return {
        "id": submap_id,
        "session_id": new.session_id,
        "seq": new.seq,
        "agent_id": new.agent_id,
        "captured_at": new.captured_at,
        "meta": new.meta_json,
        "content_sha256": new.content_sha256,
        "mesh_sha256": new.mesh_sha256,
        "mesh_bytes": len(new.mesh_data),
        "face_count": new.face_count,
        "bbox_min": new.bbox_min,
        "bbox_max": new.bbox_max,
        "pose_gps": new.pose_gps.to_json(),
        "gps_sigma_trans_m": new.gps_sigma.trans_m,
        "gps_sigma_rot_deg": new.gps_sigma.rot_deg,
        "odometry": new.odometry,
        "odometry_sigma_trans_m": new.odometry_sigma.trans_m,
        "odometry_sigma_rot_deg": new.odometry_sigma.rot_deg,
        "home_i": new.home[0],
        "home_j": new.home[1],
        "created_at": now,
    }


def _insert_portable(db: Session, new: NewSubmap, submap_id: str, now: datetime) -> None:
    """Session, submap, memberships and tile bump with portable statements (SQLite)."""
    insert_ignore(db, DrivingSession, [{"session_id": new.session_id, "agent_id": new.agent_id, "created_at": now}])
    owner = db.scalar(select(DrivingSession.agent_id).where(DrivingSession.session_id == new.session_id))
    _raise_if_other_owner(owner, new)
    db.execute(table_of(Submap).insert(), [_submap_row(new, submap_id, now)])
    if new.tiles:
        db.execute(table_of(SubmapTile).insert(), [{"submap_id": submap_id, "i": i, "j": j} for i, j in new.tiles])
    tiles.mark_dirty(db, new.tiles, now, upload=True)


_JSON_COLUMNS = ("meta", "bbox_min", "bbox_max", "pose_gps", "odometry")

# PostgreSQL: the whole insert in one statement. ``s`` inserts the session or, only when it belongs
# to another agent, returns that owner (DO UPDATE … WHERE sees the latest committed row, so a racing
# session creator is caught); ``m`` inserts the submap unless the owner differs or (session_id, seq)
# already exists; memberships and the tile upsert (one row per tile, in (i, j) order so concurrent
# uploads lock tiles in the same order) follow only when ``m`` inserted. ``tu`` is
# ``tiles.mark_dirty(upload=True)`` written inline, deliberately: the whole upload stays one round trip.
_PG_INSERT = text(
    """
    WITH s AS (
        INSERT INTO sessions (session_id, agent_id, created_at) VALUES (:session_id, :agent_id, :created_at)
        ON CONFLICT (session_id) DO UPDATE SET agent_id = sessions.agent_id
        WHERE sessions.agent_id <> EXCLUDED.agent_id
        RETURNING agent_id
    ), m AS (
        INSERT INTO submaps (
            id, session_id, seq, agent_id, captured_at, meta, content_sha256, mesh_sha256, mesh_bytes,
            face_count, bbox_min, bbox_max, pose_gps, gps_sigma_trans_m, gps_sigma_rot_deg, odometry,
            odometry_sigma_trans_m, odometry_sigma_rot_deg, home_i, home_j, created_at
        )
        SELECT :id, :session_id, :seq, :agent_id, :captured_at, CAST(:meta AS JSON), :content_sha256,
            :mesh_sha256, :mesh_bytes, :face_count, CAST(:bbox_min AS JSON), CAST(:bbox_max AS JSON),
            CAST(:pose_gps AS JSON), :gps_sigma_trans_m, :gps_sigma_rot_deg, CAST(:odometry AS JSON),
            :odometry_sigma_trans_m, :odometry_sigma_rot_deg, :home_i, :home_j, :created_at
        WHERE NOT EXISTS (SELECT 1 FROM s WHERE s.agent_id <> :agent_id)
        ON CONFLICT (session_id, seq) DO NOTHING
        RETURNING id
    ), t AS (
        SELECT u.i, u.j FROM unnest(CAST(:tile_i AS INTEGER[]), CAST(:tile_j AS INTEGER[])) AS u(i, j)
    ), st AS (
        INSERT INTO submap_tiles (submap_id, i, j) SELECT m.id, t.i, t.j FROM m CROSS JOIN t
    ), tu AS (
        INSERT INTO tiles (
            i, j, state, version, dirty_generation, fused_generation, dirty_since, last_upload_at,
            progress, updated_at
        )
        SELECT t.i, t.j, 'dirty', 0, 1, 0, :created_at, :created_at, 0.0, :created_at
        FROM m CROSS JOIN t ORDER BY t.i, t.j
        ON CONFLICT (i, j) DO UPDATE SET
            dirty_generation = tiles.dirty_generation + 1,
            dirty_since = COALESCE(tiles.dirty_since, EXCLUDED.dirty_since),
            last_upload_at = EXCLUDED.last_upload_at,
            state = CASE WHEN tiles.state IN ('queued', 'fusing') THEN tiles.state ELSE 'dirty' END,
            updated_at = EXCLUDED.updated_at
    )
    SELECT (SELECT id FROM m) AS id, (SELECT agent_id FROM s) AS owner
    """
).bindparams(
    bindparam("captured_at", type_=UTCDateTime()),
    bindparam("created_at", type_=UTCDateTime()),
)


def _insert_postgres(db: Session, new: NewSubmap, submap_id: str, now: datetime) -> bool:
    """One statement; False when (session_id, seq) appeared meanwhile (a racing upload)."""
    row = _submap_row(new, submap_id, now)
    for key in _JSON_COLUMNS:
        row[key] = json.dumps(row[key])
    row["tile_i"] = [i for i, _ in new.tiles]
    row["tile_j"] = [j for _, j in new.tiles]
    inserted, owner = db.execute(_PG_INSERT, row).one()
    _raise_if_other_owner(owner, new)
    return inserted is not None


def _store_once(db: Session, blobs: BlobStore, new: NewSubmap) -> tuple[StoredSubmap, bool]:
    existing = _precheck(db, new)
    if existing is not None:
        return existing, False
    # No lock is held yet (READ COMMITTED reads): other uploads proceed during the write and fsync.
    blobs.put(new.mesh_data)  # durable before the row that names it commits
    postgres = is_postgres(db)
    for attempt in range(_INSERT_ATTEMPTS):
        submap_id = new_id()
        try:
            if postgres:
                if not _insert_postgres(db, new, submap_id, utcnow()):
                    raise _LostRace
            else:
                _insert_portable(db, new, submap_id, utcnow())
            db.commit()
            return _created(new, submap_id), True
        except (IntegrityError, _LostRace):
            db.rollback()
            existing = _precheck(db, new)
            if existing is not None:
                return existing, False
            if attempt == _INSERT_ATTEMPTS - 1:
                raise
    raise AssertionError("unreachable")


class _LostRace(Exception):
    """(session_id, seq) was inserted by a concurrent upload after the pre-check."""


def store(db: Session, blobs: BlobStore, new: NewSubmap) -> tuple[StoredSubmap, bool]:
    """Store a validated submap; returns it and whether it was newly created. Raises
    :class:`SubmapConflict` (nothing stored) when ``(session_id, seq)`` holds other content or the
    session belongs to another agent.

    Concurrent identical uploads race on ``unique(session_id, seq)``: the loser re-reads and
    answers like a retry or a conflict, never an error. A database connection that turns out
    dead (server restart) is retried once on a fresh one: the pre-check makes the retry idempotent,
    even when the lost connection had committed (the retry then answers 200).
    """
    try:
        try:
            return _store_once(db, blobs, new)
        except DBAPIError as exc:
            if not exc.connection_invalidated:
                raise
            db.rollback()
        return _store_once(db, blobs, new)
    except BaseException:
        db.rollback()
        raise
