"""The room client: where a prompt was triggered, and how an answer was given.

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-04

``prompt.zone`` is the trigger zone the participant walked into (the browser room client sends its
category's zone; other clients may name their own trigger, or nothing). ``answer.modality`` says
how the participant answered (``button``, ``key``, ``speech``; empty: the client did not say), and
for speech ``answer.transcript`` and ``answer.transcript_confidence`` keep the recognised words and
the recogniser's confidence, so a lab can audit what speech recognition heard. Every existing row
arrives with them empty, as rows from clients that do not send them will.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("prompt", sa.Column("zone", sa.String(40), nullable=True))
    op.add_column("answer", sa.Column("modality", sa.String(16), nullable=True))
    op.add_column("answer", sa.Column("transcript", sa.String(200), nullable=True))
    op.add_column("answer", sa.Column("transcript_confidence", sa.Double(), nullable=True))


def downgrade() -> None:
    # Plain columns without keys or indexes: SQLite (3.35+) and PostgreSQL both drop them in place.
    op.drop_column("answer", "transcript_confidence")
    op.drop_column("answer", "transcript")
    op.drop_column("answer", "modality")
    op.drop_column("prompt", "zone")
