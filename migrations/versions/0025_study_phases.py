"""Study phases (draft, pilot, live) and pilot participants.

Revision ID: 0025
Revises: 0024
Create Date: 2026-12-07

- ``study.phase``: *draft* (the protocol may still change; nobody enrols), *pilot* (enrolments
  are pilot participants) or *live* (the protocol frozen, the concealed sequence under way), as
  REDCap's development and production (issue 50; app.services.study_phases). Every existing
  study is live: it has been enrolling real participants. ``study.live_at``: when it went live
  (an existing study's creation).
- ``participant.pilot`` and ``allocation.pilot``: a pilot participant's allocation comes from a
  sequence of its own (app.randomisation.pilot_seed), so the allocation's unique slot is now
  ``(study, pilot, stratum, sequence_index)``: a pilot's slot 0 and the live slot 0 are two
  slots. ``allocation.pilot`` always equals its participant's (the slot's sequence).
- ``participant`` becomes an AUTOINCREMENT table on SQLite, as ``prompt`` did in 0021: a pilot
  reset deletes participants, and an id given again would name a deleted pilot's row in a page
  or an event still in flight.

Downgrade deletes nothing: it refuses while a pilot participant or a draft or pilot study
exists (their rows would become live data), and otherwise drops the columns.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0025"
down_revision: str | None = "0024"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

OLD_SLOT = "uq_allocation_study_id_stratum_sequence_index"
NEW_SLOT = "uq_allocation_study_id_pilot_stratum_sequence_index"


def upgrade() -> None:
    sqlite = op.get_bind().dialect.name == "sqlite"
    with op.batch_alter_table("study") as batch:
        batch.add_column(sa.Column("phase", sa.String(16), nullable=False, server_default="live"))
        batch.add_column(sa.Column("live_at", sa.DateTime(timezone=True), nullable=True))
        batch.create_check_constraint("phase_known", "phase IN ('draft', 'pilot', 'live')")
    op.execute("UPDATE study SET live_at = created_at")
    with op.batch_alter_table(
        "participant",
        recreate="always" if sqlite else "auto",
        table_kwargs={"sqlite_autoincrement": True},
    ) as batch:
        batch.add_column(
            sa.Column("pilot", sa.Boolean(), nullable=False, server_default=sa.false())
        )
    with op.batch_alter_table("allocation") as batch:
        batch.add_column(
            sa.Column("pilot", sa.Boolean(), nullable=False, server_default=sa.false())
        )
        batch.drop_constraint(OLD_SLOT, type_="unique")
        batch.create_unique_constraint(NEW_SLOT, ["study_id", "pilot", "stratum", "sequence_index"])


def downgrade() -> None:
    bind = op.get_bind()
    pilots = bind.scalar(sa.text("SELECT count(*) FROM participant WHERE pilot"))
    unfinished = bind.scalar(sa.text("SELECT count(*) FROM study WHERE phase != 'live'"))
    if pilots or unfinished:
        raise RuntimeError(
            f"{pilots} pilot participant(s) and {unfinished} draft or pilot stud(ies) exist: "
            "reset the pilots and take the studies live (or delete them) before downgrading"
        )
    sqlite = bind.dialect.name == "sqlite"
    with op.batch_alter_table("allocation") as batch:
        batch.drop_constraint(NEW_SLOT, type_="unique")
        batch.create_unique_constraint(OLD_SLOT, ["study_id", "stratum", "sequence_index"])
        batch.drop_column("pilot")
    with op.batch_alter_table(
        "participant",
        recreate="always" if sqlite else "auto",
        table_kwargs={"sqlite_autoincrement": False},
    ) as batch:
        batch.drop_column("pilot")
    with op.batch_alter_table("study") as batch:
        batch.drop_constraint("phase_known", type_="check")
        batch.drop_column("live_at")
        batch.drop_column("phase")
