"""Submap ingest, the HTTP half: parse and validate an upload (meta, mesh), compute its map-frame GPS
pose, tiles and hashes. Nothing is stored here: ``service.store.submaps.store`` does that, after
every check passed, so a rejected upload leaves nothing behind.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

import numpy as np
from pydantic import ValidationError

from fusion.geo import geodetic_to_map, parse_origin
from fusion.labels import NUM_CLASSES
from fusion.meshio import MeshLimits, read_submap_ply
from fusion.tiles import home_tile, submap_tiles
from fusion.types import Pose, Sigma
from service.api.problems import ProblemError, validation_error
from service.api.schemas import UNION_TAGS, GpsPose, SubmapMeta
from service.settings import Settings
from service.store.submaps import NewSubmap


def parse_meta(raw: bytes | str) -> SubmapMeta:
    """The ``meta`` part as a validated model; 422 problem (code ``invalid_meta``) otherwise."""
    try:
        data = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        msg = f"meta is not valid JSON: {exc}"
        errors = [validation_error(["meta"], msg, "json_invalid")]
        raise ProblemError(422, msg, code="invalid_meta", errors=errors) from exc
    if not isinstance(data, dict):
        msg = "meta must be a JSON object"
        raise ProblemError(422, msg, code="invalid_meta", errors=[validation_error(["meta"], msg, "dict_type")])
    try:
        return SubmapMeta.model_validate(data)
    except ValidationError as exc:
        errors = [
            validation_error(
                ["meta", *(part for part in err["loc"] if part not in UNION_TAGS)], err["msg"], err["type"]
            )
            for err in exc.errors()
        ]
        raise ProblemError(422, "meta is invalid", code="invalid_meta", errors=errors) from exc


def map_pose_of(meta: SubmapMeta, settings: Settings) -> Pose:
    """The GPS pose local → map frame (converting a geodetic fix around the configured origin)."""
    if isinstance(meta.gps, GpsPose):
        return Pose(
            np.asarray(meta.gps.pose.t, dtype=np.float64), np.asarray(meta.gps.pose.q, dtype=np.float64)
        )
    gps = meta.gps
    return geodetic_to_map(
        gps.lat, gps.lon, gps.alt, np.asarray(gps.q, dtype=np.float64), parse_origin(settings.origin)
    )


def content_hash(meta_json: dict[str, Any], mesh_sha256: str) -> str:
    """Idempotency key: sha256 over the canonical (normalised) meta and the mesh's sha256."""
    canonical = json.dumps(meta_json, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(f"{canonical}\n{mesh_sha256}".encode()).hexdigest()


def prepare(meta: SubmapMeta, mesh_data: bytes, settings: Settings) -> NewSubmap:
    """Validate the mesh and compute poses, tiles and hashes (CPU-bound; no I/O)."""
    limits = MeshLimits(
        max_faces=settings.max_faces, max_coordinate_m=settings.max_coordinate_m, num_labels=NUM_CLASSES
    )
    mesh = read_submap_ply(mesh_data, limits)
    pose = map_pose_of(meta, settings)
    bbox_min = mesh.vertices.min(axis=0)
    bbox_max = mesh.vertices.max(axis=0)
    sigma = Sigma(meta.gps_sigma.trans_m, meta.gps_sigma.rot_deg)
    tiles = sorted(
        {(int(i), int(j)) for i, j in submap_tiles(bbox_min, bbox_max, pose, sigma, settings.tile_size)}
    )
    hi, hj = home_tile(mesh, pose, settings.tile_size)
    meta_json = meta.model_dump(mode="json")
    mesh_sha = hashlib.sha256(mesh_data).hexdigest()
    return NewSubmap(
        session_id=meta.session_id,
        seq=meta.seq,
        agent_id=meta.agent_id,
        captured_at=meta.captured_at,
        meta_json=meta_json,
        mesh_data=mesh_data,
        mesh_sha256=mesh_sha,
        content_sha256=content_hash(meta_json, mesh_sha),
        face_count=int(len(mesh.faces)),
        bbox_min=[float(v) for v in bbox_min],
        bbox_max=[float(v) for v in bbox_max],
        pose_gps=pose,
        gps_sigma=sigma,
        odometry=meta.odometry.model_dump(),
        odometry_sigma=Sigma(meta.odometry_sigma.trans_m, meta.odometry_sigma.rot_deg),
        tiles=tiles,
        home=(int(hi), int(hj)),
    )
