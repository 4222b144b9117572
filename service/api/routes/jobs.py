"""``/v1/jobs/{id}``: one fusion job (``align`` a region's poses, or ``reconstruct`` a tile)."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.deps import Operator, SessionDep
from service.api.problems import found, problem_responses
from service.api.schemas import JobPublic
from service.store.models import FusionJob

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])


def job_public(job: FusionJob) -> JobPublic:
    # A field-by-field row → wire model mapping, like the tiles and submaps routes' (declarative: the
    # wire format is kept apart from the table on purpose).
    return JobPublic(
        id=job.id,
        kind=job.kind,  # type: ignore[arg-type]
        tile=[job.tile_i, job.tile_j],
        tiles=job.tiles or [[job.tile_i, job.tile_j]],
        realign=bool(job.realign),
        state=job.state,  # type: ignore[arg-type]
        trigger=job.trigger,  # type: ignore[arg-type]
        progress=job.progress,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
        error=job.error,
        metrics=job.metrics,
    )


# the route decorators (FastAPI's declarative operation tables) of every resource are alike in shape
# (duplicates: deliberate)
@router.get(
    "/{job_id}",
    operation_id="getJob",
    response_model=JobPublic,
    responses=problem_responses(401, 403, 404, 422),
)
def get_job(job_id: str, db: SessionDep, _principal: Operator) -> JobPublic:
    """State and progress (0..1) of a fusion job."""
    return job_public(found(db.get(FusionJob, job_id), f"no fusion job {job_id!r}", "job_not_found"))
