"""A submap's monocular drift correction beside its refined pose (``submaps.drift_refined``: scale and bend
of its local frame, ``fusion.drift.Drift.to_json``; NULL: none, the submap is rigid as uploaded).

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-05
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("submaps") as batch:
        batch.add_column(sa.Column("drift_refined", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("submaps") as batch:
        batch.drop_column("drift_refined")
