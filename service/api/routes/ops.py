"""Operations: liveness, readiness, Prometheus metrics and the web viewer (no token needed)."""

from __future__ import annotations

import logging
from importlib import resources
from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.responses import HTMLResponse

from service import telemetry
from service.api.deps import SessionDep, SettingsDep
from service.api.problems import ProblemError, problem_responses
from service.api.schemas import Health, Readiness
from service.settings import Settings
from service.store.db import ping

router = APIRouter(tags=["ops"])
log = logging.getLogger(__name__)

BROKER_TIMEOUT_S = 3.0


def _ping_broker(settings: Settings) -> None:
    from kombu import Connection  # lazily: only deployments with a broker need it

    with Connection(settings.broker_url, connect_timeout=BROKER_TIMEOUT_S) as conn:
        conn.ensure_connection(max_retries=1, timeout=BROKER_TIMEOUT_S)


@router.get("/healthz", operation_id="healthz", response_model=Health)
def healthz() -> Health:
    """The process is alive."""
    return Health()


@router.get("/readyz", operation_id="readyz", response_model=Readiness, responses=problem_responses(503))
def readyz(request: Request, settings: SettingsDep) -> Readiness:
    """Database, broker (skipped when embedded) and blob store reachable; 503 otherwise."""
    checks: dict[str, str] = {}
    failures: list[dict[str, Any]] = []
    probes = {
        "database": lambda: ping(request.app.state.engine),
        "blob_store": lambda: request.app.state.blobs.ping(),
        "broker": None if settings.embedded else (lambda: _ping_broker(settings)),
    }
    for name, probe in probes.items():
        if probe is None:
            checks[name] = "skipped"
            continue
        try:
            probe()
            checks[name] = "ok"
        except Exception as exc:  # noqa: BLE001 - any failure means "not ready"
            log.warning("readiness check %s failed: %s", name, exc)
            failures.append(
                {"component": name, "loc": [name], "msg": exc.__class__.__name__, "type": "unreachable"}
            )
    if failures:
        names = ", ".join(f["component"] for f in failures)
        raise ProblemError(503, f"not ready: {names} unreachable", code="not_ready", errors=failures)
    return Readiness(checks=checks)


@router.get(
    "/metrics",
    operation_id="metrics",
    response_class=Response,
    responses={
        200: {
            "description": "Prometheus text format",
            "content": {"text/plain": {"schema": {"type": "string"}}},
        }
    },
)
def get_metrics(db: SessionDep) -> Response:
    """Prometheus metrics: uploads, bytes, rejections by reason, tiles by state, queue depth, fusion time."""
    telemetry.refresh_from_db(db)
    return Response(telemetry.render(), media_type="text/plain; version=0.0.4; charset=utf-8")


@router.get("/", operation_id="viewer", response_class=HTMLResponse)
def viewer(settings: SettingsDep) -> HTMLResponse:
    """The web viewer (a 3D map of the fused tiles). The page's ``fleetmap-auth`` meta tag says whether
    the API wants a token (``off``: the viewer connects without asking for one, e.g. ``fleetmap demo``)."""
    page = resources.files("service.api").joinpath("static/index.html").read_text(encoding="utf-8")
    mode = "on" if settings.auth_enabled else "off"
    return HTMLResponse(page.replace('<meta name="fleetmap-auth" content="on">',
                                     f'<meta name="fleetmap-auth" content="{mode}">', 1))
