"""Whether a tile's reconstruction field is its last one carried along with its surface by a re-alignment
that brought the tile no new submap (``tiles.recon_field_carried``): its re-fusion then needs only
``FusionConfig.refusion_carried_fraction`` of the steps.

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-06
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("tiles") as batch:
        batch.add_column(sa.Column("recon_field_carried", sa.Boolean(), nullable=False, server_default=sa.false()))


def downgrade() -> None:
    with op.batch_alter_table("tiles") as batch:
        batch.drop_column("recon_field_carried")
