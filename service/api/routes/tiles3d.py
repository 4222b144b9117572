"""``/v1/3dtiles``: the fused map as OGC 3D Tiles 1.1, for web globes (CesiumJS, deck.gl).

Auth as for mesh downloads (reader or operator token). The tileset names each fused tile's latest
version; a version's content never changes (cached forever), the tileset is revalidated by ETag.
Frames and bounding volumes: ``service.tiles3d``.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Header, Path, Response
from sqlalchemy import and_, select

from fusion.meshio import read_fused_ply
from service.api.deps import BlobsDep, Reader, SessionDep, SettingsDep
from service.api.downloads import IMMUTABLE, matches, read_blob
from service.api.params import TileIndex
from service.api.problems import ProblemError, problem_responses
from service.store.blobs import BlobStore
from service.store.models import Tile, TileVersion
from service.tiles3d import (
    CONTENT,
    EXTENTS,
    Extent,
    FusedTile,
    content_etag,
    content_glb,
    tileset,
    tileset_etag,
)

router = APIRouter(prefix="/v1/3dtiles", tags=["3dtiles"])

GLB_MEDIA_TYPE = "model/gltf-binary"
# Path integers are database integers: a larger one is a 422, not an overflow in the query.
_NOT_MODIFIED = {"description": "Not modified: `If-None-Match` matches the ETag"}


def _content_uri(tile: FusedTile) -> str:
    """Relative to tileset.json, so the tileset works behind any path prefix (the content route)."""
    return f"tiles/{tile.i}/{tile.j}/{tile.version}.glb"


def _extent(blobs: BlobStore, tile: FusedTile) -> Extent | None:
    return EXTENTS.get(tile.mesh_sha256, lambda: Extent.of(read_fused_ply(read_blob(blobs, tile.mesh_sha256))))


TILESET_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "The 3D Tiles 1.1 tileset: a root (map frame → ECEF `transform`) with one child "
        "per fused tile at its latest version (`region` and `box` bounding volumes, glTF content)",
        "content": {"application/json": {"schema": {"type": "object"}}},
    },
    304: _NOT_MODIFIED,
    **problem_responses(401, 403, 422, 503),
}


@router.get("/tileset.json", operation_id="get3dTileset", response_class=Response, responses=TILESET_RESPONSES)
def get_tileset(
    db: SessionDep,
    blobs: BlobsDep,
    settings: SettingsDep,
    _principal: Reader,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """The fused map as a 3D Tiles tileset; an empty map gives a root without children. The ETag
    changes exactly when a tile gets a new version (or the frame changes)."""
    rows = db.execute(
        select(Tile.i, Tile.j, Tile.version, TileVersion.mesh_sha256)
        .join(
            TileVersion,
            and_(TileVersion.tile_i == Tile.i, TileVersion.tile_j == Tile.j, TileVersion.version == Tile.version),
        )
        .where(Tile.version > 0)
        .order_by(Tile.i, Tile.j)
    ).all()
    fused = [FusedTile(row.i, row.j, row.version, row.mesh_sha256) for row in rows]
    origin = settings.origin_lla
    etag = tileset_etag(fused, origin, settings.tile_size)
    headers = {"ETag": etag, "Cache-Control": "no-cache"}
    if matches(if_none_match, etag):
        return Response(status_code=304, headers=headers)
    placed = [(tile, extent) for tile in fused if (extent := _extent(blobs, tile)) is not None]
    document = tileset(placed, origin, settings.tile_size, _content_uri)
    return Response(json.dumps(document), media_type="application/json", headers=headers)


CONTENT_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "Binary glTF of the tile version: map-frame positions relative to the tile centre "
        "(y-up, as 3D Tiles expects), label colours, per-face classes as `EXT_mesh_features` feature ids "
        "into an `EXT_structural_metadata` label table (id, name, color)",
        "content": {GLB_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
    },
    304: _NOT_MODIFIED,
    **problem_responses(401, 403, 404, 422, 503),
}


@router.get(
    "/tiles/{i}/{j}/{version}.glb",
    operation_id="get3dTileContent",
    response_class=Response,
    responses=CONTENT_RESPONSES,
)
def get_tile_content(
    i: TileIndex,
    j: TileIndex,
    version: Annotated[int, Path(ge=1, le=2**31 - 1, description="The tile version (immutable)")],
    db: SessionDep,
    blobs: BlobsDep,
    settings: SettingsDep,
    _principal: Reader,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """One tile version's content, as the tileset links it; 404 for a tile never fused or a version
    it does not have."""
    row = db.scalar(
        select(TileVersion).where(TileVersion.tile_i == i, TileVersion.tile_j == j, TileVersion.version == version)
    )
    if row is None:
        tile = db.get(Tile, (i, j))
        if tile is None or tile.version < 1:
            raise ProblemError(404, f"tile ({i}, {j}) has not been fused yet", code="mesh_not_found")
        raise ProblemError(404, f"tile ({i}, {j}) has no version {version}", code="version_not_found")
    fused = FusedTile(i, j, version, row.mesh_sha256)
    etag = content_etag(fused, settings.tile_size)
    headers = {"ETag": etag, "Cache-Control": IMMUTABLE, "X-Tile-Version": str(version)}
    if matches(if_none_match, etag):
        return Response(status_code=304, headers=headers)
    data = CONTENT.get(
        (row.mesh_sha256, i, j, settings.tile_size),
        lambda: content_glb(read_fused_ply(read_blob(blobs, row.mesh_sha256)), i, j, settings.tile_size),
    )
    return Response(data, media_type=GLB_MEDIA_TYPE, headers=headers)
