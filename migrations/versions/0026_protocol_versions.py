"""Every version of a study's protocol: ``protocol_version``.

Revision ID: 0026
Revises: 0025
Create Date: 2026-12-07

A draft's protocol is edited in the browser (issue 50), so a study's protocol is no longer fixed
at creation: each save is a new row (number 1, 2, …: the text byte for byte, its SHA-256, who,
when, why, and the study's phase then), the study row keeps the current one as before, and an
undo restores the previous text as a further version, so nothing is ever edited or deleted. An
existing study gets its protocol as version 1, from its creation.

Downgrade drops the table (the study row still holds the current protocol).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0026"
down_revision: str | None = "0025"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "protocol_version",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("study_id", sa.Integer(), nullable=False),
        sa.Column("number", sa.Integer(), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False),
        sa.Column("source", sa.Text(), nullable=False),
        sa.Column("saved_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("saved_by", sa.String(64), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("phase", sa.String(16), nullable=False),
        sa.ForeignKeyConstraint(
            ["study_id"], ["study.id"], name="fk_protocol_version_study_id_study"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_protocol_version"),
        sa.UniqueConstraint("study_id", "number", name="uq_protocol_version_study_id_number"),
        sa.CheckConstraint(
            "phase IN ('draft', 'pilot', 'live')", name="ck_protocol_version_phase_known"
        ),
    )
    op.create_index("ix_protocol_version_study_id", "protocol_version", ["study_id"])
    op.execute(
        "INSERT INTO protocol_version "
        "(study_id, number, sha256, source, saved_at, saved_by, reason, phase) "
        "SELECT id, 1, protocol_sha256, protocol_source, created_at, created_by, '', phase "
        "FROM study"
    )


def downgrade() -> None:
    op.drop_index("ix_protocol_version_study_id", table_name="protocol_version")
    op.drop_table("protocol_version")
