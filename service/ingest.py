"""Submap ingest: validate an upload, store its mesh blob, record it and mark its tiles dirty.

Order matters for durability and for "a rejected upload leaves nothing behind": everything is
validated first, then the blob is written and fsynced, then one transaction inserts the session,
the submap, its tile memberships and bumps the tiles' dirty generation.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np
from pydantic import ValidationError
from sqlalchemy import case, func, literal, select, tuple_, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from fusion.geo import geodetic_to_map, parse_origin
from fusion.labels import NUM_CLASSES
from fusion.meshio import MeshLimits, read_submap_ply
from fusion.tiles import home_tile, submap_tiles
from fusion.types import Pose, Sigma
from service.blobs import BlobStore
from service.models import DrivingSession, Submap, SubmapTile, Tile, TileState, UTCDateTime, utcnow
from service.problems import ProblemError
from service.schemas import GpsPose, SubmapCreated, SubmapMeta
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
        raise ProblemError(422, f"meta is not valid JSON: {exc}", code="invalid_meta") from exc
    if not isinstance(data, dict):
        raise ProblemError(422, "meta must be a JSON object", code="invalid_meta")
    try:
        return SubmapMeta.model_validate(data)
    except ValidationError as exc:
        errors = [
            {"loc": ["meta", *err["loc"]], "msg": err["msg"], "type": err["type"]} for err in exc.errors()
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


def _created_body(db: Session, submap: Submap) -> SubmapCreated:
    return SubmapCreated(
        id=submap.id,
        session_id=submap.session_id,
        seq=submap.seq,
        tiles=submap_tile_list(db, submap.id),
        sha256=submap.mesh_sha256,
    )


def _existing(db: Session, prepared: PreparedSubmap) -> SubmapCreated | None:
    """The stored body for an identical retry, None if absent; 409 if the content differs."""
    row = db.scalar(
        select(Submap).where(Submap.session_id == prepared.meta.session_id, Submap.seq == prepared.meta.seq)
    )
    if row is None:
        return None
    if row.content_sha256 != prepared.content_sha256:
        raise ProblemError(
            409,
            f"submap seq {row.seq} of session {row.session_id!r} is already stored with different content",
            code="submap_conflict",
        )
    return _created_body(db, row)


def _insert_ignore(db: Session, table: type, rows: list[dict[str, Any]]) -> None:
    """INSERT … ON CONFLICT DO NOTHING on either backend.

    Core executemany with bound rows: the statement compiles once and is cached (a ``.values(rows)``
    statement recompiled on every upload and was a hot spot of the ingest path).
    """
    module = postgresql if db.get_bind().dialect.name == "postgresql" else sqlite
    db.connection().execute(module.insert(table.__table__).on_conflict_do_nothing(), rows)  # type: ignore[attr-defined]


def _check_session_owner(db: Session, meta: SubmapMeta) -> None:
    """409 if the session exists under another agent (a session belongs to one agent)."""
    owner = db.scalar(select(DrivingSession.agent_id).where(DrivingSession.session_id == meta.session_id))
    if owner is not None and owner != meta.agent_id:
        raise ProblemError(
            409, f"session {meta.session_id!r} belongs to agent {owner!r}", code="session_agent_mismatch"
        )


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


def _insert(db: Session, prepared: PreparedSubmap, now: datetime) -> Submap:
    meta = prepared.meta
    _insert_ignore(
        db, DrivingSession, [{"session_id": meta.session_id, "agent_id": meta.agent_id, "created_at": now}]
    )
    _check_session_owner(db, meta)
    submap = Submap(
        session_id=meta.session_id,
        seq=meta.seq,
        agent_id=meta.agent_id,
        captured_at=meta.captured_at,
        meta=prepared.meta_json,
        content_sha256=prepared.content_sha256,
        mesh_sha256=prepared.mesh_sha256,
        mesh_bytes=len(prepared.mesh_data),
        face_count=prepared.face_count,
        bbox_min=prepared.bbox_min,
        bbox_max=prepared.bbox_max,
        pose_gps=prepared.pose_gps.to_json(),
        gps_sigma_trans_m=meta.gps_sigma.trans_m,
        gps_sigma_rot_deg=meta.gps_sigma.rot_deg,
        odometry=meta.odometry.model_dump(),
        odometry_sigma_trans_m=meta.odometry_sigma.trans_m,
        odometry_sigma_rot_deg=meta.odometry_sigma.rot_deg,
        home_i=prepared.home[0],
        home_j=prepared.home[1],
        created_at=now,
    )
    db.add(submap)
    db.flush()
    db.add_all(SubmapTile(submap_id=submap.id, i=i, j=j) for i, j in prepared.tiles)
    mark_tiles_dirty(db, prepared.tiles, now)
    db.flush()
    return submap


def store(db: Session, blobs: BlobStore, prepared: PreparedSubmap) -> tuple[SubmapCreated, bool]:
    """Store a validated submap; returns the response body and whether it was newly created.

    Concurrent identical uploads race on ``unique(session_id, seq)``: the loser re-reads and
    answers like a retry (200) or a conflict (409), never 500.
    """
    existing = _existing(db, prepared)
    if existing is not None:
        return existing, False
    _check_session_owner(db, prepared.meta)
    db.rollback()  # end the read transaction before the (slow) blob write
    blobs.put(prepared.mesh_data)  # durable before the row that names it commits
    for attempt in range(_INSERT_ATTEMPTS):
        try:
            submap = _insert(db, prepared, utcnow())
            db.commit()
            return _created_body(db, submap), True
        except IntegrityError:
            db.rollback()
            existing = _existing(db, prepared)
            if existing is not None:
                return existing, False
            if attempt == _INSERT_ATTEMPTS - 1:
                raise
        except BaseException:
            db.rollback()
            raise
    raise AssertionError("unreachable")
