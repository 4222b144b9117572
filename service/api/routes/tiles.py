"""``/v1/tiles``: tile states, operator-triggered fusion, fused mesh downloads."""

from __future__ import annotations

import hashlib
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.responses import FileResponse
from sqlalchemy import and_, distinct, func, or_, select
from sqlalchemy.orm import Session

from fusion.meshio import filter_confidence, read_fused_ply, write_fused_ply, write_glb
from service.api.deps import BlobsDep, Operator, Reader, SessionDep, SettingsDep
from service.api.downloads import IMMUTABLE, matches, read_blob
from service.api.params import TileIndex, decode_cursor, integer, keyset_page, parse_bbox
from service.api.problems import ProblemError, problem_responses
from service.api.schemas import FuseAccepted, TileLinks, TilePage, TilePublic
from service.schedule import request_fusion
from service.store.models import JobTrigger, Submap, SubmapTile, Tile, TileVersion

router = APIRouter(prefix="/v1/tiles", tags=["tiles"])

MEDIA_TYPES = {"ply": "application/octet-stream", "glb": "model/gltf-binary"}


# Per-tile aggregates as correlated subqueries: evaluated only for the tiles of the page (an index-only
# scan of ix_submap_tiles_i_j, and primary-key lookups of the tile's submaps for distinct sessions).
_SUBMAPS = (
    select(func.count())
    .select_from(SubmapTile)
    .where(SubmapTile.i == Tile.i, SubmapTile.j == Tile.j)
    .correlate(Tile)
    .scalar_subquery()
)
_SESSIONS = (
    select(func.count(distinct(Submap.session_id)))
    .select_from(SubmapTile)
    .join(Submap, Submap.id == SubmapTile.submap_id)
    .where(SubmapTile.i == Tile.i, SubmapTile.j == Tile.j)
    .correlate(Tile)
    .scalar_subquery()
)
_TILE_ROW = select(
    Tile.i,
    Tile.j,
    Tile.state,
    Tile.version,
    Tile.fused_at,
    Tile.progress,
    Tile.last_error,
    Tile.job_id,
    _SUBMAPS.label("submaps"),
    _SESSIONS.label("sessions"),
)


_I, _J = "fleetmap-tile-i", "fleetmap-tile-j"  # placeholders in the URL templates


class _Links:
    """The tile links, built from one ``url_for`` per route and request (it was two per tile)."""

    def __init__(self, request: Request) -> None:
        self.tile = str(request.url_for("get_tile", i=_I, j=_J))
        self.mesh = str(request.url_for("get_tile_mesh", i=_I, j=_J))

    def of(self, i: int, j: int) -> TileLinks:
        si, sj = str(i), str(j)
        return TileLinks(
            self=self.tile.replace(_I, si).replace(_J, sj),
            mesh=self.mesh.replace(_I, si).replace(_J, sj),
        )


def _public(links: _Links, row: Any) -> TilePublic:
    # a declarative row -> wire-model mapping, like jobs.job_public and submaps.get_submap: alike in shape
    # only, each names its own model's fields (duplicates: deliberate)
    return TilePublic(
        i=row.i,
        j=row.j,
        state=row.state,
        submaps=row.submaps,
        sessions=row.sessions,
        version=row.version,
        fused_at=row.fused_at,
        progress=min(max(row.progress, 0.0), 1.0),
        last_error=row.last_error,
        job_id=row.job_id,
        links=links.of(row.i, row.j),
    )


def _json(model: TilePublic | TilePage) -> Response:
    """Serialised once by pydantic-core (skips FastAPI's validate-then-serialise of the return value)."""
    return Response(model.model_dump_json(), media_type="application/json")


def _tile_row(db: Session, i: int, j: int) -> Any:
    """The tile's row with its counts; 404 unless it holds a submap."""
    row = db.execute(_TILE_ROW.where(Tile.i == i, Tile.j == j)).first()
    if row is None or not row.submaps:
        raise ProblemError(404, f"tile ({i}, {j}) holds no submap", code="tile_not_found")
    return row


