"""Pure-ASGI middleware: request ids + access log, the request body size limit, and CORS for the
read-only paths that viewers on other origins load (3D Tiles).

The body limit is enforced while the body streams in (Starlette caps single multipart fields
but not the whole body), and up front when ``Content-Length`` already announces too much.
"""

from __future__ import annotations

import logging
import re
import time
import uuid

from starlette.middleware.cors import CORSMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.problems import BodyTooLargeError, ProblemError, problem_response
from service.telemetry import HTTP_REQUESTS, record_rejection, request_id_var

log = logging.getLogger("fleetmap.access")

_REQUEST_ID = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")
_UPLOAD_PATH = "/v1/submaps"


class RequestContextMiddleware:
    """Assigns a request id (``X-Request-ID``, echoed back), logs and counts each request."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = dict(scope["headers"]).get(b"x-request-id", b"").decode("latin-1")
        request_id = incoming if _REQUEST_ID.match(incoming) else uuid.uuid4().hex
        token = request_id_var.set(request_id)
        status = 500
        started = time.perf_counter()

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                message.setdefault("headers", [])
                message["headers"] = [*message["headers"], (b"x-request-id", request_id.encode())]
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", "unmatched")
            HTTP_REQUESTS.labels(method=scope["method"], route=template, status=str(status)).inc()
            log.info(
                "%s %s %s %.1fms",
                scope["method"],
                scope["path"],
                status,
                (time.perf_counter() - started) * 1000,
                extra={"http_method": scope["method"], "path": scope["path"], "status": status},
            )
            request_id_var.reset(token)


class BodyLimitMiddleware:
    """Answers 413 (problem document) once a request body exceeds ``max_bytes``."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        is_upload = scope["path"].rstrip("/") == _UPLOAD_PATH
        announced = dict(scope["headers"]).get(b"content-length")
        if announced is not None and announced.isdigit() and int(announced) > self.max_bytes:
            if is_upload:
                record_rejection("body_too_large")
            await self._reject(scope, receive, send)
            return

        received = 0
        response_started = False

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    if is_upload:
                        record_rejection("body_too_large")
                    raise BodyTooLargeError(self.max_bytes)
            return message

        async def tracked_send(message: Message) -> None:
            nonlocal response_started
            if message["type"] == "http.response.start":
                response_started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracked_send)
        except BodyTooLargeError:
            if response_started:
                raise
            await self._reject(scope, receive, send)

    async def _reject(self, scope: Scope, receive: Receive, send: Send) -> None:
        exc = BodyTooLargeError(self.max_bytes)
        # the client may still be sending: close the connection rather than drain a huge body
        response = problem_response(ProblemError(exc.status, exc.detail, code=exc.code, headers={"Connection": "close"}))
        await response(scope, receive, send)


class ScopedCORSMiddleware:
    """Cross-origin reads of the paths under ``prefixes`` only (Starlette's CORS handling): a CesiumJS
    or deck.gl page on any origin may load the 3D Tiles with its bearer token. Any origin is allowed
    because the token travels in the ``Authorization`` header, never in a cookie."""

    def __init__(self, app: ASGIApp, prefixes: tuple[str, ...]) -> None:
        self.app = app
        self.prefixes = prefixes
        self.cors = CORSMiddleware(
            app,
            allow_origins=["*"],
            allow_methods=["GET"],
            allow_headers=["Authorization", "If-None-Match"],
            expose_headers=["ETag", "X-Tile-Version"],
            max_age=600,
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["path"].startswith(self.prefixes):
            await self.cors(scope, receive, send)
        else:
            await self.app(scope, receive, send)
