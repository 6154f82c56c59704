"""Withdrawal with erasure.

Revision ID: 0016
Revises: 0015
Create Date: 2026-12-06

- ``participant.erased_at``: set when a participant's data was erased
  (app.services.privacy.erasure). The row itself stays, under a pseudonym instead of the code,
  because its allocation must stay: the randomisation sequence, its balance and dropout replacements
  are checked against every revealed slot.
- ``erasure_in_progress``: marker rows that exist only inside an erasure's transaction.
- The append-only guards of ``prompt``, ``answer`` and ``audit_event`` let an erasure delete or
  rewrite the marked participant's rows (app.schema.create_erasable_guard); everyone else still
  meets the guard as before.

Downgrade restores the plain guards and drops the column and the marker table; erased
participants then look like withdrawn ones with no data.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

from app.schema import (
    ERASABLE_TABLES,
    ERASURE_MARKER,
    create_append_only_guard,
    create_erasable_guard,
    drop_append_only_guard,
)

revision: str = "0016"
down_revision: str | None = "0015"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("participant", sa.Column("erased_at", sa.DateTime(timezone=True), nullable=True))
    op.create_table(
        ERASURE_MARKER,
        sa.Column("participant_id", sa.Integer(), primary_key=True, autoincrement=False),
        sa.Column("study_id", sa.Integer(), nullable=False),
    )
    for table in ERASABLE_TABLES:
        drop_append_only_guard(table)
        create_erasable_guard(table)


def downgrade() -> None:
    for table in ERASABLE_TABLES:
        drop_append_only_guard(table)
        create_append_only_guard(table)
    if op.get_bind().dialect.name == "postgresql":
        op.execute("DROP FUNCTION IF EXISTS trustlab_append_only_unless_erasing()")
    op.drop_table(ERASURE_MARKER)
    op.drop_column("participant", "erased_at")
