"""Ids never given twice, and room presence tied to the participant it shows.

Revision ID: 0021
Revises: 0020
Create Date: 2026-12-07

- ``prompt``, ``answer`` and ``learner`` become AUTOINCREMENT tables on SQLite. Without it SQLite
  gives a new row the highest id plus one, so after an erasure deleted the participant with the
  highest step id, the next step got that id again: a robot, an export or a console form that
  still held the old step id then named someone else's step (and an answer's id its recording,
  a learner's id the process's cached learner). PostgreSQL's sequences never go back: nothing
  changes there. SQLite cannot alter a table's key in place, so each is copied into a new table
  (Alembic's batch "recreate"; migrations/env.py checks every foreign key before the commit),
  and the append-only guards of ``prompt`` and ``answer`` (app.schema) are put back. Ids deleted
  before this revision may still be given again once; none after it.
- ``room_presence.participant_id``: who was seated when the room client last reported, so that
  an erasure or retention run removes their presence after they were unseated (before, only the
  presence of the station they still sat at went). Existing rows keep it only when the station's
  current participant was seated before the row's last report (a line said before that is
  someone else's and is cleared); every other row is deleted: it shows a person nobody can name
  any more, and a room client writes the row again at its next report.

Downgrade drops the column (presence rows stay, as before this revision) and copies the three
tables back without AUTOINCREMENT.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

from app.schema import ERASABLE_TABLES, create_erasable_guard

revision: str = "0021"
down_revision: str | None = "0020"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

NEVER_REUSED = ("prompt", "answer", "learner")
PRESENCE_KEY = "fk_room_presence_participant_id_participant"


def _copy(table: str, *, autoincrement: bool) -> None:
    """SQLite: the table copied into one with (or without) AUTOINCREMENT, guards put back."""
    with op.batch_alter_table(
        table, recreate="always", table_kwargs={"sqlite_autoincrement": autoincrement}
    ):
        pass
    if table in ERASABLE_TABLES:  # dropped with the old table
        create_erasable_guard(table)


def upgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        # The copies drop tables other tables' keys point at (answer → prompt, answer_audio →
        # answer): migrations/env.py runs SQLite's migrations with keys checked at the end.
        for table in NEVER_REUSED:
            _copy(table, autoincrement=True)
        # SQLite adds a key only inline on ADD COLUMN (as 0008 does).
        op.execute(
            "ALTER TABLE room_presence ADD COLUMN participant_id INTEGER "
            f"CONSTRAINT {PRESENCE_KEY} REFERENCES participant (id)"
        )
    else:
        op.add_column("room_presence", sa.Column("participant_id", sa.Integer(), nullable=True))
        op.create_foreign_key(
            PRESENCE_KEY, "room_presence", "participant", ["participant_id"], ["id"]
        )
    op.execute(
        "UPDATE room_presence SET participant_id = (SELECT station.participant_id FROM station "
        "WHERE station.id = room_presence.station_id "
        "AND station.assigned_at <= room_presence.updated_at)"
    )
    op.execute("DELETE FROM room_presence WHERE participant_id IS NULL")
    op.execute(
        "UPDATE room_presence SET utterance_kind = NULL, utterance = NULL, utterance_at = NULL "
        "WHERE utterance_at < (SELECT station.assigned_at FROM station "
        "WHERE station.id = room_presence.station_id)"
    )


def downgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        with op.batch_alter_table("room_presence") as batch:
            batch.drop_column("participant_id")
        for table in NEVER_REUSED:
            _copy(table, autoincrement=False)
    else:
        op.drop_constraint(PRESENCE_KEY, "room_presence", type_="foreignkey")
        op.drop_column("room_presence", "participant_id")
