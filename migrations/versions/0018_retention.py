"""Retention deadlines.

Revision ID: 0018
Revises: 0017
Create Date: 2026-12-06

``participant.anonymised_at`` is set when ``trustlab retention run`` anonymised the participant
after their study's retention period ran out (app.services.privacy.retention): their code is then a
random id and their free text, transcripts and recordings are gone. Downgrade drops the column
(anonymised participants stay anonymised; a later run would only find nothing left to drop).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0018"
down_revision: str | None = "0017"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column(
        "participant", sa.Column("anonymised_at", sa.DateTime(timezone=True), nullable=True)
    )


def downgrade() -> None:
    op.drop_column("participant", "anonymised_at")
