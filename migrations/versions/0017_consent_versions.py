"""Versions of a study's consent text, and every participant's answer to each.

Revision ID: 0017
Revises: 0016
Create Date: 2026-12-07

``consent_version`` holds the consent text a study shows, one row per version with its text and
SHA-256 in every language of the study. Version 1 is the protocol's own text; it is stored when a
later version is added, so the upgrade creates the table empty and every study keeps showing its
protocol's text.

``consent_record`` holds each participant's answer to a version: accepted or (asked again after a
change) declined, the language, the SHA-256 of the words shown and when. The upgrade gives every
participant who consented before it one row, version 1, from their consent page's stored
answers (the label, language and SHA-256 it kept) and its submission time: before this revision
a study had one text only.

The downgrade refuses while any study has a later version (the record of who accepted which
words would be lost): it drops only what the upgrade can rebuild.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

from app.errors import Conflict

revision: str = "0017"
down_revision: str | None = "0016"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")


def _backfill() -> None:
    """One accepted version-1 row per participant who had consented."""
    submission = sa.table(
        "submission",
        sa.column("participant_id", sa.Integer),
        sa.column("instrument", sa.String),
        sa.column("session", sa.Integer),
        sa.column("submitted_at", sa.DateTime),
    )
    response = sa.table(
        "response",
        sa.column("participant_id", sa.Integer),
        sa.column("instrument", sa.String),
        sa.column("session", sa.Integer),
        sa.column("item", sa.String),
        sa.column("value", sa.Text),
    )
    record = sa.table(
        "consent_record",
        sa.column("participant_id", sa.Integer),
        sa.column("version", sa.Integer),
        sa.column("label", sa.String),
        sa.column("language", sa.String),
        sa.column("sha256", sa.String),
        sa.column("accepted", sa.Boolean),
        sa.column("answered_at", sa.DateTime),
    )

    def stored(item: str, width: int) -> sa.ColumnElement[str]:
        value = (
            sa.select(sa.func.substr(response.c.value, 1, width))
            .where(
                response.c.participant_id == submission.c.participant_id,
                response.c.instrument == "consent",
                response.c.session.is_(None),
                response.c.item == item,
            )
            .scalar_subquery()
        )
        return sa.func.coalesce(value, "")

    consented = sa.select(
        submission.c.participant_id,
        sa.literal(1, sa.Integer),
        stored("version", 64),
        stored("consent_language", 16),
        stored("consent_sha256", 64),
        sa.true(),
        submission.c.submitted_at,
    ).where(submission.c.instrument == "consent", submission.c.session.is_(None))
    op.execute(
        record.insert().from_select(
            ["participant_id", "version", "label", "language", "sha256", "accepted", "answered_at"],
            consented,
        )
    )


def upgrade() -> None:
    op.create_table(
        "consent_version",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("study_id", sa.Integer(), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("label", sa.String(64), nullable=False),
        sa.Column("texts", JSON, nullable=False),
        sa.Column("sha256", JSON, nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("created_by", sa.String(64), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.ForeignKeyConstraint(
            ["study_id"], ["study.id"], name="fk_consent_version_study_id_study"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_consent_version"),
        sa.UniqueConstraint("study_id", "version", name="uq_consent_version_study_id_version"),
    )
    op.create_index("ix_consent_version_study_id", "consent_version", ["study_id"], unique=False)
    op.create_table(
        "consent_record",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("label", sa.String(64), nullable=False),
        sa.Column("language", sa.String(16), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False),
        sa.Column("accepted", sa.Boolean(), nullable=False),
        sa.Column("answered_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participant.id"],
            name="fk_consent_record_participant_id_participant",
        ),
        sa.PrimaryKeyConstraint("id", name="pk_consent_record"),
    )
    op.create_index(
        "ix_consent_record_participant_id", "consent_record", ["participant_id"], unique=False
    )
    _backfill()


def downgrade() -> None:
    later = (
        op.get_bind()
        .execute(sa.text("SELECT count(*) FROM consent_version WHERE version > 1"))
        .scalar_one()
    )
    if later:
        raise Conflict(
            f"downgrading below 0017 would delete {later} later consent version(s) and the "
            "record of who accepted them: export the participants' records first"
        )
    op.drop_index("ix_consent_record_participant_id", table_name="consent_record")
    op.drop_table("consent_record")
    op.drop_index("ix_consent_version_study_id", table_name="consent_version")
    op.drop_table("consent_version")
