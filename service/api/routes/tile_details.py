"""``/v1/tiles/{i}/{j}/versions|submaps|jobs``: what a tile is made of and how it got there (the
viewer's tile panel). Each answers 404 for a tile that holds no submap, like ``GET /v1/tiles/{i}/{j}``."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from sqlalchemy.orm import Session

from service.api.deps import Operator, Reader, SessionDep
from service.api.params import TileIndex, decode_cursor, integer, keyset_page, string
from service.api.problems import ProblemError, problem_responses
from service.api.routes.jobs import job_public
from service.api.schemas import (
    JobList,
    TileSubmapPage,
    TileSubmapPublic,
    TileVersionLinks,
    TileVersionPage,
    TileVersionPublic,
)
from service.store import reads
from service.store.models import TileVersion

router = APIRouter(prefix="/v1/tiles", tags=["tiles"])

Limit = Annotated[int, Query(ge=1, le=1000, description="Items per page")]
Cursor = Annotated[str | None, Query(description="`next_cursor` of the previous page")]


def _held(db: Session, i: int, j: int) -> None:
    if not reads.tile_holds_submaps(db, i=i, j=j):
        raise ProblemError(404, f"tile ({i}, {j}) holds no submap", code="tile_not_found")


def _version_public(request: Request, row: TileVersion) -> TileVersionPublic:
    # a declarative row -> wire-model mapping, like tiles._public and jobs.job_public (duplicates: deliberate)
    mesh = str(request.url_for("get_tile_mesh", i=str(row.tile_i), j=str(row.tile_j)))
    metrics = row.metrics or {}
    return TileVersionPublic(
        version=row.version,
        fused_at=row.created_at,
        job_id=row.job_id,
        mesh_sha256=row.mesh_sha256,
        glb_sha256=row.glb_sha256,
        faces=metrics.get("faces"),
        vertices=metrics.get("vertices"),
        links=TileVersionLinks(
            ply=f"{mesh}?format=ply&version={row.version}", glb=f"{mesh}?format=glb&version={row.version}"
        ),
    )


@router.get(
    "/{i}/{j}/versions",
    operation_id="listTileVersions",
    response_model=TileVersionPage,
    responses=problem_responses(401, 403, 404, 422),
)
def list_tile_versions(
    i: TileIndex,
    j: TileIndex,
    request: Request,
    db: SessionDep,
    _principal: Reader,
    limit: Limit = 100,
    cursor: Cursor = None,
) -> TileVersionPage:
    """The tile's fused versions, newest first: when, by which job, the mesh's hashes and size, and
    links to each (immutable) version's mesh."""
    _held(db, i, j)
    before = decode_cursor(cursor, integer)[0] if cursor is not None else None
    rows = reads.tile_versions(db, i=i, j=j, limit=limit + 1, before=before)
    page, next_cursor = keyset_page(rows, limit, lambda r: (r.version,))
    return TileVersionPage(items=[_version_public(request, r) for r in page], next_cursor=next_cursor)


@router.get(
    "/{i}/{j}/submaps",
    operation_id="listTileSubmaps",
    response_model=TileSubmapPage,
    responses=problem_responses(401, 403, 404, 422),
)
def list_tile_submaps(
    i: TileIndex, j: TileIndex, db: SessionDep, _principal: Reader, limit: Limit = 100, cursor: Cursor = None
) -> TileSubmapPage:
    """The submaps the tile holds, ordered by (session_id, seq)."""
    _held(db, i, j)
    after: tuple[str, int] | None = None
    if cursor is not None:
        session_id, seq = decode_cursor(cursor, string, integer)
        after = (session_id, seq)
    rows = reads.tile_submaps(db, i=i, j=j, limit=limit + 1, after=after)
    page, next_cursor = keyset_page(rows, limit, lambda r: (r.session_id, r.seq))
    items = [
        TileSubmapPublic(
            id=r.id, session_id=r.session_id, seq=r.seq, agent_id=r.agent_id, captured_at=r.captured_at,
            refined=r.refined,
        )
        for r in page
    ]
    return TileSubmapPage(items=items, next_cursor=next_cursor)


@router.get(
    "/{i}/{j}/jobs",
    operation_id="listTileJobs",
    response_model=JobList,
    responses=problem_responses(401, 403, 404, 422),
)
def list_tile_jobs(
    i: TileIndex,
    j: TileIndex,
    db: SessionDep,
    _principal: Operator,
    limit: Annotated[int, Query(ge=1, le=100, description="At most this many, the newest")] = 20,
) -> JobList:
    """The newest fusion jobs that touched the tile (operator): its reconstruct jobs and the align jobs
    whose region held it."""
    _held(db, i, j)
    return JobList(items=[job_public(job) for job in reads.tile_jobs(db, i=i, j=j, limit=limit)])
