"""Live dashboard: each step records the preferred question's probability; device connections.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-22

``p_preferred`` is derived from the stored probabilities and the protocol's preferred question and
written once with the step (the step log stays append-only), so adaptation curves aggregate in SQL
instead of decoding every probability list.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

from app.schema import create_append_only_guard, drop_append_only_guard

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("prompt", sa.Column("p_preferred", sa.Double(), nullable=True))
    op.add_column("answer", sa.Column("p_preferred", sa.Double(), nullable=True))
    op.add_column("device", sa.Column("connected_at", sa.DateTime(timezone=True), nullable=True))
    op.add_column("device", sa.Column("disconnected_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("device") as batch:
        batch.drop_column("disconnected_at")
        batch.drop_column("connected_at")
    for table in ("answer", "prompt"):
        # SQLite drops a column by rebuilding the table, which loses its triggers: re-add them.
        drop_append_only_guard(table)
        with op.batch_alter_table(table) as batch:
            batch.drop_column("p_preferred")
        create_append_only_guard(table)
