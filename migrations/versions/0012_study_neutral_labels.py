"""Neutral labels drawn per study: which condition a blinded study calls *Group A* is its secret.

Revision ID: 0012
Revises: 0011
Create Date: 2026-12-12

Before this revision the neutral labels followed the protocol (C1 was always *Group A*, or the
condition's own ``neutral_label``), and experimenters can read the protocol, so the labels told
them the conditions. ``study.neutral_labels`` holds each blinded study's condition id → label,
drawn at random at creation (app.services.studies.draw_neutral_labels) and shown only once the
study is unblinded.

Upgrade, for the blinded studies already in the database:

- a study nobody has been enrolled in yet gets a fresh random draw (no label has been attached to
  anyone yet, so nothing changes under anybody);
- a study with participants keeps the labels it has been showing (the protocol's, by position):
  a running study must not see its groups change under its experimenters. Its labels remain as
  guessable as before; the PI guide says how to report that.

Studies that are not blinded get none. Downgrade drops the column (the old code derives the labels
from the protocol again), and so is refused while any study holds a draw that differs from the
protocol's labels: the draw exists nowhere else, and the older code would show that study's groups
under the other labels (a running study's participants would swap groups in the experimenters'
view, an unblinded study's record of "was Group B while blinded" would turn false).
"""

from __future__ import annotations

import secrets
from collections.abc import Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

from app.errors import Conflict

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")

study = sa.table(
    "study",
    sa.column("id", sa.Integer()),
    sa.column("name", sa.String()),
    sa.column("protocol", JSON),
    sa.column("neutral_labels", JSON),
)
participant = sa.table("participant", sa.column("study_id", sa.Integer()))


def _protocol_labels(protocol: dict[str, Any]) -> dict[str, str]:
    """The labels as the code before this revision showed them: own, or Group A, B… by place."""
    return {
        condition["id"]: condition.get("neutral_label") or f"Group {chr(ord('A') + position)}"
        for position, condition in enumerate(protocol["conditions"])
    }


def _drawn(labels: dict[str, str]) -> dict[str, str]:
    shuffled = secrets.SystemRandom().sample(list(labels.values()), len(labels))
    return dict(zip(labels, shuffled, strict=True))


def upgrade() -> None:
    op.add_column("study", sa.Column("neutral_labels", JSON, nullable=True))
    connection = op.get_bind()
    enrolled = set(connection.scalars(sa.select(participant.c.study_id).distinct()))
    for study_id, protocol in connection.execute(sa.select(study.c.id, study.c.protocol)).all():
        if not protocol.get("study", {}).get("blinded", False):
            continue
        labels = _protocol_labels(protocol)
        if study_id not in enrolled:
            labels = _drawn(labels)
        connection.execute(
            study.update().where(study.c.id == study_id).values(neutral_labels=labels)
        )


def downgrade() -> None:
    rows = op.get_bind().execute(sa.select(study.c.name, study.c.protocol, study.c.neutral_labels))
    drawn = sorted(
        name for name, protocol, labels in rows if labels and labels != _protocol_labels(protocol)
    )
    if drawn:
        raise Conflict(
            f"downgrading below 0012 would lose the neutral labels drawn for {', '.join(drawn)}: "
            "the older code shows their groups under the protocol's labels instead, so their "
            "participants would swap groups; restore a backup made before the upgrade instead"
        )
    # In place (SQLite ≥ 3.35 drops a plain column itself), as 0007 does: a batch copy of
    # ``study`` would trip the participants' foreign keys.
    op.drop_column("study", "neutral_labels")
