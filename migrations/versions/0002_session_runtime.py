"""Session runtime: stations, device keys, learners, sessions, runs and the step log.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

from app.schema import create_append_only_guard, drop_append_only_guard

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")


def _timestamp(name: str, *, nullable: bool = False) -> sa.Column[object]:
    return sa.Column(name, sa.DateTime(timezone=True), nullable=nullable)


def upgrade() -> None:
    op.create_table(
        "station",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("name", sa.String(64), nullable=False),
        _timestamp("created_at"),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=True),
        _timestamp("assigned_at", nullable=True),
        sa.UniqueConstraint("name"),
        sa.UniqueConstraint("participant_id"),
    )
    op.create_table(
        "device",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("station_id", sa.Integer(), sa.ForeignKey("station.id"), nullable=False),
        sa.Column("label", sa.String(64), nullable=False),
        sa.Column("key_hash", sa.String(64), nullable=False),
        sa.Column("key_prefix", sa.String(16), nullable=False),
        _timestamp("created_at"),
        sa.Column("created_by", sa.String(64), nullable=False),
        _timestamp("revoked_at", nullable=True),
        _timestamp("last_seen_at", nullable=True),
        sa.UniqueConstraint("key_hash"),
    )
    op.create_index("ix_device_station_id", "device", ["station_id"])
    op.create_table(
        "learner",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=False),
        sa.Column("category", sa.String(40), nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("n_arms", sa.Integer(), nullable=False),
        sa.Column("config", JSON, nullable=False),
        sa.Column("checkpoint_sha256", sa.String(64), nullable=True),
        sa.Column("initial_state", JSON, nullable=False),
        sa.Column("state", JSON, nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        _timestamp("updated_at"),
        sa.UniqueConstraint("participant_id", "category"),
    )
    op.create_table(
        "study_session",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=False),
        sa.Column("station_id", sa.Integer(), sa.ForeignKey("station.id"), nullable=False),
        sa.Column("number", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        _timestamp("started_at"),
        sa.Column("started_by", sa.String(64), nullable=False),
        _timestamp("ended_at", nullable=True),
        sa.Column("ended_by", sa.String(64), nullable=False),
        sa.CheckConstraint(
            "status IN ('running', 'completed', 'ended_early')", name="status_known"
        ),
        sa.UniqueConstraint("participant_id", "number"),
    )
    op.create_index("ix_study_session_participant_id", "study_session", ["participant_id"])
    op.create_table(
        "run",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("session_id", sa.Integer(), sa.ForeignKey("study_session.id"), nullable=False),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=False),
        sa.Column("number", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        _timestamp("started_at"),
        _timestamp("ended_at", nullable=True),
        sa.CheckConstraint(
            "status IN ('running', 'completed', 'ended_early')", name="status_known"
        ),
        sa.UniqueConstraint("session_id", "number"),
    )
    op.create_index("ix_run_session_id", "run", ["session_id"])
    op.create_index("ix_run_participant_id", "run", ["participant_id"])
    op.create_table(
        "prompt",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=False),
        sa.Column("run_id", sa.Integer(), sa.ForeignKey("run.id"), nullable=False),
        sa.Column("category", sa.String(40), nullable=False),
        sa.Column("action", sa.Integer(), nullable=False),
        sa.Column("question", sa.Text(), nullable=False),
        sa.Column("probabilities", JSON, nullable=False),
        sa.Column("learner_version", sa.Integer(), nullable=False),
        sa.Column("adapts", sa.Boolean(), nullable=False),
        _timestamp("prompted_at"),
        sa.Column("device_id", sa.Integer(), sa.ForeignKey("device.id"), nullable=True),
        sa.Column("actor", sa.String(64), nullable=False),
        sa.UniqueConstraint("run_id", "category"),
    )
    op.create_index("ix_prompt_participant_id", "prompt", ["participant_id"])
    op.create_table(
        "answer",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("prompt_id", sa.Integer(), sa.ForeignKey("prompt.id"), nullable=False),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=False),
        sa.Column("answer", sa.Boolean(), nullable=False),
        sa.Column("reward", sa.Double(), nullable=False),
        sa.Column("probabilities_after", JSON, nullable=False),
        sa.Column("probability", sa.Double(), nullable=False),
        sa.Column("confidence_level", sa.Integer(), nullable=False),
        sa.Column("confidence", sa.String(40), nullable=False),
        sa.Column("reply", sa.Text(), nullable=False),
        sa.Column("learner_version", sa.Integer(), nullable=False),
        sa.Column("idempotency_key", sa.String(100), nullable=False),
        _timestamp("answered_at"),
        sa.Column("processing_ms", sa.Double(), nullable=False),
        sa.Column("device_id", sa.Integer(), sa.ForeignKey("device.id"), nullable=True),
        sa.Column("actor", sa.String(64), nullable=False),
        sa.UniqueConstraint("prompt_id"),
    )
    op.create_index("ix_answer_participant_id", "answer", ["participant_id"])
    create_append_only_guard("prompt")
    create_append_only_guard("answer")


def downgrade() -> None:
    drop_append_only_guard("answer")
    drop_append_only_guard("prompt")
    op.drop_table("answer")
    op.drop_table("prompt")
    op.drop_table("run")
    op.drop_table("study_session")
    op.drop_table("learner")
    op.drop_table("device")
    op.drop_table("station")
