"""Alembic migrations run programmatically (``fleetmap db upgrade``; embedded serve upgrades on start)."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine

import migrations

ALEMBIC_INI = Path(migrations.__file__).resolve().parent / "alembic.ini"


def alembic_config() -> Config:
    """The packaged Alembic configuration (script location is the ``migrations`` package)."""
    return Config(str(ALEMBIC_INI))


def upgrade(engine: Engine, revision: str = "head") -> None:
    """Upgrade the database behind ``engine`` to ``revision`` in one transaction."""
    cfg = alembic_config()
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, revision)
