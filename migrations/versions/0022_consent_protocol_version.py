"""The consent record's ``version`` answer is named ``protocol_version``.

Revision ID: 0022
Revises: 0021
Create Date: 2026-12-07

A participant's consent is stored as answers of the ``consent`` instrument; one of them, the
consent text's version as its protocol (or consent file) names it ("1.0"), was called ``version``
and so became a column ``version`` of the wide CSV and SPSS files, beside ``consent_version`` (the
number of the version accepted), where nobody could tell which version it was. It is now
``protocol_version``; the upgrade renames the stored answers, the downgrade names them back.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0022"
down_revision: str | None = "0021"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _rename(old: str, new: str) -> None:
    op.execute(
        sa.text(
            "UPDATE response SET item = :new WHERE instrument = 'consent' AND item = :old"
        ).bindparams(old=old, new=new)
    )


def upgrade() -> None:
    _rename("version", "protocol_version")


def downgrade() -> None:
    _rename("protocol_version", "version")
