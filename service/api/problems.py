"""RFC 9457 problem documents (``application/problem+json``) for every error the API answers.

All mapping from exceptions to problems lives here: HTTP errors, request validation, the fusion
library's typed errors, oversized bodies, an unavailable database, and anything unexpected
(logged with its stack trace, answered without one).
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Sequence
from http import HTTPStatus
from typing import Any, TypeVar

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy.exc import OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException

from fusion.errors import FusionLibraryError, MeshValidationError, PoseError
from service.store.blobs import BlobStoreUnavailableError

log = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_PREFIX = "urn:fleetmap:problem:"


class ValidationErrorItem(BaseModel):
    """One validation failure: where (``loc``), what (``msg``) and a short machine code (``type``)."""

    model_config = ConfigDict(extra="allow")

    loc: list[str | int] = Field(
        description="Path to the offending input: part or parameter first, then names and indices",
        examples=[["mesh", "face", 1234], ["meta", "gps", "pose", "q"], ["query", "bbox"]],
    )
    msg: str = Field(examples=["face 1234 refers to vertex 9, but vertex indices must be in 0..2"])
    type: str = Field(examples=["bad_vertex_index"])


class Problem(BaseModel):
    """An RFC 9457 problem document; ``code`` is a stable machine-readable reason."""

    model_config = ConfigDict(extra="allow")

    type: str = Field(default="about:blank", examples=["urn:fleetmap:problem:too_many_faces"])
    title: str = Field(examples=["Unprocessable Content"])
    status: int = Field(examples=[422])
    detail: str | None = Field(default=None, examples=["mesh has 3000000 faces, at most 2000000 allowed"])
    code: str | None = Field(default=None, examples=["too_many_faces"])
    errors: list[ValidationErrorItem] | None = Field(
        default=None,
        description="Validation failures (every 400 and 422): one entry per offending field, never empty",
    )


class ProblemError(Exception):
    """Raise anywhere in the service to answer with a problem document."""

    def __init__(
        self,
        status: int,
        detail: str | None = None,
        *,
        code: str | None = None,
        title: str | None = None,
        errors: list[dict[str, Any]] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(detail or code or str(status))
        self.status = status
        self.detail = detail
        self.code = code
        self.title = title
        self.errors = errors
        self.headers = headers


Row = TypeVar("Row")


def found(row: Row | None, detail: str, code: str) -> Row:
    """``row``, or a 404 problem (``code``) saying what is missing."""
    if row is None:
        raise ProblemError(404, detail, code=code)
    return row


class BodyTooLargeError(ProblemError):
    """The request body crossed ``FLEETMAP_MAX_UPLOAD_BYTES`` (raised while streaming)."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body exceeds the limit of {limit} bytes", code="body_too_large")


VALIDATION_STATUSES = (400, 422)  # validation failures: their problems always carry ``errors``


def validation_error(loc: Sequence[str | int], msg: str, type_: str) -> dict[str, Any]:
    """One ``errors`` entry (``ValidationErrorItem``)."""
    return {"loc": list(loc), "msg": msg, "type": type_}


