"""``GET /v1/capabilities``: limits and frame, so vehicles need no out-of-band configuration."""

from __future__ import annotations

from fastapi import APIRouter, Request

from service.api.deps import AnyRole, SettingsDep
from service.api.problems import problem_responses
from service.api.schemas import Capabilities, Origin

router = APIRouter(prefix="/v1/capabilities", tags=["capabilities"])


@router.get(
    "", operation_id="getCapabilities", response_model=Capabilities, responses=problem_responses(401, 403)
)
def get_capabilities(request: Request, settings: SettingsDep, _principal: AnyRole) -> Capabilities:
    """Upload limits (bytes, faces, metres), tile size (metres) and the map frame's geodetic origin."""
    lat, lon, alt = settings.origin_lla
    return Capabilities(
        max_upload_bytes=settings.max_upload_bytes,
        max_faces=settings.max_faces,
        max_coordinate_m=settings.max_coordinate_m,
        tile_size_m=settings.tile_size,
        origin=Origin(lat=lat, lon=lon, alt=alt),
        labels_url=str(request.url_for("list_labels")),
    )
