"""The room's live state: where each station's room client last saw the participant.

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-05

``room_presence`` holds one row per station, overwritten while a participant walks through the
browser room (position, heading, the trigger zone they stand in, and the last line spoken or
heard): the operator console's room panel reads it on any worker. It is not a log, so the
upgrade creates it empty and the downgrade drops it with whatever it holds.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "room_presence",
        sa.Column("station_id", sa.Integer(), nullable=False),
        sa.Column("device_id", sa.Integer(), nullable=True),
        sa.Column("x", sa.Double(), nullable=False),
        sa.Column("z", sa.Double(), nullable=False),
        sa.Column("heading", sa.Double(), nullable=False),
        sa.Column("zone", sa.String(40), nullable=True),
        sa.Column("utterance_kind", sa.String(16), nullable=True),
        sa.Column("utterance", sa.String(300), nullable=True),
        sa.Column("utterance_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["station_id"], ["station.id"], name="fk_room_presence_station_id_station"
        ),
        sa.ForeignKeyConstraint(
            ["device_id"], ["device.id"], name="fk_room_presence_device_id_device"
        ),
        sa.PrimaryKeyConstraint("station_id", name="pk_room_presence"),
    )


def downgrade() -> None:
    op.drop_table("room_presence")
