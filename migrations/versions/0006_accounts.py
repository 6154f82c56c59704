"""Accounts: an admin's unlock clears an account's failed sign-ins without deleting them.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-29

``login_attempt.cleared_at`` marks failures that no longer count towards the lockout
(``trustlab user unlock`` or *Unlock* on the admin's user page); the attempts stay on record.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column(
        "login_attempt", sa.Column("cleared_at", sa.DateTime(timezone=True), nullable=True)
    )


def downgrade() -> None:
    with op.batch_alter_table("login_attempt") as batch:
        batch.drop_column("cleared_at")
