"""``/v1/sessions/{session_id}/poses``: the poses of one session's submaps, by ``seq``."""

from __future__ import annotations

from fastapi import APIRouter
from sqlalchemy import select

from service.api.deps import Reader, SessionDep
from service.api.problems import found, problem_responses
from service.api.schemas import Pose, SessionPose
from service.store.models import DrivingSession, Submap

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])


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
