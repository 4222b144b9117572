"""Each aligned submap records the tiles its surface reaches at its refined pose: a tile is fused again
for a new submap only where its surface comes within ``refusion_band_m`` of it, not wherever its GPS
uncertainty reaches (``worker.inputs.shapes_tile``). Submaps aligned before this hold NULL (they count
in every tile they touch).

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-04
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("submaps") as batch:
        batch.add_column(sa.Column("surface_tiles", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("submaps") as batch:
        batch.drop_column("surface_tiles")
