"""Stations have a site: ``station.site``, one of the sites the studies declare (NULL: shared).

Revision ID: 0023
Revises: 0022
Create Date: 2026-12-07

A station of a site is, for an account limited to other sites, as if it did not exist, and only
that site's participants are seated there; a shared station (NULL, every station so far) is
listed for everyone, its robots' contact shown to a limited account only while one of its own
participants is seated there (app.services.privacy.sites).

Downgrade drops the column: every station is shared again.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0023"
down_revision: str | None = "0022"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("station", sa.Column("site", sa.String(length=40), nullable=True))


def downgrade() -> None:
    # In place (SQLite 3.35+ drops a plain column), not a batch rebuild: other rows refer to
    # station (device, step logs).
    op.drop_column("station", "site")
