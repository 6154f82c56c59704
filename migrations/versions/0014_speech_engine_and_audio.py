"""Which recogniser heard a spoken answer, and the answer's audio where a study records it.

Revision ID: 0014
Revises: 0013
Create Date: 2026-12-06

``answer.transcript_engine`` names the recogniser of a spoken answer beside its transcript and
confidence (the trustlab server's offline one, or ``browser`` for a browser's own). Answers
stored before have none (NULL): their engine was never recorded.

``answer_audio`` holds the voice of a spoken answer, one row per answer, only for a study whose
protocol sets ``[speech] record_audio = true``; otherwise nothing is ever written to it. The
upgrade creates it empty. The downgrade refuses to drop recordings (they are part of a study's
record): erase them first; it drops the column and an empty table.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

from app.errors import Conflict

revision: str = "0014"
down_revision: str | None = "0013"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("answer", sa.Column("transcript_engine", sa.String(60), nullable=True))
    op.create_table(
        "answer_audio",
        sa.Column("answer_id", sa.Integer(), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("wav", sa.LargeBinary(), nullable=False),
        sa.Column("seconds", sa.Double(), nullable=False),
        sa.Column("recorded_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["answer_id"], ["answer.id"], name="fk_answer_audio_answer_id_answer"
        ),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participant.id"],
            name="fk_answer_audio_participant_id_participant",
        ),
        sa.PrimaryKeyConstraint("answer_id", name="pk_answer_audio"),
    )
    op.create_index(
        "ix_answer_audio_participant_id", "answer_audio", ["participant_id"], unique=False
    )


def downgrade() -> None:
    recordings = op.get_bind().execute(sa.text("SELECT count(*) FROM answer_audio")).scalar_one()
    if recordings:
        raise Conflict(
            f"downgrading below 0014 would delete {recordings} recorded answer(s) in answer_audio: "
            "export or erase them first"
        )
    op.drop_index("ix_answer_audio_participant_id", table_name="answer_audio")
    op.drop_table("answer_audio")
    # In place, as 0007, 0012 and 0013 do (a batch copy of ``answer`` would trip foreign keys).
    op.drop_column("answer", "transcript_engine")
