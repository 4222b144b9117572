"""Database tables (SQLAlchemy 2, typed). The schema is only ever changed by an Alembic migration.

Frames: ``bbox_min``/``bbox_max`` are in the submap's local frame (metres); ``pose_gps`` and
``pose_refined`` map local → map frame (``{"t": [x, y, z], "q": [w, x, y, z]}``).
Timestamps are timezone-aware UTC on every backend (see :class:`UTCDateTime`).
"""

from __future__ import annotations

import enum
import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    ForeignKeyConstraint,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    false,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> datetime:
    """Now, timezone-aware UTC."""
    return datetime.now(UTC)


def new_id() -> str:
    """A new random UUID as a string (primary key of submaps, jobs, tokens)."""
    return str(uuid.uuid4())


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on every backend (SQLite stores them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map = {datetime: UTCDateTime(), dict[str, Any]: JSON(), list[Any]: JSON()}


class Role(enum.StrEnum):
    vehicle = "vehicle"
    operator = "operator"
    reader = "reader"


class TileState(enum.StrEnum):
    dirty = "dirty"
    queued = "queued"
    fusing = "fusing"
    fused = "fused"
    failed = "failed"


class JobState(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"


class JobKind(enum.StrEnum):
    align = "align"  # the poses of a region's unaligned submaps, over the region's tiles
    reconstruct = "reconstruct"  # one tile's field and mesh, poses held


class JobTrigger(enum.StrEnum):
    auto = "auto"
    operator = "operator"


class Token(Base):
    """A bearer token, stored only as the sha256 of its secret. For vehicles, ``name`` is the agent_id."""

    __tablename__ = "tokens"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200), index=True)
    role: Mapped[str] = mapped_column(String(16))
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(default=None)


