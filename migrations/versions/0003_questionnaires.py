"""Questionnaires: responses in long format, submissions, participant and kiosk tokens, locking.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22

New columns are added in place (SQLite's ALTER TABLE ADD COLUMN), never by recreating tables that
other tables reference; uniqueness of nullable token hashes is a unique index on both engines.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _partial_unique(name: str, table: str, columns: list[str], where: str) -> None:
    op.create_index(
        name,
        table,
        columns,
        unique=True,
        sqlite_where=sa.text(where),
        postgresql_where=sa.text(where),
    )


def upgrade() -> None:
    op.add_column("participant", sa.Column("locked_at", sa.DateTime(timezone=True), nullable=True))
    op.add_column("participant", sa.Column("token_hash", sa.String(64), nullable=True))
    op.add_column(
        "participant",
        sa.Column("token_generation", sa.Integer(), nullable=False, server_default="0"),
    )
    op.create_index("ix_participant_token_hash", "participant", ["token_hash"], unique=True)
    op.add_column("station", sa.Column("kiosk_token_hash", sa.String(64), nullable=True))
    op.add_column(
        "station", sa.Column("kiosk_generation", sa.Integer(), nullable=False, server_default="0")
    )
    op.create_index("ix_station_kiosk_token_hash", "station", ["kiosk_token_hash"], unique=True)
    op.create_table(
        "response",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=False),
        sa.Column("instrument", sa.String(40), nullable=False),
        sa.Column("session", sa.Integer(), nullable=True),
        sa.Column("item", sa.String(80), nullable=False),
        sa.Column("value", sa.Text(), nullable=False),
        sa.Column("answered_at", sa.DateTime(timezone=True), nullable=False),
    )
    op.create_index("ix_response_participant_id", "response", ["participant_id"])
    _partial_unique(
        "uq_response_session_item",
        "response",
        ["participant_id", "instrument", "session", "item"],
        "session IS NOT NULL",
    )
    _partial_unique(
        "uq_response_item", "response", ["participant_id", "instrument", "item"], "session IS NULL"
    )
    op.create_table(
        "submission",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("participant_id", sa.Integer(), sa.ForeignKey("participant.id"), nullable=False),
        sa.Column("instrument", sa.String(40), nullable=False),
        sa.Column("session", sa.Integer(), nullable=True),
        sa.Column("submitted_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("revision", sa.Integer(), nullable=False),
        sa.Column("revised_at", sa.DateTime(timezone=True), nullable=True),
    )
    op.create_index("ix_submission_participant_id", "submission", ["participant_id"])
    _partial_unique(
        "uq_submission_session",
        "submission",
        ["participant_id", "instrument", "session"],
        "session IS NOT NULL",
    )
    _partial_unique(
        "uq_submission", "submission", ["participant_id", "instrument"], "session IS NULL"
    )


def downgrade() -> None:
    op.drop_table("submission")
    op.drop_table("response")
    op.drop_index("ix_station_kiosk_token_hash", "station")
    with op.batch_alter_table("station") as batch:
        batch.drop_column("kiosk_generation")
        batch.drop_column("kiosk_token_hash")
    op.drop_index("ix_participant_token_hash", "participant")
    with op.batch_alter_table("participant") as batch:
        batch.drop_column("token_generation")
        batch.drop_column("token_hash")
        batch.drop_column("locked_at")
