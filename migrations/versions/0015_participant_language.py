"""A participant's language.

Revision ID: 0015
Revises: 0014
Create Date: 2026-12-06

``participant.language`` is the language the participant sees and hears everything in (one of
the study's ``study.languages``). NULL means not chosen yet: the study's first language applies,
and a protocol with ``study.language_choice`` asks on the tablet's first page. Participants
enrolled before this revision keep NULL, which is exactly what they had: the study's only
language. Downgrade drops the column (a multi-language study would then show its first language).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0015"
down_revision: str | None = "0014"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("participant", sa.Column("language", sa.String(16), nullable=True))


def downgrade() -> None:
    op.drop_column("participant", "language")
