"""Sites: the place each participant belongs to, and the sites a staff account is limited to.

Revision ID: 0019
Revises: 0018
Create Date: 2026-12-06

- ``participant.site``: one of the study's ``[sites] names`` (NULL in a study without sites).
- ``user.sites``: a JSON list of site names the account's participants are limited to; NULL
  means every site (app.services.privacy.sites). Admins see every site whatever it holds.

Downgrade drops both columns: every account then sees every participant again.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.postgresql import JSONB

revision: str = "0019"
down_revision: str | None = "0018"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("participant", sa.Column("site", sa.String(length=40), nullable=True))
    op.add_column(
        "user", sa.Column("sites", sa.JSON().with_variant(JSONB(), "postgresql"), nullable=True)
    )


def downgrade() -> None:
    # In place (SQLite 3.35+ drops a plain column), not a batch rebuild: a rebuild of participant
    # or user fails on SQLite once other rows refer to them.
    op.drop_column("user", "sites")
    op.drop_column("participant", "site")
