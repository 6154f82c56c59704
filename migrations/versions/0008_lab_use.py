"""Lab use: a station's own study, and hiding finished studies and stations.

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-04

``station.study_id`` is the study a station's console seats participants from (empty: the console
asks for one); ``study.archived_at`` and ``station.archived_at`` hide the demo study, finished
studies and the bots' stations from the everyday lists without deleting anything. Every existing
row arrives with these empty: nothing is hidden and no station is tied to a study by the upgrade.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("study", sa.Column("archived_at", sa.DateTime(timezone=True), nullable=True))
    op.add_column("station", sa.Column("archived_at", sa.DateTime(timezone=True), nullable=True))
    # SQLite has no ALTER … ADD CONSTRAINT but takes the key inline on ADD COLUMN; a batch copy
    # would drop the station table, which its devices' and sessions' keys refuse once it has rows.
    if op.get_bind().dialect.name == "sqlite":
        op.execute(
            "ALTER TABLE station ADD COLUMN study_id INTEGER "
            "CONSTRAINT fk_station_study_id_study REFERENCES study (id)"
        )
    else:
        op.add_column("station", sa.Column("study_id", sa.Integer(), nullable=True))
        op.create_foreign_key("fk_station_study_id_study", "station", "study", ["study_id"], ["id"])


def downgrade() -> None:
    # SQLite cannot drop a column that a key uses except by a batch copy, which takes the key with
    # it (an empty station table only, like the downgrades of 0003 and 0004).
    if op.get_bind().dialect.name == "sqlite":
        with op.batch_alter_table("station") as batch:
            batch.drop_column("study_id")
    else:
        op.drop_constraint("fk_station_study_id_study", "station", type_="foreignkey")
        op.drop_column("station", "study_id")
    op.drop_column("station", "archived_at")
    op.drop_column("study", "archived_at")
