"""Fusion jobs of two kinds: ``align`` (a region's poses, over ``tiles``) and ``reconstruct`` (a tile);
each tile keeps the blob of the field its last alignment trained (incremental alignment tracks new
submaps against it).

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-01
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("fusion_jobs") as batch:
        batch.add_column(sa.Column("kind", sa.String(length=16), nullable=False, server_default="reconstruct"))
        batch.add_column(sa.Column("tiles", sa.JSON(), nullable=True))
    with op.batch_alter_table("tiles") as batch:
        batch.add_column(sa.Column("align_field_sha256", sa.String(length=64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("tiles") as batch:
        batch.drop_column("align_field_sha256")
    with op.batch_alter_table("fusion_jobs") as batch:
        batch.drop_column("tiles")
        batch.drop_column("kind")
