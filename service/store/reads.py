"""Read-only queries behind the viewer's routes: a tile's versions, submaps and fusion jobs, and the
sessions (with their trajectories) that drove through a range of tiles.

Every listing is bounded by a ``limit``; the long ones resume after a sort key (keyset pagination), so
a page costs the same however deep it is. Frames: trajectories are map-frame translations, metres.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from sqlalchemy import and_, cast, func, literal, or_, select
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import Session
from sqlalchemy.sql.elements import ColumnElement

from service.store.db import is_postgres
from service.store.models import DrivingSession, FusionJob, JobKind, Submap, SubmapTile, TileVersion

TileRange = tuple[int, int, int, int]  # i0, j0, i1, j1, inclusive

Vec3 = tuple[float, float, float]


def tile_holds_submaps(db: Session, *, i: int, j: int) -> bool:
    """Whether any submap touches tile ``(i, j)`` (the API's test for "the tile exists")."""
    found = db.scalar(select(SubmapTile.submap_id).where(SubmapTile.i == i, SubmapTile.j == j).limit(1))
    return found is not None


def tile_versions(db: Session, *, i: int, j: int, limit: int, before: int | None = None) -> list[TileVersion]:
    """The tile's versions, newest first, at most ``limit``; only those older than ``before``."""
    query = select(TileVersion).where(TileVersion.tile_i == i, TileVersion.tile_j == j)
    if before is not None:
        query = query.where(TileVersion.version < before)
    return list(db.scalars(query.order_by(TileVersion.version.desc()).limit(limit)))


@dataclass(frozen=True)
class TileSubmap:
    """A submap a tile holds (no mesh, no meta): who uploaded it, when, and whether it is aligned."""

    id: str
    session_id: str
    seq: int
    agent_id: str
    captured_at: Any
    refined: bool


def tile_submaps(
    db: Session, *, i: int, j: int, limit: int, after: tuple[str, int] | None = None
) -> list[TileSubmap]:
    """The submaps touching the tile ordered by ``(session_id, seq)``, at most ``limit``, after the key
    ``after``."""
    query = (
        select(
            Submap.id,
            Submap.session_id,
            Submap.seq,
            Submap.agent_id,
            Submap.captured_at,
            Submap.pose_refined.is_not(None).label("refined"),
        )
        .join(SubmapTile, SubmapTile.submap_id == Submap.id)
        .where(SubmapTile.i == i, SubmapTile.j == j)
    )
    if after is not None:
        session_id, seq = after
        query = query.where(
            or_(Submap.session_id > session_id, and_(Submap.session_id == session_id, Submap.seq > seq))
        )
    rows = db.execute(query.order_by(Submap.session_id, Submap.seq).limit(limit)).all()
    return [TileSubmap(r.id, r.session_id, r.seq, r.agent_id, r.captured_at, bool(r.refined)) for r in rows]


def _region_covers(db: Session, i: int, j: int) -> ColumnElement[bool]:
    """An align job's region (``FusionJob.tiles``, ``[[i, j], ...]``) holds tile ``(i, j)``: one of its
    elements equals the pair (JSON equality, not text matching; jsonb's ``@>`` would also match
    ``[j, i]`` and ``[i, 7]`` pairs holding both numbers)."""
    if is_postgres(db):
        member = func.jsonb_array_elements(cast(FusionJob.tiles, JSONB)).table_valued("value").alias("member")
        same = member.c.value == cast(literal(json.dumps([i, j])), JSONB)
    else:
        member = func.json_each(FusionJob.tiles).table_valued("value").alias("member")
        same = and_(
            func.json_extract(member.c.value, "$[0]") == i, func.json_extract(member.c.value, "$[1]") == j
        )
    return select(literal(1)).select_from(member).where(same).exists()


def tile_jobs(db: Session, *, i: int, j: int, limit: int) -> list[FusionJob]:
    """The fusion jobs that touched the tile, newest first, at most ``limit``: its reconstruct jobs and
    the align jobs whose region held it."""
    own = and_(FusionJob.tile_i == i, FusionJob.tile_j == j)
    region = and_(FusionJob.kind == JobKind.align.value, FusionJob.tiles.is_not(None), _region_covers(db, i, j))
    query = select(FusionJob).where(or_(own, region)).order_by(FusionJob.created_at.desc(), FusionJob.id)
    return list(db.scalars(query.limit(limit)))


@dataclass(frozen=True)
class TrackPoint:
    """One submap of a session: its ``seq`` and the translations of its GPS and refined poses."""

    seq: int
    gps: Vec3
    refined: Vec3 | None


@dataclass(frozen=True)
class SessionTrack:
    """A session and its trajectory; ``points`` is every submap, or an even subsample (first and last
    kept) when the session has more than the caller's ``max_points``."""

    session_id: str
    agent_id: str
    submaps: int
    points: list[TrackPoint]


def _translation(pose: dict[str, Any] | None) -> Vec3 | None:
    if pose is None:
        return None
    x, y, z = pose["t"]
    return float(x), float(y), float(z)


def _subsample(points: list[TrackPoint], max_points: int) -> list[TrackPoint]:
    if len(points) <= max_points:
        return points
    if max_points == 1:
        return points[:1]
    step = (len(points) - 1) / (max_points - 1)
    return [points[round(k * step)] for k in range(max_points)]


def sessions_in(db: Session, *, tiles: TileRange | None, limit: int, after: str | None = None) -> list[str]:
    """Session ids in order, at most ``limit`` after ``after``; with ``tiles``, only the sessions with a
    submap touching a tile of that range."""
    query = select(Submap.session_id).group_by(Submap.session_id).order_by(Submap.session_id).limit(limit)
    if tiles is not None:
        i0, j0, i1, j1 = tiles
        query = query.join(SubmapTile, SubmapTile.submap_id == Submap.id).where(
            SubmapTile.i.between(i0, i1), SubmapTile.j.between(j0, j1)
        )
    if after is not None:
        query = query.where(Submap.session_id > after)
    return list(db.scalars(query))


def session_tracks(db: Session, *, session_ids: list[str], max_points: int) -> list[SessionTrack]:
    """The sessions ``session_ids`` (in that order) with their whole trajectories (map frame, metres),
    each subsampled to ``max_points``."""
    if not session_ids:
        return []
    agents: dict[str, str] = {
        sid: agent for sid, agent in db.execute(
            select(DrivingSession.session_id, DrivingSession.agent_id).where(DrivingSession.session_id.in_(session_ids))
        )
    }
    points: dict[str, list[TrackPoint]] = {sid: [] for sid in session_ids}
    rows = db.execute(
        select(Submap.session_id, Submap.seq, Submap.pose_gps, Submap.pose_refined)
        .where(Submap.session_id.in_(session_ids))
        .order_by(Submap.session_id, Submap.seq)
    )
    for session_id, seq, pose_gps, pose_refined in rows:
        gps = _translation(pose_gps)
        assert gps is not None  # the column is NOT NULL
        points[session_id].append(TrackPoint(seq, gps, _translation(pose_refined)))
    return [
        SessionTrack(sid, agents.get(sid, ""), len(points[sid]), _subsample(points[sid], max_points))
        for sid in session_ids
    ]