@router.get("", operation_id="listTiles", response_model=TilePage, responses=problem_responses(401, 403, 422))
def list_tiles(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    _principal: Reader,
    state: Annotated[Literal["dirty", "queued", "fusing", "fused", "failed"] | None, Query()] = None,
    bbox: Annotated[str | None, Query(description="xmin,ymin,xmax,ymax (map frame, metres)")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    cursor: Annotated[str | None, Query(description="`next_cursor` of the previous page")] = None,
) -> TilePage:
    """Tiles ordered by (i, j), optionally filtered by state and by a map-frame box."""
    query = _TILE_ROW.order_by(Tile.i, Tile.j).limit(limit + 1)
    if state is not None:
        query = query.where(Tile.state == state)
    if bbox is not None:
        i0, j0, i1, j1 = parse_bbox(bbox, settings.tile_size)
        query = query.where(Tile.i.between(i0, i1), Tile.j.between(j0, j1))
    if cursor is not None:
        ci, cj = decode_cursor(cursor, integer, integer)
        query = query.where(or_(Tile.i > ci, and_(Tile.i == ci, Tile.j > cj)))
    rows = db.execute(query).all()
    page, next_cursor = keyset_page(rows, limit, lambda r: (r.i, r.j))
    links = _Links(request)
    return _json(TilePage(items=[_public(links, r) for r in page], next_cursor=next_cursor))  # type: ignore[return-value]


@router.get(
    "/{i}/{j}",
    operation_id="getTile",
    response_model=TilePublic,
    responses=problem_responses(401, 403, 404, 422),
)
def get_tile(i: TileIndex, j: TileIndex, request: Request, db: SessionDep, _principal: Reader) -> TilePublic:
    """One tile's state, counts, version and links."""
    return _json(_public(_Links(request), _tile_row(db, i, j)))  # type: ignore[return-value]


@router.post(
    "/{i}/{j}/fuse",
    operation_id="fuseTile",
    status_code=202,
    response_model=FuseAccepted,
    responses=problem_responses(401, 403, 404, 422, 503),
)
def request_tile_fusion(
    i: TileIndex, j: TileIndex, db: SessionDep, settings: SettingsDep, _principal: Operator
) -> FuseAccepted:
    """Queue a (re-)fusion of the tile; an already queued or running job is returned instead. When
    the tile holds submaps not aligned yet, the job is its region's alignment (`GET /v1/jobs/{id}`:
    `kind` `align`), which then reconstructs every tile of the region."""
    _tile_row(db, i, j)
    try:
        job = request_fusion(db, i, j, trigger=JobTrigger.operator.value, settings=settings)
    except LookupError as exc:
        raise ProblemError(404, f"tile ({i}, {j}) holds no submap", code="tile_not_found") from exc
    return FuseAccepted(job_id=job.id, tile=[i, j])


def _etag(mesh_sha256: str, fmt: str, min_confidence: float | None) -> str:
    key = f"{mesh_sha256}:{fmt}:{'-' if min_confidence is None else repr(float(min_confidence))}"
    return '"' + hashlib.sha256(key.encode()).hexdigest()[:32] + '"'


MESH_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "The fused mesh (PLY binary little endian, or GLB), map frame",
        "content": {
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
            "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}},
        },
    },
    304: {"description": "Not modified: `If-None-Match` matches the ETag"},
    **problem_responses(401, 403, 404, 422, 503),
}


@router.get("/{i}/{j}/mesh", operation_id="getTileMesh", response_class=Response, responses=MESH_RESPONSES)
def get_tile_mesh(
    i: TileIndex,
    j: TileIndex,
    db: SessionDep,
    blobs: BlobsDep,
    _principal: Reader,
    format: Annotated[Literal["ply", "glb"], Query()] = "ply",
    version: Annotated[int | None, Query(ge=1, description="Default: the latest")] = None,
    min_confidence: Annotated[float | None, Query(ge=0, le=1, description="Drop faces below")] = None,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """The fused semantic mesh of the latest (or the given, immutable) version; 404 while never fused."""
    tile = db.get(Tile, (i, j))
    if tile is None or tile.version < 1:
        raise ProblemError(404, f"tile ({i}, {j}) has not been fused yet", code="mesh_not_found")
    wanted = version if version is not None else tile.version
    row = db.scalar(
        select(TileVersion).where(
            TileVersion.tile_i == i, TileVersion.tile_j == j, TileVersion.version == wanted
        )
    )
    if row is None:
        raise ProblemError(404, f"tile ({i}, {j}) has no version {wanted}", code="version_not_found")
    etag = _etag(row.mesh_sha256, format, min_confidence)
    headers = {
        "ETag": etag,
        "Cache-Control": IMMUTABLE if version is not None else "no-cache",
        "Content-Disposition": f'attachment; filename="tile_{i}_{j}_v{wanted}.{format}"',
        "X-Tile-Version": str(wanted),
    }
    if matches(if_none_match, etag):
        return Response(status_code=304, headers=headers)
    stored = row.mesh_sha256 if format == "ply" else row.glb_sha256
    if min_confidence is None and stored is not None:
        path = blobs.path(stored)
        if path is not None and path.is_file():
            return FileResponse(path, media_type=MEDIA_TYPES[format], headers=headers)
        return Response(read_blob(blobs, stored), media_type=MEDIA_TYPES[format], headers=headers)
    fused = read_fused_ply(read_blob(blobs, row.mesh_sha256))
    if min_confidence is not None:
        fused = filter_confidence(fused, min_confidence)
    data = write_fused_ply(fused) if format == "ply" else write_glb(fused)
    return Response(data, media_type=MEDIA_TYPES[format], headers=headers)
