"""Device sockets: one row per open station WebSocket, so that overlapping sockets of one key are
counted rather than the last open or close winning.

Revision ID: 0020
Revises: 0019
Create Date: 2026-12-06

A bridge that reconnects opens its new socket before the server notices the old, half-open one
has gone; when the old one then closed, ``device.disconnected_at`` made the console show the
device as not connected while the new socket was open. ``device_socket`` holds a row per open
socket (inserted when it opens, deleted when it closes, its ``expires_at`` pushed on at each
heartbeat, so a dead worker's rows lapse): a device is connected while it has an unexpired row.

Nothing to carry over: no socket survives the upgrade's restart, and the downgrade drops the table
(``connected_at`` and ``disconnected_at`` are kept up to date all along, as before).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0020"
down_revision: str | None = "0019"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "device_socket",
        sa.Column("id", sa.String(32), nullable=False),
        sa.Column("device_id", sa.Integer(), nullable=False),
        sa.Column("opened_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("expires_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["device_id"], ["device.id"], name="fk_device_socket_device_id_device"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_device_socket"),
    )
    op.create_index("ix_device_socket_device_id", "device_socket", ["device_id"])


def downgrade() -> None:
    op.drop_index("ix_device_socket_device_id", table_name="device_socket")
    op.drop_table("device_socket")
