"""Initial schema: tokens, sessions, submaps, submap_tiles, tiles, fusion_jobs, tile_versions.

Revision ID: 0001
Revises:
Create Date: 2026-11-25
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # a frozen, declarative schema snapshot (Alembic): its like table shapes are deliberate (duplicates)
    op.create_table(
        "sessions",
        sa.Column("session_id", sa.String(length=255), nullable=False),
        sa.Column("agent_id", sa.String(length=200), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("session_id", name=op.f("pk_sessions")),
    )
    op.create_index(op.f("ix_sessions_agent_id"), "sessions", ["agent_id"], unique=False)

    op.create_table(
        "tiles",
        sa.Column("i", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("j", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("dirty_generation", sa.Integer(), nullable=False),
        sa.Column("fused_generation", sa.Integer(), nullable=False),
        sa.Column("dirty_since", sa.DateTime(timezone=True), nullable=True),
        sa.Column("last_upload_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("lease_owner", sa.String(length=200), nullable=True),
        sa.Column("lease_until", sa.DateTime(timezone=True), nullable=True),
        sa.Column("job_id", sa.String(length=36), nullable=True),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("last_error", sa.Text(), nullable=True),
        sa.Column("fused_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("i", "j", name=op.f("pk_tiles")),
    )
    op.create_index(op.f("ix_tiles_state"), "tiles", ["state"], unique=False)

    op.create_table(
        "tokens",
        sa.Column("id", sa.String(length=36), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("role", sa.String(length=16), nullable=False),
        sa.Column("token_hash", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("revoked_at", sa.DateTime(timezone=True), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_tokens")),
        sa.UniqueConstraint("token_hash", name=op.f("uq_tokens_token_hash")),
    )
    op.create_index(op.f("ix_tokens_name"), "tokens", ["name"], unique=False)

    op.create_table(
        "fusion_jobs",
        sa.Column("id", sa.String(length=36), nullable=False),
        sa.Column("tile_i", sa.Integer(), nullable=False),
        sa.Column("tile_j", sa.Integer(), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("trigger", sa.String(length=16), nullable=False),
        sa.Column("generation", sa.Integer(), nullable=False),
        sa.Column("input_fingerprint", sa.String(length=64), nullable=True),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("enqueued_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("metrics", sa.JSON(), nullable=True),
        sa.ForeignKeyConstraint(
            ["tile_i", "tile_j"], ["tiles.i", "tiles.j"], name=op.f("fk_fusion_jobs_tile_i_tiles")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_fusion_jobs")),
    )
    op.create_index("ix_fusion_jobs_tile_state", "fusion_jobs", ["tile_i", "tile_j", "state"], unique=False)

    op.create_table(
        "submaps",
        sa.Column("id", sa.String(length=36), nullable=False),
        sa.Column("session_id", sa.String(length=255), nullable=False),
        sa.Column("seq", sa.Integer(), nullable=False),
        sa.Column("agent_id", sa.String(length=200), nullable=False),
        sa.Column("captured_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("meta", sa.JSON(), nullable=False),
        sa.Column("content_sha256", sa.String(length=64), nullable=False),
        sa.Column("mesh_sha256", sa.String(length=64), nullable=False),
        sa.Column("mesh_bytes", sa.BigInteger(), nullable=False),
        sa.Column("face_count", sa.Integer(), nullable=False),
        sa.Column("bbox_min", sa.JSON(), nullable=False),
        sa.Column("bbox_max", sa.JSON(), nullable=False),
        sa.Column("pose_gps", sa.JSON(), nullable=False),
        sa.Column("gps_sigma_trans_m", sa.Float(), nullable=False),
        sa.Column("gps_sigma_rot_deg", sa.Float(), nullable=False),
        sa.Column("odometry", sa.JSON(), nullable=False),
        sa.Column("odometry_sigma_trans_m", sa.Float(), nullable=False),
        sa.Column("odometry_sigma_rot_deg", sa.Float(), nullable=False),
        sa.Column("pose_refined", sa.JSON(), nullable=True),
        sa.Column("refined_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("home_i", sa.Integer(), nullable=False),
        sa.Column("home_j", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.session_id"], name=op.f("fk_submaps_session_id_sessions")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_submaps")),
        sa.UniqueConstraint("session_id", "seq", name=op.f("uq_submaps_session_id_seq")),
    )
    op.create_index(op.f("ix_submaps_agent_id"), "submaps", ["agent_id"], unique=False)
    op.create_index(op.f("ix_submaps_mesh_sha256"), "submaps", ["mesh_sha256"], unique=False)

    op.create_table(
        "submap_tiles",
        sa.Column("submap_id", sa.String(length=36), nullable=False),
        sa.Column("i", sa.Integer(), nullable=False),
        sa.Column("j", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(
            ["submap_id"], ["submaps.id"], name=op.f("fk_submap_tiles_submap_id_submaps")
        ),
        sa.PrimaryKeyConstraint("submap_id", "i", "j", name=op.f("pk_submap_tiles")),
    )
    op.create_index("ix_submap_tiles_i_j", "submap_tiles", ["i", "j"], unique=False)

    op.create_table(
        "tile_versions",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("tile_i", sa.Integer(), nullable=False),
        sa.Column("tile_j", sa.Integer(), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("job_id", sa.String(length=36), nullable=True),
        sa.Column("mesh_sha256", sa.String(length=64), nullable=False),
        sa.Column("glb_sha256", sa.String(length=64), nullable=True),
        sa.Column("border_sha256", sa.String(length=64), nullable=True),
        sa.Column("input_fingerprint", sa.String(length=64), nullable=True),
        sa.Column("metrics", sa.JSON(), nullable=True),
        sa.Column("fusion_config", sa.JSON(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["job_id"], ["fusion_jobs.id"], name=op.f("fk_tile_versions_job_id_fusion_jobs")
        ),
        sa.ForeignKeyConstraint(
            ["tile_i", "tile_j"], ["tiles.i", "tiles.j"], name=op.f("fk_tile_versions_tile_i_tiles")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_tile_versions")),
        sa.UniqueConstraint(
            "tile_i", "tile_j", "version", name=op.f("uq_tile_versions_tile_i_tile_j_version")
        ),
    )


def downgrade() -> None:
    op.drop_table("tile_versions")
    op.drop_index("ix_submap_tiles_i_j", table_name="submap_tiles")

    op.drop_table("submap_tiles")
    op.drop_index(op.f("ix_submaps_mesh_sha256"), table_name="submaps")
    op.drop_index(op.f("ix_submaps_agent_id"), table_name="submaps")

    op.drop_table("submaps")
    op.drop_index("ix_fusion_jobs_tile_state", table_name="fusion_jobs")

    op.drop_table("fusion_jobs")
    op.drop_index(op.f("ix_tokens_name"), table_name="tokens")

    op.drop_table("tokens")
    op.drop_index(op.f("ix_tiles_state"), table_name="tiles")

    op.drop_table("tiles")
    op.drop_index(op.f("ix_sessions_agent_id"), table_name="sessions")

    op.drop_table("sessions")