def problem_body(
    status: int,
    detail: str | None = None,
    *,
    code: str | None = None,
    title: str | None = None,
    errors: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The JSON object of a problem document."""
    try:
        default_title = HTTPStatus(status).phrase
    except ValueError:
        default_title = "Error"
    body: dict[str, Any] = {
        "type": f"{TYPE_PREFIX}{code}" if code else "about:blank",
        "title": title or default_title,
        "status": status,
        "detail": detail,
    }
    if code:
        body["code"] = code
    if not errors and status in VALIDATION_STATUSES:
        errors = [validation_error(["request"], detail or body["title"], code or "invalid_request")]
    if errors is not None:
        body["errors"] = errors
    return body


def problem_response(problem: ProblemError) -> JSONResponse:
    """The response carrying ``problem``'s document (for handlers and middleware that cannot raise)."""
    body = problem_body(problem.status, problem.detail, code=problem.code, title=problem.title, errors=problem.errors)
    return JSONResponse(
        jsonable_encoder(body), status_code=problem.status, headers=problem.headers, media_type=PROBLEM_MEDIA_TYPE
    )


def _validation_errors(raw: list[Any]) -> list[dict[str, Any]]:
    """Pydantic errors without the offending input echoed back (it may be large or binary)."""
    out = []
    for err in raw:
        entry = {"loc": list(err.get("loc", ())), "msg": str(err.get("msg", "")), "type": err.get("type", "")}
        out.append(entry)
    return out


async def _handle_problem(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ProblemError)
    return problem_response(exc)


async def _handle_http(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    detail = exc.detail if isinstance(exc.detail, str) else None
    errors = None
    if exc.status_code == 400:  # Starlette's only 400s: a body (multipart form) it cannot parse
        errors = [validation_error(["body"], detail or "malformed request body", "malformed_body")]
    return problem_response(ProblemError(exc.status_code, detail, errors=errors, headers=dict(exc.headers or {})))


async def _handle_validation(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = _validation_errors(list(exc.errors()))
    return problem_response(ProblemError(422, "the request is invalid", code="invalid_request", errors=errors))


async def _handle_fusion(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, FusionLibraryError)
    if isinstance(exc, MeshValidationError | PoseError):
        part = "mesh" if isinstance(exc, MeshValidationError) else "meta"
        loc = list(exc.loc) if exc.loc else [part]
        errors = [validation_error(loc, exc.message, exc.code)]
        return problem_response(ProblemError(422, exc.message, code=exc.code, errors=errors))
    log.error("fusion library error: %s", exc.message)
    return problem_response(ProblemError(500, exc.message, code=exc.code))


def _unavailable(service: str, code: str) -> Callable[[Request, Exception], Awaitable[JSONResponse]]:
    """A handler answering 503 (with ``Retry-After``) when ``service`` cannot be reached."""

    async def handle(_request: Request, exc: Exception) -> JSONResponse:
        log.error("%s unavailable: %s", service, exc.__class__.__name__, exc_info=exc)
        return problem_response(ProblemError(503, f"the {service} is unavailable, retry later", code=code, headers={"Retry-After": "5"}))

    return handle


_handle_db_unavailable = _unavailable("database", "database_unavailable")
_handle_blobs_unavailable = _unavailable("blob store", "blob_store_unavailable")


async def _handle_unexpected(_request: Request, exc: Exception) -> JSONResponse:
    log.error("unhandled error", exc_info=exc)
    return problem_response(ProblemError(500, "an unexpected error occurred; it has been logged", code="internal_error"))


def install_problem_handlers(app: FastAPI) -> None:
    """Register every exception → problem mapping on ``app``."""
    app.add_exception_handler(ProblemError, _handle_problem)
    app.add_exception_handler(StarletteHTTPException, _handle_http)
    app.add_exception_handler(RequestValidationError, _handle_validation)
    app.add_exception_handler(FusionLibraryError, _handle_fusion)
    app.add_exception_handler(OperationalError, _handle_db_unavailable)
    app.add_exception_handler(PoolTimeoutError, _handle_db_unavailable)  # every pooled connection busy
    app.add_exception_handler(BlobStoreUnavailableError, _handle_blobs_unavailable)
    app.add_exception_handler(Exception, _handle_unexpected)


_DESCRIPTIONS = {
    304: "Not modified (the `If-None-Match` ETag matches)",
    401: "Missing or invalid bearer token",
    403: "The token's role may not do this",
    404: "Not found",
    409: "Conflicts with the stored state",
    413: "Request body too large",
    422: "Invalid input (validation failures are listed in `errors`)",
    503: "A dependency (database, broker, blob store) is unavailable",
}


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries declaring problem documents for ``statuses``."""
    out: dict[int | str, dict[str, Any]] = {}
    for status in statuses:
        out[status] = {
            "model": Problem,
            "description": _DESCRIPTIONS.get(status, HTTPStatus(status).phrase),
            "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
    return out
