"""``/v1/submaps``: upload (multipart meta + mesh) and read back a stored submap."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, HTTPException, Request, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.orm import Session, sessionmaker
from starlette.datastructures import UploadFile

from fusion.errors import FusionLibraryError
from service.api.auth import Principal
from service.api.deps import BlobsDep, Reader, SessionDep, SettingsDep, Uploader
from service.api.ingest import parse_meta, prepare
from service.api.problems import BodyTooLargeError, ProblemError, found, problem_responses
from service.api.schemas import DriftCorrection, Pose, SubmapCreated, SubmapPublic
from service.settings import Settings
from service.store.blobs import BlobStore
from service.store.models import Submap
from service.store.submaps import SubmapConflict, store, submap_tile_list
from service.telemetry import UPLOAD_BYTES, UPLOADS, record_rejection

router = APIRouter(prefix="/v1/submaps", tags=["submaps"])

UPLOAD_REQUEST_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["meta", "mesh"],
                    "properties": {
                        "meta": {"$ref": "#/components/schemas/SubmapMeta"},
                        "mesh": {
                            "type": "string",
                            "format": "binary",
                            "description": "PLY (ascii or binary), local frame, metres, with semantic labels",
                        },
                    },
                },
                "encoding": {"meta": {"contentType": "application/json"}},
            }
        },
    }
}


async def _read_parts(request: Request, settings: Settings) -> tuple[bytes, bytes]:
    """The ``meta`` and ``mesh`` parts; the body size limit is enforced by BodyLimitMiddleware."""
    form = await request.form(max_files=4, max_fields=8, max_part_size=settings.max_upload_bytes)
    try:
        parts: dict[str, bytes] = {}
        for name in ("meta", "mesh"):
            value = form.get(name)
            if isinstance(value, UploadFile):
                parts[name] = await value.read()
            elif isinstance(value, str):
                parts[name] = value.encode("utf-8")
        missing = [name for name in ("meta", "mesh") if name not in parts]
        if missing:
            raise ProblemError(
                422,
                f"multipart/form-data part(s) missing: {', '.join(missing)}",
                code="missing_part",
                errors=[
                    {"loc": ["body", name], "msg": "part required", "type": "missing"} for name in missing
                ],
            )
        return parts["meta"], parts["mesh"]
    finally:
        await form.close()


@router.post(
    "",
    operation_id="uploadSubmap",
    status_code=201,
    response_model=SubmapCreated,
    responses={
        200: {
            "model": SubmapCreated,
            "description": "Idempotent retry: already stored with identical content",
        },
        201: {"description": "Stored (mesh blob and row are durable)"},
        **problem_responses(400, 401, 403, 409, 413, 422, 503),
    },
    openapi_extra=UPLOAD_REQUEST_BODY,
)
async def upload_submap(
    request: Request,
    principal: Uploader,
    settings: SettingsDep,
    blobs: BlobsDep,
) -> Response:
    """Upload one submap: `meta` (JSON) and `mesh` (PLY in the submap's local frame, metres)."""
    try:
        meta_raw, mesh_data = await _read_parts(request, settings)
        body, created = await run_in_threadpool(
            _ingest, request.app.state.session_factory, blobs, settings, principal, meta_raw, mesh_data
        )
    except BodyTooLargeError:
        raise  # counted by BodyLimitMiddleware
    except ProblemError as exc:
        record_rejection(exc.code or str(exc.status))
        raise
    except FusionLibraryError as exc:
        record_rejection(exc.code)
        raise
    except HTTPException as exc:  # malformed multipart
        record_rejection("malformed_multipart" if exc.status_code == 400 else str(exc.status_code))
        raise
    if created:
        UPLOADS.labels(outcome="created").inc()
        UPLOAD_BYTES.inc(len(mesh_data))
    else:
        UPLOADS.labels(outcome="retry").inc()
    return Response(
        body.model_dump_json(), status_code=201 if created else 200, media_type="application/json"
    )


def _ingest(
    session_factory: sessionmaker[Session],
    blobs: BlobStore,
    settings: Settings,
    principal: Principal,
    meta_raw: bytes,
    mesh_data: bytes,
) -> tuple[SubmapCreated, bool]:
    """The synchronous part of an upload, in one threadpool hop: meta, agent check, mesh
    validation, blob and transaction."""
    meta = parse_meta(meta_raw)
    if not principal.may_upload_as(meta.agent_id):
        raise ProblemError(
            403, f"this token may upload only as agent {principal.name!r}", code="agent_mismatch"
        )
    new = prepare(meta, mesh_data, settings)
    with session_factory() as db:
        try:
            stored, created = store(db, blobs, new)
        except SubmapConflict as exc:
            raise ProblemError(409, exc.message, code=exc.code) from exc
    return SubmapCreated(**asdict(stored)), created


@router.get(
    "/{submap_id}",
    operation_id="getSubmap",
    response_model=SubmapPublic,
    responses=problem_responses(401, 403, 404, 422),
)
def get_submap(submap_id: str, db: SessionDep, _principal: Reader) -> SubmapPublic:
    """The stored meta plus `pose_gps` and `pose_refined` (map frame) and the tiles it touches."""
    row = found(db.get(Submap, submap_id), f"no submap {submap_id!r}", "submap_not_found")
    meta = row.meta
    return SubmapPublic(
        id=row.id,
        agent_id=row.agent_id,
        session_id=row.session_id,
        seq=row.seq,
        captured_at=row.captured_at,
        gps=meta["gps"],
        gps_sigma=meta["gps_sigma"],
        odometry=meta["odometry"],
        odometry_sigma=meta["odometry_sigma"],
        pose_gps=Pose.model_validate(row.pose_gps),
        pose_refined=Pose.model_validate(row.pose_refined) if row.pose_refined else None,
        refined_at=row.refined_at,
        drift_refined=DriftCorrection.model_validate(row.drift_refined) if row.drift_refined else None,
        tiles=submap_tile_list(db, row.id),
        home_tile=[row.home_i, row.home_j],
        sha256=row.mesh_sha256,
        face_count=row.face_count,
        created_at=row.created_at,
    )
