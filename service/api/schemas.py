"""Wire models (requests and responses). Separate from the tables in ``service.store.models``.

Poses map a submap's local frame into the target frame: ``p = R(q) · p_local + t``, metres,
quaternion Hamilton ``[w, x, y, z]``.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import AwareDatetime, BaseModel, ConfigDict, Discriminator, Field, Tag, field_validator

from fusion.types import UNIT_QUATERNION_TOLERANCE

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Quat = Annotated[list[float], Field(min_length=4, max_length=4, description="[w, x, y, z], unit length")]
TileIndex = Annotated[list[int], Field(min_length=2, max_length=2, description="[i, j]")]
TileStateName = Literal["dirty", "queued", "fusing", "fused", "failed"]
JobStateName = Literal["queued", "running", "succeeded", "failed"]


def normalise_quaternion(q: list[float]) -> list[float]:
    """Unit quaternion from one within 1e-3 of unit length; raises ValueError otherwise."""
    if not all(math.isfinite(v) for v in q):
        raise ValueError("quaternion components must be finite")
    norm = math.sqrt(sum(v * v for v in q))
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        raise ValueError(
            f"quaternion must be unit length within {UNIT_QUATERNION_TOLERANCE} (norm {norm:.6f})"
        )
    return [v / norm for v in q]


class Pose(BaseModel):
    """Rigid transform local → target frame."""

    model_config = ConfigDict(extra="forbid")

    t: Vec3 = Field(description="Translation, metres")
    q: Quat

    @field_validator("t")
    @classmethod
    def _finite(cls, t: list[float]) -> list[float]:
        if not all(math.isfinite(v) for v in t):
            raise ValueError("translation components must be finite")
        return t

    @field_validator("q")
    @classmethod
    def _unit(cls, q: list[float]) -> list[float]:
        return normalise_quaternion(q)


class GpsPose(BaseModel):
    """A GPS pose given directly in the map frame."""

    model_config = ConfigDict(extra="forbid")

    pose: Pose


class GpsGeodetic(BaseModel):
    """A GPS pose given geodetically (WGS84 degrees, metres); ``q`` relative to local ENU axes."""

    model_config = ConfigDict(extra="forbid")

    lat: float = Field(ge=-90, le=90)
    lon: float = Field(ge=-180, le=180)
    alt: float = Field(allow_inf_nan=False)
    q: Quat

    @field_validator("q")
    @classmethod
    def _unit(cls, q: list[float]) -> list[float]:
        return normalise_quaternion(q)


def _gps_kind(value: Any) -> str | None:
    """Which GPS form an input is (so errors name only its fields); None: neither, an error."""
    if isinstance(value, dict):
        return "GpsPose" if "pose" in value else "GpsGeodetic"
    if isinstance(value, GpsPose | GpsGeodetic):
        return type(value).__name__
    return None


GpsChoice = Annotated[
    Annotated[GpsPose, Tag("GpsPose")] | Annotated[GpsGeodetic, Tag("GpsGeodetic")],
    Discriminator(_gps_kind),
]
UNION_TAGS = frozenset({"GpsPose", "GpsGeodetic"})  # pydantic puts the chosen tag in error locations


class Sigma(BaseModel):
    """1-sigma pose uncertainty."""

    model_config = ConfigDict(extra="forbid")

    trans_m: float = Field(gt=0, allow_inf_nan=False, description="Translation, metres")
    rot_deg: float = Field(gt=0, allow_inf_nan=False, description="Rotation, degrees")


class SubmapMeta(BaseModel):
    """The ``meta`` part of a submap upload."""

    model_config = ConfigDict(extra="forbid")

    agent_id: str = Field(min_length=1, max_length=200, examples=["veh-042"])
    session_id: str = Field(min_length=1, max_length=255, examples=["veh-042/2026-11-24T08:00:00Z"])
    seq: int = Field(ge=0, lt=2**31, examples=[17])
    captured_at: AwareDatetime
    gps: GpsChoice
    gps_sigma: Sigma = Sigma(trans_m=2.0, rot_deg=2.0)
    odometry: Pose
    odometry_sigma: Sigma = Sigma(trans_m=0.05, rot_deg=0.5)


class SubmapCreated(BaseModel):
    """Answer to an upload (201 stored, 200 idempotent retry)."""

    id: str
    session_id: str
    seq: int
    tiles: list[TileIndex]
    sha256: str = Field(description="sha256 of the uploaded mesh bytes")


class SubmapPublic(BaseModel):
    """A stored submap: its (normalised) meta plus poses and tiles."""

    id: str
    agent_id: str
    session_id: str
    seq: int
    captured_at: datetime
    gps: dict[str, Any] = Field(description="As uploaded (quaternion normalised)")
    gps_sigma: Sigma
    odometry: Pose
    odometry_sigma: Sigma
    pose_gps: Pose = Field(description="GPS pose in the map frame")
    pose_refined: Pose | None = Field(
        description="Map-frame pose refined by fusion; null until then. A joint re-alignment of its region "
        "(a job with `realign` true) may rewrite it later")
    refined_at: datetime | None = Field(description="When the submap was first aligned (its first `pose_refined`)")
    drift_refined: DriftCorrection | None = Field(
        default=None,
        description="The monocular drift correction of its local frame found with `pose_refined` (only with the "
        "fusion option `fine_drift`; null: none, the mesh is used as uploaded). The fused map holds the submap "
        "at `pose_refined` · D(p)")
    tiles: list[TileIndex]
    home_tile: TileIndex
    sha256: str = Field(description="sha256 of the mesh bytes")
    face_count: int
    created_at: datetime


class DriftCorrection(BaseModel):
    """D(p) in the submap's local frame (metres), about its origin: with `axis` a the horizontal direction ahead,
    b = z × a and x = p·a, p turned about z by `bend_yaw_rad_per_m`·x/2 and about b by `bend_pitch_rad_per_m`·x/2,
    then scaled by `scale`."""

    scale: float
    bend_yaw_rad_per_m: float
    bend_pitch_rad_per_m: float
    axis: Annotated[list[float], Field(min_length=2, max_length=2, description="[x, y], unit, local frame")]


class SessionPose(BaseModel):
    seq: int
    id: str
    pose_gps: Pose
    pose_refined: Pose | None


class Label(BaseModel):
    id: int
    name: str
    color: Annotated[list[int], Field(min_length=3, max_length=3, description="[r, g, b], 0..255")]


class Origin(BaseModel):
    lat: float
    lon: float
    alt: float


class Capabilities(BaseModel):
    max_upload_bytes: int
    max_faces: int
    max_coordinate_m: float
    tile_size_m: float
    origin: Origin
    labels_url: str


class TileLinks(BaseModel):
    self: str
    mesh: str


class TilePublic(BaseModel):
    i: int
    j: int
    state: TileStateName
    submaps: int = Field(description="Number of submaps touching the tile")
    sessions: int = Field(description="Number of distinct sessions among them")
    version: int = Field(description="Successful fusions so far (0: never fused)")
    fused_at: datetime | None
    progress: float = Field(ge=0, le=1)
    last_error: str | None
    job_id: str | None
    links: TileLinks


class TilePage(BaseModel):
    items: list[TilePublic]
    next_cursor: str | None = Field(description="Opaque; pass as `cursor` for the next page, null at the end")


class FuseAccepted(BaseModel):
    job_id: str
    tile: TileIndex


class JobPublic(BaseModel):
    id: str
    kind: Literal["align", "reconstruct"] = Field(
        description="`align`: refine the poses of a region's new submaps over `tiles` (writes "
        "`pose_refined`); `reconstruct`: fit one tile's field with the poses held and extract its mesh"
    )
    tile: TileIndex = Field(description="The tile (reconstruct), or the region's first tile (align)")
    tiles: list[TileIndex] = Field(description="Every tile the job covers: `[tile]`, or the region (align)")
    realign: bool = Field(
        False, description="align only: true when the job re-aligns the region jointly (the poses of its aligned "
        "submaps may move and are rewritten), because a large share of the region's sessions had been added "
        "incrementally, against a map they could not move. A tile the new sessions do not reach and whose "
        "surface moved less than `realign_keep_m` (0.05 m) goes back to `fused` with its mesh "
        "(`metrics.kept_tiles`; `metrics.tile_moved_m` per tile, null where a new submap is); every other tile "
        "is reconstructed, starting from its last field carried by the tile's rigid motion (`refusion_carry`: "
        "`metrics.carried_tiles`), with fewer steps where no new submap reaches the tile "
        "(`refusion_carried_fraction`: `metrics.quiet_tiles`). "
        "With `realign_hold` (off by default) the whole map is first held where it stood")
    state: JobStateName
    trigger: Literal["auto", "operator"]
    progress: float
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    error: str | None
    metrics: dict[str, Any] | None = Field(
        description="What the job measured: align jobs list `reconstruct_jobs`, `kept_tiles`, `carried_tiles`, `quiet_tiles`, `joined_tiles`, "
        "`aligned_submaps`, losses and timing; reconstruct jobs the mesh's size, timing and `version`")


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class Readiness(BaseModel):
    status: Literal["ok"] = "ok"
    checks: dict[str, str] = Field(description="Component → 'ok' or 'skipped'")


# ------------------------------------------------------------------ the viewer's reads (not in API.md)


class TileVersionLinks(BaseModel):
    ply: str = Field(description="This version's mesh as PLY (immutable, cacheable forever)")
    glb: str = Field(description="This version's mesh as GLB")


class TileVersionPublic(BaseModel):
    """One successful fusion of a tile."""

    version: int = Field(ge=1)
    fused_at: datetime = Field(description="When the fusion that made it committed")
    job_id: str | None = Field(description="The fusion job that made it (null for versions made outside a job)")
    mesh_sha256: str = Field(description="sha256 of the stored PLY")
    glb_sha256: str | None = Field(description="sha256 of the stored GLB, if one was stored")
    faces: int | None = Field(description="Triangles of the mesh, if recorded")
    vertices: int | None = Field(description="Vertices of the mesh, if recorded")
    links: TileVersionLinks


class TileVersionPage(BaseModel):
    items: list[TileVersionPublic] = Field(description="Newest first")
    next_cursor: str | None = Field(description="Opaque; pass as `cursor` for the next page, null at the end")


class TileSubmapPublic(BaseModel):
    """A submap the tile holds (its mesh and meta: `GET /v1/submaps/{id}`)."""

    id: str
    session_id: str
    seq: int
    agent_id: str
    captured_at: datetime
    refined: bool = Field(description="Whether a fusion has refined its pose (`pose_refined` set)")


class TileSubmapPage(BaseModel):
    items: list[TileSubmapPublic] = Field(description="Ordered by (session_id, seq)")
    next_cursor: str | None = Field(description="Opaque; pass as `cursor` for the next page, null at the end")


class JobList(BaseModel):
    items: list[JobPublic] = Field(description="Newest first")


class TrackPoint(BaseModel):
    seq: int
    pose_gps_t: Vec3 = Field(description="Translation of the submap's `pose_gps` (map frame, metres)")
    pose_refined_t: Vec3 | None = Field(
        description="Translation of its `pose_refined` (map frame, metres); null until a fusion refined it"
    )


class SessionTrack(BaseModel):
    """A driving session and its trajectory: one point per submap, ordered by `seq`."""

    session_id: str
    agent_id: str
    submaps: int = Field(description="Submaps of the session (all of them, not only those in the box)")
    points: list[TrackPoint] = Field(
        description="Every submap, or an even subsample of `max_points` (first and last kept) when it has more"
    )


class SessionTrackPage(BaseModel):
    items: list[SessionTrack] = Field(description="Ordered by session_id")
    next_cursor: str | None = Field(description="Opaque; pass as `cursor` for the next page, null at the end")
