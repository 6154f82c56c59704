"""Sign-in attempts: a password check is pending until it has failed or succeeded.

Revision ID: 0011
Revises: 0010
Create Date: 2026-12-12

Before this revision an attempt was recorded as a failure *before* its password was checked
(``succeeded`` false), and marked succeeded afterwards: parallel right passwords were refused,
and a server that stopped during a check left a failure that locked the account for the window.
``login_attempt.outcome`` replaces the flag: ``pending`` while the check runs, then ``failed``
or ``succeeded``; a start turns pending attempts into ``abandoned``
(app.services.staff.login_throttle).

Upgrade: succeeded attempts become ``succeeded``, every other one ``failed`` (the old rows cannot
tell a real failure from an interrupted check, so the failures recorded in the last 15 minutes
keep counting until their window ends, exactly as before the upgrade). Downgrade: the flag comes
back from the outcome; pending and abandoned attempts, which never failed, are marked cleared so
that the old code does not count them as failures.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0011"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

OUTCOMES = "outcome IN ('pending', 'failed', 'succeeded', 'abandoned')"


def upgrade() -> None:
    with op.batch_alter_table("login_attempt") as batch:
        batch.add_column(
            sa.Column("outcome", sa.String(16), nullable=False, server_default="failed")
        )
    op.execute("UPDATE login_attempt SET outcome = 'succeeded' WHERE succeeded")
    with op.batch_alter_table("login_attempt") as batch:
        batch.alter_column("outcome", server_default=None)
        batch.drop_column("succeeded")
        batch.create_check_constraint("outcome_known", OUTCOMES)


def downgrade() -> None:
    with op.batch_alter_table("login_attempt") as batch:
        batch.add_column(
            sa.Column("succeeded", sa.Boolean(), nullable=False, server_default=sa.false())
        )
    op.execute(
        "UPDATE login_attempt SET cleared_at = attempted_at "
        "WHERE outcome IN ('pending', 'abandoned') AND cleared_at IS NULL"
    )
    op.execute("UPDATE login_attempt SET succeeded = (outcome = 'succeeded')")
    with op.batch_alter_table("login_attempt") as batch:
        batch.alter_column("succeeded", server_default=None)
        batch.drop_constraint("outcome_known", type_="check")
        batch.drop_column("outcome")
