"""Which protocol version each participant and session ran under.

Revision ID: 0027
Revises: 0026
Create Date: 2026-12-07

A live study's protocol may be amended (issue 50: a new version, with a reason, refused when it
would break comparability), so a participant's data must say under which version it was
collected: ``participant.protocol_version`` (the version when they enrolled) and
``study_session.protocol_version`` (when the session started). Existing rows were all collected
under their study's only version, 1.

Downgrade drops both columns.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0027"
down_revision: str | None = "0026"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Plain ADD COLUMN (no batch copy): study_session is referenced by runs and prompts.
    op.add_column("participant", sa.Column("protocol_version", sa.Integer(), nullable=True))
    op.add_column("study_session", sa.Column("protocol_version", sa.Integer(), nullable=True))
    op.execute("UPDATE participant SET protocol_version = 1")
    op.execute("UPDATE study_session SET protocol_version = 1")


def downgrade() -> None:
    op.drop_column("study_session", "protocol_version")
    op.drop_column("participant", "protocol_version")
