"""The one settings object of the service (``FLEETMAP_*`` environment variables), read once."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from fusion.config import FusionConfig

MIB = 1024 * 1024


class Settings(BaseSettings):
    """Deployment configuration. Units: metres, seconds, bytes."""

    model_config = SettingsConfigDict(env_prefix="FLEETMAP_", env_file=None, extra="ignore")

    data_dir: Path = Field(default=Path("./fleetmap-data"), description="Root of embedded state")
    database_url: str = Field(default="", description="SQLAlchemy URL; empty: SQLite under data_dir")
    broker_url: str = Field(default="", description="Celery broker URL; empty: embedded worker, no broker")
    blob_url: str = Field(default="", description="Blob store URL; empty: file://<data_dir>/blobs")
    tile_size: float = Field(default=64.0, gt=0, description="Tile edge length, metres")
    origin: str = Field(default="48.2620,11.6670,480.0", description="Map frame origin 'lat,lon,alt'")
    fuse_debounce_s: float = Field(default=30.0, ge=0)
    fuse_max_wait_s: float = Field(default=600.0, ge=0)
    auth: Literal["on", "off"] = "on"
    max_upload_bytes: int = Field(default=64 * MIB, gt=0)
    max_faces: int = Field(default=2_000_000, gt=0)
    max_coordinate_m: float = Field(default=1000.0, gt=0)
    fusion_preset: str = "cpu"
    fusion_set: str = Field(
        default="",
        description="Overrides of the preset's FusionConfig fields, 'KEY=VALUE;KEY=VALUE' (as `fleetmap bench "
        "--set`), e.g. 'realign_share=0.5;realign_iterations_fraction=0.5'; checked at start-up",
    )
    fusion_queue: str = "fusion"
    scheduler_interval_s: float = Field(default=5.0, gt=0)
    lease_s: float = Field(
        default=120.0, gt=0, description="Fusion lease per tile, seconds; renewed every lease_s/3 while a worker lives"
    )
    fuse_requeue_s: float = Field(default=600.0, gt=0, description="Re-send a job still queued after this")
    fusion_time_limit_s: float = Field(default=3600.0, gt=0, description="Soft time limit of one fusion")
    # PostgreSQL connection handling (ignored on SQLite). Small timeouts: an outage must give quick
    # 503s, never requests that hang.
    db_pool_size: int = Field(default=10, ge=1, description="Connections kept open per process")
    db_max_overflow: int = Field(default=20, ge=0, description="Extra connections under load per process")
    db_pool_timeout_s: float = Field(default=5.0, gt=0, description="Wait for a free pooled connection")
    db_connect_timeout_s: int = Field(default=5, ge=1, description="TCP/TLS connect timeout, seconds")
    db_statement_timeout_ms: int = Field(default=30_000, ge=0, description="Per statement; 0: none")
    db_pool_recycle_s: float = Field(default=1800.0, gt=0, description="Reopen connections older than this")
    db_ping_idle_s: float = Field(
        default=1.0,
        ge=0,
        description="Ping a pooled PostgreSQL connection on checkout only after it sat idle this long "
        "(0: on every checkout); a connection that died in use invalidates the pool and the upload is "
        "retried once",
    )
    auth_cache_s: float = Field(
        default=5.0,
        ge=0,
        description="Cache valid bearer tokens this long per API process (0: off); a revocation takes "
        "effect within this many seconds (at once in the process that revoked)",
    )
    torch_threads: int = Field(
        default=0,
        ge=0,
        description="torch intra-op threads of a fusion worker process (0: torch's default, every core); "
        "set 1-2 where the worker shares the host with the API and the database",
    )
    worker_metrics_port: int = Field(
        default=0,
        ge=0,
        le=65535,
        description="Port of a fusion worker's own Prometheus exporter (GET /metrics); 0: off. The "
        "embedded worker child uses it too",
    )
    log_level: str = "INFO"
    log_json: bool = False

    @field_validator("auth", mode="before")
    @classmethod
    def _auth_bool(cls, value: object) -> object:
        """Accept the usual boolean spellings for ``FLEETMAP_AUTH``."""
        if isinstance(value, bool):
            return "on" if value else "off"
        if isinstance(value, str):
            lowered = value.strip().lower()
            if lowered in {"1", "true", "yes", "on"}:
                return "on"
            if lowered in {"0", "false", "no", "off"}:
                return "off"
        return value

    @model_validator(mode="after")
    def _fusion_config_valid(self) -> Settings:
        """An unknown preset, key or value stops the process at start-up, not at its first fusion."""
        try:
            fusion_config(self)
        except ValueError as exc:
            raise ValueError(f"FLEETMAP_FUSION_PRESET / FLEETMAP_FUSION_SET: {exc}") from None
        return self

    @property
    def auth_enabled(self) -> bool:
        return self.auth == "on"

    @property
    def embedded(self) -> bool:
        """True when no broker server is configured (jobs run inside the serve process)."""
        return not self.broker_url

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'fleetmap.db').resolve()}"

    @property
    def resolved_blob_url(self) -> str:
        if self.blob_url:
            return self.blob_url
        return f"file://{(self.data_dir / 'blobs').resolve()}"

    @property
    def origin_lla(self) -> tuple[float, float, float]:
        """The map frame's geodetic origin (degrees, degrees, metres)."""
        parts = [float(p) for p in self.origin.split(",")]
        if len(parts) != 3:
            raise ValueError("FLEETMAP_ORIGIN must be 'lat,lon,alt'")
        return parts[0], parts[1], parts[2]


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings (read from the environment once)."""
    return Settings()


def fusion_config(settings: Settings) -> FusionConfig:
    """The configured preset (``FLEETMAP_FUSION_PRESET``: ``cpu``, ``paper`` or ``tiny``) with the overrides
    of ``FLEETMAP_FUSION_SET``; raises ``ValueError`` naming what does not parse."""
    config = FusionConfig.preset(settings.fusion_preset)
    items = [item.strip() for item in settings.fusion_set.split(";") if item.strip()]
    return config.with_overrides(items) if items else config
