"""Re-aligning a region grown incrementally: each submap records whether its refined pose came from an
incremental alignment (``submaps.aligned_incrementally``; NULL before this: counted as joint), and an align
job whether it re-aligns its region jointly (``fusion_jobs.realign``).

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-04
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("submaps") as batch:
        batch.add_column(sa.Column("aligned_incrementally", sa.Boolean(), nullable=True))
    with op.batch_alter_table("fusion_jobs") as batch:
        batch.add_column(sa.Column("realign", sa.Boolean(), nullable=False, server_default=sa.false()))


def downgrade() -> None:
    with op.batch_alter_table("fusion_jobs") as batch:
        batch.drop_column("realign")
    with op.batch_alter_table("submaps") as batch:
        batch.drop_column("aligned_incrementally")