class DrivingSession(Base):
    """One drive of one agent; its submaps are ordered by ``seq``."""

    __tablename__ = "sessions"

    session_id: Mapped[str] = mapped_column(String(255), primary_key=True)
    agent_id: Mapped[str] = mapped_column(String(200), index=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Submap(Base):
    """An uploaded submap: its meta, the mesh blob it names, and its poses."""

    __tablename__ = "submaps"
    __table_args__ = (UniqueConstraint("session_id", "seq"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    session_id: Mapped[str] = mapped_column(String(255), ForeignKey("sessions.session_id"))
    seq: Mapped[int] = mapped_column(Integer)
    agent_id: Mapped[str] = mapped_column(String(200), index=True)
    captured_at: Mapped[datetime]
    meta: Mapped[dict[str, Any]]
    content_sha256: Mapped[str] = mapped_column(String(64))
    mesh_sha256: Mapped[str] = mapped_column(String(64), index=True)
    mesh_bytes: Mapped[int] = mapped_column(BigInteger)
    face_count: Mapped[int] = mapped_column(Integer)
    bbox_min: Mapped[list[Any]]
    bbox_max: Mapped[list[Any]]
    pose_gps: Mapped[dict[str, Any]]
    gps_sigma_trans_m: Mapped[float] = mapped_column(Float)
    gps_sigma_rot_deg: Mapped[float] = mapped_column(Float)
    odometry: Mapped[dict[str, Any]]
    odometry_sigma_trans_m: Mapped[float] = mapped_column(Float)
    odometry_sigma_rot_deg: Mapped[float] = mapped_column(Float)
    pose_refined: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    refined_at: Mapped[datetime | None] = mapped_column(default=None)
    # the monocular drift correction of its local frame found with the refined pose (``fusion.drift``:
    # ``{"scale", "bend_yaw_rad_per_m", "bend_pitch_rad_per_m", "axis"}``; written with the pose; NULL: none)
    drift_refined: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    # the tiles its surface reaches at the refined pose, [[i, j], ...] (``fusion.tiles.surface_tiles`` with
    # ``refusion_band_m``; written with the pose): a tile is fused again for this submap only if it is here
    surface_tiles: Mapped[list[Any] | None] = mapped_column(default=None)
    # the refined pose came from an incremental alignment (against a held map: it never moved that map),
    # not from a joint one; counts towards its region's re-alignment (``FusionConfig.realign_share``). NULL:
    # aligned before this was recorded (counts as joint)
    aligned_incrementally: Mapped[bool | None] = mapped_column(Boolean, default=None)
    home_i: Mapped[int] = mapped_column(Integer)
    home_j: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class SubmapTile(Base):
    """Membership: submap ``submap_id`` touches tile ``(i, j)``."""

    __tablename__ = "submap_tiles"
    __table_args__ = (Index("ix_submap_tiles_i_j", "i", "j"),)

    submap_id: Mapped[str] = mapped_column(String(36), ForeignKey("submaps.id"), primary_key=True)
    i: Mapped[int] = mapped_column(Integer, primary_key=True)
    j: Mapped[int] = mapped_column(Integer, primary_key=True)


class Tile(Base):
    """Scheduling state of tile ``(i, j)``; the source of truth for what needs fusing.

    ``dirty_generation`` grows with every upload touching the tile; ``fused_generation`` is the
    dirty generation the latest successful fusion covered. A lease (``lease_owner``,
    ``lease_until``) guarantees one fusion per tile at a time.
    """

    __tablename__ = "tiles"

    i: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    j: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    state: Mapped[str] = mapped_column(String(16), default=TileState.dirty.value, index=True)
    version: Mapped[int] = mapped_column(Integer, default=0)
    dirty_generation: Mapped[int] = mapped_column(Integer, default=0)
    fused_generation: Mapped[int] = mapped_column(Integer, default=0)
    dirty_since: Mapped[datetime | None] = mapped_column(default=None)
    last_upload_at: Mapped[datetime | None] = mapped_column(default=None)
    lease_owner: Mapped[str | None] = mapped_column(String(200), default=None)
    lease_until: Mapped[datetime | None] = mapped_column(default=None)
    job_id: Mapped[str | None] = mapped_column(String(36), default=None)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    last_error: Mapped[str | None] = mapped_column(Text, default=None)
    fused_at: Mapped[datetime | None] = mapped_column(default=None)
    # the field the tile's last alignment trained (a torch state dict blob): later alignments track new
    # submaps against it instead of re-training the map
    align_field_sha256: Mapped[str | None] = mapped_column(String(64), default=None)
    # the field the tile's last reconstruction trained, at the held poses of its submaps: the warm start of
    # its re-fusion after an incremental alignment added submaps (cleared when an alignment trains the tile)
    recon_field_sha256: Mapped[str | None] = mapped_column(String(64), default=None)
    # that field is the last one carried along with the tile's surface by a re-alignment that brought the tile
    # no new submap (``fusion.field.moved_state``): its re-fusion needs fewer steps (WarmKind "carried")
    recon_field_carried: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)


class FusionJob(Base):
    """One fusion job. ``reconstruct``: tile (``tile_i``, ``tile_j``), covering its ``dirty_generation`` at
    ``generation``. ``align``: the region ``tiles`` (``[[i, j], ...]``; ``tile_i``/``tile_j`` its first)."""

    __tablename__ = "fusion_jobs"
    __table_args__ = (
        ForeignKeyConstraint(["tile_i", "tile_j"], ["tiles.i", "tiles.j"]),
        Index("ix_fusion_jobs_tile_state", "tile_i", "tile_j", "state"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    tile_i: Mapped[int] = mapped_column(Integer)
    tile_j: Mapped[int] = mapped_column(Integer)
    state: Mapped[str] = mapped_column(String(16), default=JobState.queued.value)
    kind: Mapped[str] = mapped_column(String(16), default=JobKind.reconstruct.value, server_default="reconstruct")
    tiles: Mapped[list[Any] | None] = mapped_column(default=None)
    # align only: a joint re-alignment of the region (every submap whose tiles all lie in ``tiles`` free, from
    # its refined pose; the poses rewritten) rather than the alignment of its new submaps against the map
    realign: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    trigger: Mapped[str] = mapped_column(String(16), default=JobTrigger.auto.value)
    generation: Mapped[int] = mapped_column(Integer, default=0)
    input_fingerprint: Mapped[str | None] = mapped_column(String(64), default=None)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    # When the job was last handed to the broker; the scheduler's sweeper re-sends jobs queued too long.
    enqueued_at: Mapped[datetime | None] = mapped_column(default=None)
    started_at: Mapped[datetime | None] = mapped_column(default=None)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    metrics: Mapped[dict[str, Any] | None] = mapped_column(default=None)


class TileVersion(Base):
    """A successful fusion of a tile: the fused mesh blobs (PLY and GLB) and how they were made."""

    __tablename__ = "tile_versions"
    __table_args__ = (
        UniqueConstraint("tile_i", "tile_j", "version"),
        ForeignKeyConstraint(["tile_i", "tile_j"], ["tiles.i", "tiles.j"]),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    tile_i: Mapped[int] = mapped_column(Integer)
    tile_j: Mapped[int] = mapped_column(Integer)
    version: Mapped[int] = mapped_column(Integer)
    job_id: Mapped[str | None] = mapped_column(String(36), ForeignKey("fusion_jobs.id"), default=None)
    mesh_sha256: Mapped[str] = mapped_column(String(64))
    glb_sha256: Mapped[str | None] = mapped_column(String(64), default=None)
    border_sha256: Mapped[str | None] = mapped_column(String(64), default=None)
    input_fingerprint: Mapped[str | None] = mapped_column(String(64), default=None)
    metrics: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    fusion_config: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
