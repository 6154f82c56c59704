"""A device's notice to the operator console.

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-06

A robot bridge (``trustlab bridge``) tells the console what it cannot do itself: that it lost the
robot and is reconnecting, or that the participant's answer stayed unclear and the operator must
give a Wizard-of-Oz answer. ``device.notice`` holds the newest such line, ``notice_attention``
whether it asks the operator to act, ``notice_at`` when it was said. Downgrade drops them (the
notices are transient: nothing of the study's record is lost).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0013"
down_revision: str | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("device", sa.Column("notice", sa.String(300), nullable=True))
    op.add_column(
        "device",
        sa.Column("notice_attention", sa.Boolean(), nullable=False, server_default=sa.false()),
    )
    op.add_column("device", sa.Column("notice_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    # In place, as 0007 and 0012 do (a batch copy of ``device`` would trip foreign keys).
    op.drop_column("device", "notice_at")
    op.drop_column("device", "notice_attention")
    op.drop_column("device", "notice")
