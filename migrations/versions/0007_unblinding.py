"""Unblinding: when an admin lifted a blinded study's blinding.

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-03

``study.unblinded_at`` stays empty for every existing study: a blinded study stays blinded until
an admin unblinds it (``trustlab study unblind`` or *Unblind* on the study page), which is audited.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("study", sa.Column("unblinded_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    # A plain DROP COLUMN (SQLite 3.35 and later): a batch copy would drop and recreate the study
    # table, which the participants' foreign keys refuse once a study has participants.
    op.drop_column("study", "unblinded_at")
