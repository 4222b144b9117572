"""The FastAPI application factory.

``create_app(settings)`` wires settings, database, blob store, middleware, problem handlers and
routers. Its lifespan upgrades the database in embedded mode and then calls the background hook
``service.schedule.start_background(app)`` (scheduler + embedded worker, owned by the jobs
module), which leaves its handle in ``app.state.scheduler``; shutdown calls
``service.schedule.stop_background(app)`` if defined, else ``app.state.scheduler.stop()``.
``app.state`` carries ``settings``, ``engine``, ``session_factory`` and ``blobs``.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool
from fastapi.openapi.utils import get_openapi
from fastapi.staticfiles import StaticFiles

from service.api.middleware import BodyLimitMiddleware, RequestContextMiddleware, ScopedCORSMiddleware
from service.api.problems import PROBLEM_MEDIA_TYPE, install_problem_handlers
from service.api.routes import (
    capabilities,
    jobs,
    labels,
    ops,
    sessions,
    submaps,
    tile_details,
    tiles,
    tiles3d,
)
from service.api.schemas import SubmapMeta
from service.schedule import start_background, stop_background
from service.settings import Settings, get_settings
from service.store.blobs import blob_store_from_url
from service.store.db import engine_from_settings, make_sessionmaker
from service.store.migrate import upgrade
from service.telemetry import configure_logging

log = logging.getLogger(__name__)

API_DESCRIPTION = """Crowd-sourced semantic mapping: vehicles upload semantic submaps, the service
fuses them tile by tile and serves fused semantic meshes. Every error is an RFC 9457 problem document
(`application/problem+json`). Frames: map frame = ENU metres around the configured origin."""


def _lifespan(migrate: bool, background: bool) -> Any:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if migrate:
            upgrade(app.state.engine)
        if background:
            start_background(app)
        try:
            yield
        finally:
            if background:
                await run_in_threadpool(stop_background, app)
            app.state.engine.dispose()

    return lifespan


def _openapi(app: FastAPI) -> dict[str, Any]:
    """OpenAPI with the multipart meta schema registered and errors only as problem+json."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(
        title=app.title,
        version=app.version,
        description=app.description,
        routes=app.routes,
        tags=app.openapi_tags,
    )
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    meta_schema = SubmapMeta.model_json_schema(ref_template="#/components/schemas/{model}")
    components.update(meta_schema.pop("$defs", {}))
    components["SubmapMeta"] = meta_schema
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            for status, response in operation.get("responses", {}).items():
                content = response.get("content", {})
                if str(status).startswith(("4", "5")) and PROBLEM_MEDIA_TYPE in content:
                    content.pop("application/json", None)
    app.openapi_schema = schema
    return schema


def create_app(
    settings: Settings | None = None, *, migrate: bool | None = None, background: bool = True
) -> FastAPI:
    """Build the API. ``migrate`` defaults to "upgrade on start in embedded mode" (no broker);
    ``background=False`` skips the scheduler/embedded-worker hook (tests of the API alone)."""
    settings = settings or get_settings()
    configure_logging(settings.log_level, settings.log_json)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    if migrate is None:
        migrate = settings.embedded

    app = FastAPI(
        title="fleetmap",
        version="1.0.0",
        description=API_DESCRIPTION,
        lifespan=_lifespan(migrate, background),
        openapi_tags=[
            {"name": "submaps", "description": "Upload and read submaps"},
            {"name": "tiles", "description": "Tile states, fusion, fused meshes"},
            {"name": "3dtiles", "description": "The fused map as OGC 3D Tiles 1.1 (CesiumJS, deck.gl)"},
            {"name": "jobs", "description": "Fusion jobs"},
            {"name": "sessions", "description": "Poses per driving session"},
            {"name": "labels", "description": "The semantic label set"},
            {"name": "capabilities", "description": "Deployment limits and frame"},
            {"name": "ops", "description": "Health, readiness, metrics, web viewer"},
        ],
    )
    app.state.settings = settings
    app.state.engine = engine_from_settings(settings)
    app.state.session_factory = make_sessionmaker(app.state.engine)
    app.state.blobs = blob_store_from_url(settings.resolved_blob_url)

    install_problem_handlers(app)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_upload_bytes)
    app.add_middleware(RequestContextMiddleware)
    app.add_middleware(ScopedCORSMiddleware, prefixes=(tiles3d.router.prefix + "/",))
    for module in (labels, capabilities, submaps, tiles, tile_details, tiles3d, jobs, sessions, ops):
        app.include_router(module.router)
    # The viewer's scripts and the vendored three.js (no token; not API routes, so not in the schema).
    app.mount("/static", StaticFiles(packages=[("service.api", "static")]), name="static")
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app
