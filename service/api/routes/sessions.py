"""``/v1/sessions``: driving sessions with their trajectories (by map-frame box), and the poses of one
session's submaps by ``seq``."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from sqlalchemy import select

from service.api.deps import Reader, SessionDep, SettingsDep
from service.api.params import decode_cursor, encode_cursor, parse_bbox, string
from service.api.problems import found, problem_responses
from service.api.schemas import Pose, SessionPose, SessionTrack, SessionTrackPage, TrackPoint
from service.store import reads
from service.store.models import DrivingSession, Submap

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])


@router.get(
    "",
    operation_id="listSessions",
    response_model=SessionTrackPage,
    responses=problem_responses(401, 403, 422),
)
def list_sessions(
    db: SessionDep,
    settings: SettingsDep,
    _principal: Reader,
    bbox: Annotated[
        str | None,
        Query(description="xmin,ymin,xmax,ymax (map frame, metres): only sessions with a submap in a tile it touches"),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=200, description="Sessions per page")] = 50,
    max_points: Annotated[
        int, Query(ge=2, le=10000, description="Points per trajectory at most (longer ones are subsampled)")
    ] = 1000,
    cursor: Annotated[str | None, Query(description="`next_cursor` of the previous page")] = None,
) -> SessionTrackPage:
    """Sessions ordered by id, each with its GPS and refined trajectory: the translations of its
    submaps' `pose_gps` and `pose_refined` (map frame, metres), by `seq`."""
    tiles = parse_bbox(bbox, settings.tile_size) if bbox is not None else None
    after = decode_cursor(cursor, string)[0] if cursor is not None else None
    ids = reads.sessions_in(db, tiles=tiles, limit=limit + 1, after=after)
    page = reads.session_tracks(db, session_ids=ids[:limit], max_points=max_points)
    items = [
        SessionTrack(
            session_id=row.session_id,
            agent_id=row.agent_id,
            submaps=row.submaps,
            points=[
                TrackPoint(
                    seq=p.seq,
                    pose_gps_t=list(p.gps),
                    pose_refined_t=list(p.refined) if p.refined is not None else None,
                )
                for p in row.points
            ],
        )
        for row in page
    ]
    next_cursor = encode_cursor(page[-1].session_id) if len(ids) > limit else None
    return SessionTrackPage(items=items, next_cursor=next_cursor)


@router.get(
    "/{session_id:path}/poses",
    operation_id="listSessionPoses",
    response_model=list[SessionPose],
    responses=problem_responses(401, 403, 404, 422),
)
def list_session_poses(session_id: str, db: SessionDep, _principal: Reader) -> list[SessionPose]:
    """GPS and refined poses (map frame) per submap, ordered by `seq`. URL-encode `/` in the id."""
    found(db.get(DrivingSession, session_id), f"no session {session_id!r}", "session_not_found")
    rows = db.scalars(select(Submap).where(Submap.session_id == session_id).order_by(Submap.seq)).all()
    return [
        SessionPose(
            seq=row.seq,
            id=row.id,
            pose_gps=Pose.model_validate(row.pose_gps),
            pose_refined=Pose.model_validate(row.pose_refined) if row.pose_refined else None,
        )
        for row in rows
    ]
