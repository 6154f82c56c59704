"""Data quality: how long each questionnaire page took, and time away from the study's tab.

Revision ID: 0029
Revises: 0028
Create Date: 2026-12-07

Each submission records the seconds its page was open until the first submission and the seconds
of that time the tab was hidden (both measured by the page, NULL where it could not say: a page
sent by an API client, or submitted before this revision). An online participation adds up the
time its room page was hidden. app/services/participants/data_quality.py turns them into the
'speeding' and 'away' flags (issue 51).

Downgrade drops the three columns.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0029"
down_revision: str | None = "0028"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("submission") as batch:
        batch.add_column(sa.Column("seconds_on_page", sa.Double(), nullable=True))
        batch.add_column(sa.Column("seconds_away", sa.Double(), nullable=True))
    with op.batch_alter_table("online_participation") as batch:
        batch.add_column(
            sa.Column("room_seconds_away", sa.Double(), nullable=False, server_default="0")
        )


def downgrade() -> None:
    with op.batch_alter_table("online_participation") as batch:
        batch.drop_column("room_seconds_away")
    with op.batch_alter_table("submission") as batch:
        batch.drop_column("seconds_away")
        batch.drop_column("seconds_on_page")
