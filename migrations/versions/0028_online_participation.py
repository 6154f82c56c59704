"""Online studies: ``online_participation`` and ``station.online``.

Revision ID: 0028
Revises: 0027
Create Date: 2026-12-07

A study declaring ``[online]`` is joined from a public link (issue 51). Each recruitment ID gets
one participation row (its keyed hash unique per study, so two joins with one ID cannot both
enrol), pointing at the participant it enrolled and the virtual station made for them; the
station is marked ``online`` so that the lab's station list leaves it out. Existing stations are
the lab's.

Downgrade drops the table and the column.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0028"
down_revision: str | None = "0027"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
STATUSES = "'active', 'completed', 'screened_out', 'expired', 'ended'"


def upgrade() -> None:
    op.add_column(
        "station", sa.Column("online", sa.Boolean(), nullable=False, server_default=sa.false())
    )
    when = sa.DateTime(timezone=True)
    op.create_table(
        "online_participation",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("study_id", sa.Integer(), nullable=False),
        sa.Column("recruitment_hash", sa.String(64), nullable=True),
        sa.Column("participant_id", sa.Integer(), nullable=True),
        sa.Column("station_id", sa.Integer(), nullable=True),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("reason", sa.String(200), nullable=False),
        sa.Column("parameters", JSON, nullable=True),
        sa.Column("browser", sa.String(64), nullable=True),
        sa.Column("device", sa.String(16), nullable=False),
        sa.Column("step", sa.String(80), nullable=False),
        sa.Column("step_at", when, nullable=False),
        sa.Column("joined_at", when, nullable=False),
        sa.Column("expires_at", when, nullable=False),
        sa.Column("finished_at", when, nullable=True),
        sa.Column("last_seen_at", when, nullable=False),
        sa.Column("key_generation", sa.Integer(), nullable=False),
        sa.Column("flags", JSON, nullable=False),
        sa.Column("pilot", sa.Boolean(), nullable=False, server_default=sa.false()),
        sa.ForeignKeyConstraint(
            ["study_id"], ["study.id"], name="fk_online_participation_study_id_study"
        ),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participant.id"],
            name="fk_online_participation_participant_id_participant",
        ),
        sa.ForeignKeyConstraint(
            ["station_id"], ["station.id"], name="fk_online_participation_station_id_station"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_online_participation"),
        sa.UniqueConstraint(
            "study_id",
            "recruitment_hash",
            name="uq_online_participation_study_id_recruitment_hash",
        ),
        sa.UniqueConstraint("participant_id", name="uq_online_participation_participant_id"),
        sa.UniqueConstraint("station_id", name="uq_online_participation_station_id"),
        sa.CheckConstraint(f"status IN ({STATUSES})", name="ck_online_participation_status_known"),
        sqlite_autoincrement=True,
    )
    op.create_index("ix_online_participation_study_id", "online_participation", ["study_id"])


def downgrade() -> None:
    op.drop_index("ix_online_participation_study_id", table_name="online_participation")
    op.drop_table("online_participation")
    with op.batch_alter_table("station") as batch:
        batch.drop_column("online")
