"""A name taken between the check and the insert (two creations at once, on PostgreSQL) is a clear
Conflict, as when it was taken before: the unique index refuses it and the service says so."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from sqlalchemy import event, insert
from sqlalchemy.orm import Session

from app.db import Database
from app.errors import Conflict
from app.protocol import default_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.sessions import stations
from app.tables import AuditEvent, Station, Study

ACTOR = Actor.system("tests")


def _create_station(db: Session) -> None:
    stations.create_station(db, name="twin", actor=ACTOR)


def _create_study(db: Session) -> None:
    studies.create_study(db, name="twin", loaded=default_protocol(), actor=ACTOR)


def _taken_by_another_connection(database: Database, table: type[Station] | type[Study]) -> None:
    row = {"name": "twin"}
    if table is Study:
        loaded = default_protocol()
        row |= {
            "title": "T",
            "protocol": loaded.protocol.model_dump(mode="json"),
            "protocol_source": loaded.source_text,
            "protocol_sha256": loaded.sha256,
            "allocation_seed": "seed",
        }
    with database.engine.begin() as connection:
        connection.execute(insert(table).values(**row))


@pytest.mark.parametrize(
    ("create", "table", "what"),
    [(_create_station, Station, "station"), (_create_study, Study, "study")],
    ids=["station", "study"],
)
def test_a_name_taken_meanwhile_is_a_conflict(
    database: Database, create: Callable[[Session], None], table: type, what: str
) -> None:
    expected = f"a {what} named 'twin' already exists"
    with database.writing() as db:
        if not database.is_sqlite:
            # PostgreSQL: another connection takes the name after this one found it free
            # (SQLite's single writer makes that impossible: its check always sees the name)
            event.listen(
                db,
                "before_flush",
                lambda *_: _taken_by_another_connection(database, table),
                once=True,
            )
            with pytest.raises(Conflict) as refused:
                create(db)
            assert refused.value.message == expected
        else:
            create(db)
    with database.writing() as db, pytest.raises(Conflict, match=expected):
        create(db)
    with database.read_session() as db:
        assert db.query(table).filter_by(name="twin").count() == 1
        created = db.query(AuditEvent).filter(AuditEvent.action == f"{what}.created").count()
        assert created == (0 if not database.is_sqlite else 1)  # the refused one left nothing
