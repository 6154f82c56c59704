"""Foundation: users and logins, studies, participants, allocations, the audit log.

Revision ID: 0001
Revises:
Create Date: 2026-11-22
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

from app.schema import create_append_only_guard, drop_append_only_guard

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")


def _timestamp(name: str, *, nullable: bool = False) -> sa.Column[object]:
    return sa.Column(name, sa.DateTime(timezone=True), nullable=nullable)


def upgrade() -> None:
    op.create_table(
        "user",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("username", sa.String(64), nullable=False),
        sa.Column("password_hash", sa.String(255), nullable=False),
        sa.Column("role", sa.String(16), nullable=False),
        sa.Column("is_active", sa.Boolean(), nullable=False),
        _timestamp("created_at"),
        _timestamp("last_login_at", nullable=True),
        sa.CheckConstraint("role IN ('admin', 'experimenter', 'analyst')", name="role_known"),
        sa.UniqueConstraint("username"),
    )
    op.create_table(
        "login_session",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column(
            "user_id", sa.Integer(), sa.ForeignKey("user.id", ondelete="CASCADE"), nullable=False
        ),
        sa.Column("token_hash", sa.String(64), nullable=False),
        sa.Column("csrf_token", sa.String(64), nullable=False),
        _timestamp("created_at"),
        _timestamp("last_seen_at"),
        _timestamp("expires_at"),
        _timestamp("revoked_at", nullable=True),
        sa.Column("user_agent", sa.String(255), nullable=False),
        sa.Column("client_address", sa.String(64), nullable=False),
        sa.UniqueConstraint("token_hash"),
    )
    op.create_index("ix_login_session_user_id", "login_session", ["user_id"])
    op.create_table(
        "study",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("name", sa.String(64), nullable=False),
        sa.Column("title", sa.String(200), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("protocol", JSON, nullable=False),
        sa.Column("protocol_source", sa.Text(), nullable=False),
        sa.Column("protocol_sha256", sa.String(64), nullable=False),
        sa.Column("allocation_seed", sa.String(64), nullable=False),
        _timestamp("created_at"),
        sa.Column("created_by", sa.String(64), nullable=False),
        _timestamp("closed_at", nullable=True),
        sa.CheckConstraint("status IN ('open', 'closed')", name="status_known"),
        sa.UniqueConstraint("name"),
    )
    op.create_table(
        "participant",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("study_id", sa.Integer(), sa.ForeignKey("study.id"), nullable=False),
        sa.Column("code", sa.String(32), nullable=False),
        sa.Column("stratum", sa.String(200), nullable=False),
        sa.Column("strata", JSON, nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        _timestamp("enrolled_at"),
        sa.Column("enrolled_by", sa.String(64), nullable=False),
        _timestamp("withdrawn_at", nullable=True),
        sa.Column("withdrawal_reason", sa.Text(), nullable=False),
        sa.CheckConstraint("status IN ('active', 'withdrawn', 'completed')", name="status_known"),
        sa.UniqueConstraint("study_id", "code"),
    )
    op.create_index("ix_participant_study_id", "participant", ["study_id"])
    op.create_table(
        "allocation",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("study_id", sa.Integer(), sa.ForeignKey("study.id"), nullable=False),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=False),
        sa.Column("stratum", sa.String(200), nullable=False),
        sa.Column("sequence_index", sa.Integer(), nullable=True),
        sa.Column("block_number", sa.Integer(), nullable=True),
        sa.Column("block_size", sa.Integer(), nullable=True),
        sa.Column("condition", sa.String(32), nullable=False),
        sa.Column(
            "replaces_participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=True
        ),
        _timestamp("revealed_at"),
        sa.CheckConstraint(
            "(sequence_index IS NULL) = (replaces_participant_id IS NOT NULL)",
            name="sequence_or_replacement",
        ),
        sa.UniqueConstraint("participant_id"),
        sa.UniqueConstraint("replaces_participant_id"),
        sa.UniqueConstraint("study_id", "stratum", "sequence_index"),
    )
    op.create_index("ix_allocation_study_id", "allocation", ["study_id"])
    op.create_table(
        "audit_event",
        sa.Column("id", sa.Integer(), primary_key=True),
        _timestamp("occurred_at"),
        sa.Column("actor_kind", sa.String(16), nullable=False),
        sa.Column("actor", sa.String(64), nullable=False),
        sa.Column("action", sa.String(64), nullable=False),
        sa.Column("study_id", sa.Integer(), sa.ForeignKey("study.id"), nullable=True),
        sa.Column("subject", sa.String(128), nullable=False),
        sa.Column("details", JSON, nullable=False),
        sa.CheckConstraint(
            "actor_kind IN ('user', 'device', 'participant', 'cli', 'system')",
            name="actor_kind_known",
        ),
    )
    op.create_index("ix_audit_event_action", "audit_event", ["action"])
    op.create_index(
        "ix_audit_event_study_id_occurred_at", "audit_event", ["study_id", "occurred_at"]
    )
    create_append_only_guard("audit_event")


def downgrade() -> None:
    drop_append_only_guard("audit_event")
    op.drop_table("audit_event")
    op.drop_table("allocation")
    op.drop_table("participant")
    op.drop_table("study")
    op.drop_table("login_session")
    op.drop_table("user")
