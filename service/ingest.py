"""Submap ingest: validate an upload, store its mesh blob, record it and mark its tiles dirty.

Order matters for durability and for "a rejected upload leaves nothing behind": everything is
validated first, then the blob is written and fsynced, then one transaction inserts the session,
the submap, its tile memberships and bumps the tiles' dirty generation.

Cost per upload on PostgreSQL: one transaction of three round trips (BEGIN + a pre-check SELECT, one
data-modifying CTE statement, COMMIT); the blob is written and fsynced between the pre-check and the
CTE, while the transaction holds no lock. The response is built from the prepared upload (no
re-read). Other backends (SQLite) take the portable path with the same semantics.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from datetime import datetime
from typing import Any, cast

import numpy as np
from pydantic import ValidationError
from sqlalchemy import Table, bindparam, case, func, literal, select, text, tuple_, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.exc import DBAPIError, IntegrityError
from sqlalchemy.orm import Session

from fusion.geo import geodetic_to_map, parse_origin
from fusion.labels import NUM_CLASSES
from fusion.meshio import MeshLimits, read_submap_ply
from fusion.tiles import home_tile, submap_tiles
from fusion.types import Pose, Sigma
from service.blobs import BlobStore
from service.models import (
    Base,
    DrivingSession,
    Submap,
    SubmapTile,
    Tile,
    TileState,
    UTCDateTime,
    new_id,
    utcnow,
)
from service.problems import ProblemError, validation_error
from service.schemas import UNION_TAGS, GpsPose, SubmapCreated, SubmapMeta
from service.settings import Settings

_INSERT_ATTEMPTS = 3


@dataclass
class PreparedSubmap:
    """A validated upload, ready to store. ``bbox_*``: local frame, metres; ``pose_gps``: map frame."""

    meta: SubmapMeta
    meta_json: dict[str, Any]
    mesh_data: bytes
    mesh_sha256: str
    content_sha256: str
    face_count: int
    bbox_min: list[float]
    bbox_max: list[float]
    pose_gps: Pose
    tiles: list[tuple[int, int]]
    home: tuple[int, int]


def parse_meta(raw: bytes | str) -> SubmapMeta:
    """The ``meta`` part as a validated model; 422 problem (code ``invalid_meta``) otherwise."""
    try:
        data = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        msg = f"meta is not valid JSON: {exc}"
        errors = [validation_error(["meta"], msg, "json_invalid")]
        raise ProblemError(422, msg, code="invalid_meta", errors=errors) from exc
    if not isinstance(data, dict):
        msg = "meta must be a JSON object"
        raise ProblemError(422, msg, code="invalid_meta", errors=[validation_error(["meta"], msg, "dict_type")])
    try:
        return SubmapMeta.model_validate(data)
    except ValidationError as exc:
        errors = [
            validation_error(
                ["meta", *(part for part in err["loc"] if part not in UNION_TAGS)], err["msg"], err["type"]
            )
            for err in exc.errors()
        ]
        raise ProblemError(422, "meta is invalid", code="invalid_meta", errors=errors) from exc


def map_pose_of(meta: SubmapMeta, settings: Settings) -> Pose:
    """The GPS pose local → map frame (converting a geodetic fix around the configured origin)."""
    if isinstance(meta.gps, GpsPose):
        return Pose(
            np.asarray(meta.gps.pose.t, dtype=np.float64), np.asarray(meta.gps.pose.q, dtype=np.float64)
        )
    gps = meta.gps
    return geodetic_to_map(
        gps.lat, gps.lon, gps.alt, np.asarray(gps.q, dtype=np.float64), parse_origin(settings.origin)
    )


def content_hash(meta_json: dict[str, Any], mesh_sha256: str) -> str:
    """Idempotency key: sha256 over the canonical (normalised) meta and the mesh's sha256."""
    canonical = json.dumps(meta_json, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(f"{canonical}\n{mesh_sha256}".encode()).hexdigest()


def prepare(meta: SubmapMeta, mesh_data: bytes, settings: Settings) -> PreparedSubmap:
    """Validate the mesh and compute poses, tiles and hashes (CPU-bound; no I/O)."""
    limits = MeshLimits(
        max_faces=settings.max_faces, max_coordinate_m=settings.max_coordinate_m, num_labels=NUM_CLASSES
    )
    mesh = read_submap_ply(mesh_data, limits)
    pose = map_pose_of(meta, settings)
    bbox_min = mesh.vertices.min(axis=0)
    bbox_max = mesh.vertices.max(axis=0)
    sigma = Sigma(meta.gps_sigma.trans_m, meta.gps_sigma.rot_deg)
    tiles = sorted(
        {(int(i), int(j)) for i, j in submap_tiles(bbox_min, bbox_max, pose, sigma, settings.tile_size)}
    )
    hi, hj = home_tile(mesh, pose, settings.tile_size)
    meta_json = meta.model_dump(mode="json")
    mesh_sha = hashlib.sha256(mesh_data).hexdigest()
    return PreparedSubmap(
        meta=meta,
        meta_json=meta_json,
        mesh_data=mesh_data,
        mesh_sha256=mesh_sha,
        content_sha256=content_hash(meta_json, mesh_sha),
        face_count=int(len(mesh.faces)),
        bbox_min=[float(v) for v in bbox_min],
        bbox_max=[float(v) for v in bbox_max],
        pose_gps=pose,
        tiles=tiles,
        home=(int(hi), int(hj)),
    )


def submap_tile_list(db: Session, submap_id: str) -> list[list[int]]:
    rows = db.execute(
        select(SubmapTile.i, SubmapTile.j)
        .where(SubmapTile.submap_id == submap_id)
        .order_by(SubmapTile.i, SubmapTile.j)
    ).all()
    return [[i, j] for i, j in rows]


def _created_body(prepared: PreparedSubmap, submap_id: str) -> SubmapCreated:
    return SubmapCreated(
        id=submap_id,
        session_id=prepared.meta.session_id,
        seq=prepared.meta.seq,
        tiles=[[i, j] for i, j in prepared.tiles],
        sha256=prepared.mesh_sha256,
    )


# Session owner and the stored (session_id, seq) row, if any, in one round trip (every backend).
_PRECHECK = text(
    """
    SELECT s.agent_id, m.id, m.content_sha256, m.mesh_sha256
    FROM (SELECT :sid AS sid) AS k
    LEFT JOIN sessions AS s ON s.session_id = k.sid
    LEFT JOIN submaps AS m ON m.session_id = k.sid AND m.seq = :seq
    """
)


def _precheck(db: Session, prepared: PreparedSubmap) -> SubmapCreated | None:
    """The stored body for an identical retry, None if new; 409 if the content or the session's
    agent differs (a session belongs to one agent)."""
    meta = prepared.meta
    owner, submap_id, content_sha, mesh_sha = db.execute(
        _PRECHECK, {"sid": meta.session_id, "seq": meta.seq}
    ).one()
    if submap_id is not None:
        if content_sha != prepared.content_sha256:
            raise ProblemError(
                409,
                f"submap seq {meta.seq} of session {meta.session_id!r} is already stored with different content",
                code="submap_conflict",
            )
        return SubmapCreated(
            id=submap_id,
            session_id=meta.session_id,
            seq=meta.seq,
            tiles=submap_tile_list(db, submap_id),
            sha256=mesh_sha,
        )
    _raise_if_other_owner(owner, meta)
    return None


def _raise_if_other_owner(owner: str | None, meta: SubmapMeta) -> None:
    if owner is not None and owner != meta.agent_id:
        raise ProblemError(
            409, f"session {meta.session_id!r} belongs to agent {owner!r}", code="session_agent_mismatch"
        )


def _table(model: type[Base]) -> Table:
    """The Core ``Table`` of a declarative model (SQLAlchemy types ``__table__`` as a ``FromClause``)."""
    return cast(Table, model.__table__)


def _insert_ignore(db: Session, table: type[Base], rows: list[dict[str, Any]]) -> None:
    """INSERT … ON CONFLICT DO NOTHING on either backend.

    Core executemany with bound rows: the statement compiles once and is cached (a ``.values(rows)``
    statement recompiled on every upload and was a hot spot of the ingest path).
    """
    module = postgresql if db.get_bind().dialect.name == "postgresql" else sqlite
    db.connection().execute(module.insert(_table(table)).on_conflict_do_nothing(), rows)


def mark_tiles_dirty(db: Session, tiles: list[tuple[int, int]], now: datetime) -> None:
    """Create missing tile rows and bump their dirty generation (one atomic UPDATE).

    Tiles being queued or fused keep their state: the job runner compares generations afterwards
    and makes the tile dirty again.
    """
    if not tiles:
        return
    rows = [{"i": i, "j": j, "state": TileState.dirty.value, "updated_at": now} for i, j in tiles]
    _insert_ignore(db, Tile, rows)
    active = [TileState.queued.value, TileState.fusing.value]
    db.execute(
        update(Tile)
        .where(tuple_(Tile.i, Tile.j).in_(tiles))
        .values(
            dirty_generation=Tile.dirty_generation + 1,
            dirty_since=func.coalesce(Tile.dirty_since, literal(now, UTCDateTime())),
            last_upload_at=now,
            state=case((Tile.state.in_(active), Tile.state), else_=TileState.dirty.value),
            updated_at=now,
        )
        .execution_options(synchronize_session=False)
    )


def _submap_row(prepared: PreparedSubmap, submap_id: str, now: datetime) -> dict[str, Any]:
    meta = prepared.meta
    return {
        "id": submap_id,
        "session_id": meta.session_id,
        "seq": meta.seq,
        "agent_id": meta.agent_id,
        "captured_at": meta.captured_at,
        "meta": prepared.meta_json,
        "content_sha256": prepared.content_sha256,
        "mesh_sha256": prepared.mesh_sha256,
        "mesh_bytes": len(prepared.mesh_data),
        "face_count": prepared.face_count,
        "bbox_min": prepared.bbox_min,
        "bbox_max": prepared.bbox_max,
        "pose_gps": prepared.pose_gps.to_json(),
        "gps_sigma_trans_m": meta.gps_sigma.trans_m,
        "gps_sigma_rot_deg": meta.gps_sigma.rot_deg,
        "odometry": meta.odometry.model_dump(),
        "odometry_sigma_trans_m": meta.odometry_sigma.trans_m,
        "odometry_sigma_rot_deg": meta.odometry_sigma.rot_deg,
        "home_i": prepared.home[0],
        "home_j": prepared.home[1],
        "created_at": now,
    }


def _insert_portable(db: Session, prepared: PreparedSubmap, submap_id: str, now: datetime) -> None:
    """Session, submap, memberships and tile bump with portable statements (SQLite)."""
    meta = prepared.meta
    _insert_ignore(
        db, DrivingSession, [{"session_id": meta.session_id, "agent_id": meta.agent_id, "created_at": now}]
    )
    owner = db.scalar(select(DrivingSession.agent_id).where(DrivingSession.session_id == meta.session_id))
    _raise_if_other_owner(owner, meta)
    db.execute(_table(Submap).insert(), [_submap_row(prepared, submap_id, now)])
    if prepared.tiles:
        db.execute(
            _table(SubmapTile).insert(),
            [{"submap_id": submap_id, "i": i, "j": j} for i, j in prepared.tiles],
        )
    mark_tiles_dirty(db, prepared.tiles, now)


_JSON_COLUMNS = ("meta", "bbox_min", "bbox_max", "pose_gps", "odometry")

# PostgreSQL: the whole insert in one statement. ``s`` inserts the session or, only when it belongs
# to another agent, returns that owner (DO UPDATE … WHERE sees the latest committed row, so a racing
# session creator is caught); ``m`` inserts the submap unless the owner differs or (session_id, seq)
# already exists; memberships and the tile upsert (one row per tile, in (i, j) order so concurrent
# uploads lock tiles in the same order) follow only when ``m`` inserted. Queued/fusing tiles keep
# their state (the job runner compares generations afterwards).
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


def _insert_postgres(db: Session, prepared: PreparedSubmap, submap_id: str, now: datetime) -> bool:
    """One statement; False when (session_id, seq) appeared meanwhile (a racing upload)."""
    row = _submap_row(prepared, submap_id, now)
    for key in _JSON_COLUMNS:
        row[key] = json.dumps(row[key])
    row["tile_i"] = [i for i, _ in prepared.tiles]
    row["tile_j"] = [j for _, j in prepared.tiles]
    inserted, owner = db.execute(_PG_INSERT, row).one()
    _raise_if_other_owner(owner, prepared.meta)
    return inserted is not None


def _store_once(db: Session, blobs: BlobStore, prepared: PreparedSubmap) -> tuple[SubmapCreated, bool]:
    existing = _precheck(db, prepared)
    if existing is not None:
        return existing, False
    # No lock is held yet (READ COMMITTED reads): other uploads proceed during the write and fsync.
    blobs.put(prepared.mesh_data)  # durable before the row that names it commits
    postgres = db.get_bind().dialect.name == "postgresql"
    for attempt in range(_INSERT_ATTEMPTS):
        submap_id = new_id()
        try:
            if postgres:
                if not _insert_postgres(db, prepared, submap_id, utcnow()):
                    raise _LostRace
            else:
                _insert_portable(db, prepared, submap_id, utcnow())
            db.commit()
            return _created_body(prepared, submap_id), True
        except (IntegrityError, _LostRace):
            db.rollback()
            existing = _precheck(db, prepared)
            if existing is not None:
                return existing, False
            if attempt == _INSERT_ATTEMPTS - 1:
                raise
    raise AssertionError("unreachable")


class _LostRace(Exception):
    """(session_id, seq) was inserted by a concurrent upload after the pre-check."""


def store(db: Session, blobs: BlobStore, prepared: PreparedSubmap) -> tuple[SubmapCreated, bool]:
    """Store a validated submap; returns the response body and whether it was newly created.

    Concurrent identical uploads race on ``unique(session_id, seq)``: the loser re-reads and
    answers like a retry (200) or a conflict (409), never 500. A database connection that turns out
    dead (server restart) is retried once on a fresh one: the pre-check makes the retry idempotent,
    even when the lost connection had committed (the retry then answers 200).
    """
    try:
        try:
            return _store_once(db, blobs, prepared)
        except DBAPIError as exc:
            if not exc.connection_invalidated:
                raise
            db.rollback()
        return _store_once(db, blobs, prepared)
    except BaseException:
        db.rollback()
        raise
