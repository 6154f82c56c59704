"""Migrations produce exactly the ORM's schema and go up and down cleanly on both engines."""

from __future__ import annotations

from datetime import UTC, datetime
from functools import partial

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import JSON, Connection, MetaData, Table, inspect, select, text
from sqlalchemy.exc import DBAPIError

from app import schema
from app.db import Database
from app.errors import Conflict
from app.protocol import default_protocol
from app.services import audit
from app.services.audit import Actor
from app.tables import AuditEvent, Base
from tests.conftest import sqlite_only


def _differences(database: Database) -> list[object]:
    with database.engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        return list(compare_metadata(context, Base.metadata))


def test_migrations_match_the_orm(blank_database_url: str) -> None:
    database = Database(blank_database_url)
    schema.upgrade(database)
    assert schema.current_revision(database) == schema.head_revision()
    assert _differences(database) == []
    database.dispose()


def test_revisions_are_read_as_alembic_reads_them(blank_database_url: str) -> None:
    """Commands compare the two without Alembic (app.schema); Alembic's answers must agree,
    before, between and after migrations."""
    from alembic.script import ScriptDirectory

    script = ScriptDirectory.from_config(schema.alembic_config())
    assert schema.head_revision() == script.get_current_head()
    database = Database(blank_database_url)

    def alembic_current() -> str | None:
        with database.engine.connect() as connection:
            return MigrationContext.configure(connection).get_current_revision()

    assert schema.current_revision(database) is None
    assert alembic_current() is None
    for revision in ("0001", "0012", "head"):
        schema.upgrade(database, revision)
        assert schema.current_revision(database) == alembic_current()
    assert schema.current_revision(database) == script.get_current_head()
    schema.downgrade(database, "base")
    assert schema.current_revision(database) is None
    assert alembic_current() is None
    database.dispose()


def test_upgrade_downgrade_upgrade(blank_database_url: str) -> None:
    database = Database(blank_database_url)
    schema.upgrade(database)
    schema.downgrade(database, "base")
    assert schema.current_revision(database) is None
    remaining = set(inspect(database.engine).get_table_names()) - {"alembic_version"}
    assert remaining == set()
    schema.upgrade(database)
    assert _differences(database) == []
    database.dispose()


def test_sqlite_runs_with_wal_and_foreign_keys(tmp_path: object) -> None:
    database = Database(f"sqlite:///{tmp_path}/pragmas.sqlite3")
    with database.engine.connect() as connection:
        assert connection.execute(text("PRAGMA journal_mode")).scalar() == "wal"
        assert connection.execute(text("PRAGMA foreign_keys")).scalar() == 1
    database.dispose()


def test_audit_log_is_append_only(database: Database) -> None:
    with database.writing() as db:
        audit.record(db, actor=Actor.system("tests"), action="test.event", subject="x")
        db.commit()
    for statement in ("UPDATE audit_event SET action = 'tampered'", "DELETE FROM audit_event"):
        with database.writing() as db, pytest.raises(DBAPIError, match="append-only"):
            db.execute(text(statement))
    with database.read_session() as db:
        assert db.query(AuditEvent).one().action == "test.event"


def test_0006_keeps_the_recorded_sign_in_attempts(blank_database_url: str) -> None:
    """login_attempt.cleared_at (an admin's unlock) arrives empty: every recorded failure still
    counts after the upgrade, and a downgrade keeps the attempts."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0005")
    insert = text(
        "INSERT INTO login_attempt (username, client_address, succeeded, attempted_at) "
        "VALUES ('ada', '10.0.0.1', false, CURRENT_TIMESTAMP)"
    )
    with database.engine.begin() as connection:
        connection.execute(insert)
    schema.upgrade(database, "0006")
    with database.engine.connect() as connection:
        rows = connection.execute(text("SELECT username, cleared_at FROM login_attempt")).all()
    assert [tuple(row) for row in rows] == [("ada", None)]
    schema.downgrade(database, "0005")
    with database.engine.connect() as connection:
        assert connection.execute(text("SELECT count(*) FROM login_attempt")).scalar() == 1
        columns = {c["name"] for c in inspect(connection).get_columns("login_attempt")}
    assert "cleared_at" not in columns
    database.dispose()


def test_0007_leaves_every_study_blinded_as_it_was(blank_database_url: str) -> None:
    """study.unblinded_at arrives empty (a blinded study stays sealed after the upgrade), and a
    downgrade keeps the studies and what refers to them."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0006")
    with database.engine.begin() as connection:
        connection.execute(
            text(
                "INSERT INTO study (name, title, status, protocol, protocol_source, "
                "protocol_sha256, allocation_seed, created_at, created_by) VALUES ('s', 'S', "
                "'open', '{}', '', 'h', 'seed', CURRENT_TIMESTAMP, 'tests')"
            )
        )
        connection.execute(
            text(
                "INSERT INTO participant (study_id, code, stratum, strata, status, enrolled_at, "
                "enrolled_by, withdrawal_reason) SELECT id, 'P001', '', '{}', 'active', "
                "CURRENT_TIMESTAMP, 'tests', '' FROM study"
            )
        )
    schema.upgrade(database, "0007")
    with database.engine.connect() as connection:
        rows = connection.execute(text("SELECT name, unblinded_at FROM study")).all()
    assert [tuple(row) for row in rows] == [("s", None)]
    schema.downgrade(database, "0006")
    with database.engine.connect() as connection:
        assert connection.execute(text("SELECT name FROM study")).scalars().all() == ["s"]
        assert connection.execute(text("SELECT count(*) FROM participant")).scalar() == 1
        columns = {c["name"] for c in inspect(connection).get_columns("study")}
    assert "unblinded_at" not in columns
    database.dispose()


def test_0008_hides_nothing_and_ties_no_station_to_a_study(blank_database_url: str) -> None:
    """The upgrade runs on a station that already has a device (no table copy on SQLite, whose
    foreign keys would refuse it): every study and station arrives shown and untied."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0007")
    with database.engine.begin() as connection:
        connection.execute(
            text(
                "INSERT INTO study (name, title, status, protocol, protocol_source, "
                "protocol_sha256, allocation_seed, created_at, created_by) VALUES ('s', 'S', "
                "'open', '{}', '', 'h', 'seed', CURRENT_TIMESTAMP, 'tests')"
            )
        )
        connection.execute(
            text("INSERT INTO station (name, created_at) VALUES ('lab-1', CURRENT_TIMESTAMP)")
        )
        connection.execute(
            text(
                "INSERT INTO device (station_id, label, key_hash, key_prefix, created_at, "
                "created_by) SELECT id, 'robot', 'hash', 'tlk_ab', CURRENT_TIMESTAMP, 'tests' "
                "FROM station"
            )
        )
    schema.upgrade(database, "0008")
    with database.engine.connect() as connection:
        stations = connection.execute(text("SELECT name, study_id, archived_at FROM station"))
        assert [tuple(row) for row in stations] == [("lab-1", None, None)]
        shown = connection.execute(text("SELECT name, archived_at FROM study")).all()
        assert [tuple(row) for row in shown] == [("s", None)]
        assert connection.execute(text("SELECT count(*) FROM device")).scalar() == 1
    schema.upgrade(database)
    assert _differences(database) == []
    database.dispose()


def test_0011_turns_the_sign_in_flag_into_outcomes(blank_database_url: str) -> None:
    """Old rows keep counting as they did (a failure stays a failure for its window); on the way
    down, attempts that never failed (pending, abandoned) are cleared so the old code does not
    count them."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0010")
    with database.engine.begin() as connection:
        for succeeded in ("true", "false"):
            connection.execute(
                text(
                    "INSERT INTO login_attempt (username, client_address, succeeded, attempted_at)"
                    f" VALUES ('ada', '', {succeeded}, CURRENT_TIMESTAMP)"
                )
            )
    schema.upgrade(database, "0011")
    with database.engine.begin() as connection:
        outcomes = connection.execute(text("SELECT outcome FROM login_attempt ORDER BY id"))
        assert list(outcomes.scalars()) == ["succeeded", "failed"]
        for outcome in ("pending", "abandoned"):
            connection.execute(
                text(
                    "INSERT INTO login_attempt (username, client_address, outcome, attempted_at)"
                    f" VALUES ('ada', '', '{outcome}', CURRENT_TIMESTAMP)"
                )
            )
        with pytest.raises(DBAPIError), connection.begin_nested():
            connection.execute(
                text(
                    "INSERT INTO login_attempt (username, client_address, outcome, "
                    "attempted_at) VALUES ('ada', '', 'maybe', CURRENT_TIMESTAMP)"
                )
            )
    schema.downgrade(database, "0010")
    with database.engine.connect() as connection:
        rows = connection.execute(
            text("SELECT succeeded, cleared_at IS NULL FROM login_attempt ORDER BY id")
        )
        assert [(bool(s), bool(c)) for s, c in rows] == [
            (True, True),
            (False, True),
            (False, False),
            (False, False),
        ]
    database.dispose()


def test_0012_gives_each_blinded_study_its_labels(blank_database_url: str) -> None:
    """A blinded study with participants keeps the labels it has shown (the protocol's, by
    position: C1 is Group A); one nobody is enrolled in gets a random draw of the same labels; a
    study that is not blinded gets none."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0011")
    blinded = default_protocol().protocol.model_dump(mode="json")
    blinded["study"]["blinded"] = True
    with database.engine.begin() as connection:
        study = Table("study", MetaData(), autoload_with=connection)
        participant = Table("participant", MetaData(), autoload_with=connection)
        for name, protocol in (
            ("running", blinded),
            ("empty", blinded),
            ("open", default_protocol().protocol.model_dump(mode="json")),
        ):
            connection.execute(
                study.insert().values(
                    name=name,
                    title=name,
                    status="open",
                    protocol=protocol,
                    protocol_source="",
                    protocol_sha256="0" * 64,
                    allocation_seed="0" * 64,
                    created_at=datetime.now(UTC),
                    created_by="tests",
                )
            )
        running = connection.execute(select(study.c.id).where(study.c.name == "running"))
        connection.execute(
            participant.insert().values(
                study_id=running.scalar_one(),
                code="P001",
                stratum="",
                strata={},
                status="active",
                enrolled_at=datetime.now(UTC),
                enrolled_by="tests",
                withdrawal_reason="",
            )
        )
    schema.upgrade(database, "0012")
    with database.engine.connect() as connection:
        study = Table("study", MetaData(), autoload_with=connection)
        labels = dict(connection.execute(select(study.c.name, study.c.neutral_labels)).all())
    assert labels["running"] == {"C1": "Group A", "C2": "Group B"}
    assert labels["empty"] in (
        {"C1": "Group A", "C2": "Group B"},
        {"C1": "Group B", "C2": "Group A"},
    )
    assert labels["open"] is None
    with database.engine.begin() as connection:  # a draw the protocol's labels would contradict
        swapped = {"C1": "Group B", "C2": "Group A"}
        connection.execute(
            study.update().where(study.c.name == "empty"), {"neutral_labels": swapped}
        )
    with pytest.raises(Conflict, match="would lose the neutral labels drawn for empty"):
        schema.downgrade(database, "0011")
    assert schema.current_revision(database) == "0012"
    with database.engine.connect() as connection:
        kept = connection.execute(select(study.c.neutral_labels).where(study.c.name == "empty"))
        assert kept.scalar_one() == swapped
    with database.engine.begin() as connection:  # as the protocol shows them: nothing is lost
        connection.execute(study.delete().where(study.c.name == "empty"))
    schema.downgrade(database, "0011")
    assert "neutral_labels" not in {
        c["name"] for c in inspect(database.engine).get_columns("study")
    }
    database.dispose()


def test_0014_keeps_recorded_answers_from_a_downgrade(blank_database_url: str) -> None:
    """0014 adds the recogniser's name (NULL for older answers) and the recordings' table; going
    back below it would delete recordings, so it is refused while there are any."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0014")
    _insert_without_foreign_keys(
        database,
        "INSERT INTO answer_audio (answer_id, participant_id, wav, seconds, recorded_at) "
        "VALUES (1, 1, {blob}, 0.5, CURRENT_TIMESTAMP)",
    )
    with pytest.raises(Conflict, match="would delete 1 recorded answer"):
        schema.downgrade(database, "0013")
    assert schema.current_revision(database) == "0014"
    with database.engine.begin() as connection:
        connection.execute(text("DELETE FROM answer_audio"))
    schema.downgrade(database, "0013")
    tables = set(inspect(database.engine).get_table_names())
    assert "answer_audio" not in tables
    assert "transcript_engine" not in {
        c["name"] for c in inspect(database.engine).get_columns("answer")
    }
    database.dispose()


def _insert_without_foreign_keys(database: Database, statement: str) -> None:
    """Run an INSERT without the rows its foreign keys name (``{blob}``: a small binary value);
    on the driver's own connection, where SQLite's foreign keys can be switched off."""
    raw = database.engine.raw_connection()
    try:
        cursor = raw.cursor()
        if database.is_sqlite:
            cursor.execute("PRAGMA foreign_keys = OFF")
            cursor.execute(statement.format(blob="X'52494646'"))
            cursor.execute("PRAGMA foreign_keys = ON")
        else:
            cursor.execute("SET session_replication_role = replica")
            cursor.execute(statement.format(blob="'RIFF'::bytea"))
            cursor.execute("SET session_replication_role = origin")
        raw.commit()
    finally:
        raw.close()


def test_0017_keeps_earlier_consents_as_version_1(blank_database_url: str) -> None:
    """Participants who consented before 0017 get a version-1 consent record from their consent
    page's answers; going back is refused while a study has a later version of the text."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0016")
    now = datetime.now(UTC)
    with database.engine.begin() as connection:
        tables = MetaData()
        tables.reflect(connection, only=["study", "participant", "submission", "response"])
        study_id = connection.execute(
            tables.tables["study"]
            .insert()
            .values(
                name="old",
                title="old",
                status="open",
                protocol=default_protocol().protocol.model_dump(mode="json"),
                protocol_source="",
                protocol_sha256="0" * 64,
                allocation_seed="0" * 64,
                created_at=now,
                created_by="tests",
            )
        ).inserted_primary_key[0]
        participant = tables.tables["participant"]
        for code in ("P001", "P002"):
            connection.execute(
                participant.insert().values(
                    study_id=study_id,
                    code=code,
                    stratum="",
                    strata={},
                    status="active",
                    enrolled_at=now,
                    enrolled_by="tests",
                    withdrawal_reason="",
                )
            )
        consented = connection.execute(
            select(participant.c.id).where(participant.c.code == "P001")
        ).scalar_one()
        connection.execute(
            tables.tables["submission"].insert(),
            [
                {
                    "participant_id": consented,
                    "instrument": "consent",
                    "submitted_at": now,
                    "revision": 1,
                }
            ],
        )
        stored = {"accepted": "yes", "version": "1.0", "consent_language": "en"}
        stored["consent_sha256"] = "a" * 64
        connection.execute(
            tables.tables["response"].insert(),
            [
                {
                    "participant_id": consented,
                    "instrument": "consent",
                    "item": item,
                    "value": value,
                    "answered_at": now,
                }
                for item, value in stored.items()
            ],
        )
    schema.upgrade(database)
    with database.engine.begin() as connection:
        record = Table("consent_record", MetaData(), autoload_with=connection)
        rows = connection.execute(
            select(
                record.c.participant_id,
                record.c.version,
                record.c.label,
                record.c.language,
                record.c.sha256,
                record.c.accepted,
            )
        ).all()
        assert [tuple(row) for row in rows] == [(consented, 1, "1.0", "en", "a" * 64, True)]
        versions = Table("consent_version", MetaData(), autoload_with=connection)
        connection.execute(
            versions.insert().values(
                study_id=study_id,
                version=2,
                label="2",
                texts={"en": "new"},
                sha256={"en": "b" * 64},
                created_at=now,
                created_by="tests",
                reason="",
            )
        )
    with pytest.raises(Conflict, match="would delete 1 later consent version"):
        schema.downgrade(database, "0016")
    with database.engine.begin() as connection:
        connection.execute(text("DELETE FROM consent_version"))
    schema.downgrade(database, "0016")
    assert "consent_record" not in inspect(database.engine).get_table_names()
    database.dispose()


def test_0021_never_reuses_ids_and_ties_presence_to_whoever_was_seated(
    blank_database_url: str,
) -> None:
    """0021 copies prompt, answer and learner into AUTOINCREMENT tables on SQLite (rows, keys
    and the append-only guards kept) and gives room presence its participant: a row reported
    since the station's participant sat down is theirs (a line said before is cleared), any
    other row is deleted."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0020")
    earlier, seated, report = (datetime(2026, 1, 1, hour, tzinfo=UTC) for hour in (9, 10, 11))
    with database.engine.begin() as connection:
        row = partial(_insert_row, connection)
        row("study", id=1, name="s", status="open")
        for code in (7, 8):
            row("participant", id=code, study_id=1, code=f"P{code}", status="active")
        row("station", id=1, name="seated", participant_id=7, assigned_at=seated)
        row("station", id=2, name="free")
        row("station", id=3, name="reseated", participant_id=8, assigned_at=report)
        for station, said_at, updated_at in (
            (1, earlier, report),
            (2, earlier, earlier),
            (3, earlier, seated),
        ):
            row(
                "room_presence",
                station_id=station,
                utterance_kind="participant",
                utterance=f"said at {station}",
                utterance_at=said_at,
                updated_at=updated_at,
            )
        row("study_session", id=1, participant_id=7, station_id=1, status="running")
        row("run", id=1, session_id=1, participant_id=7, status="running")
        row("prompt", id=41, participant_id=7, run_id=1, probabilities=[0.5])
        row("answer", id=42, prompt_id=41, participant_id=7, probabilities_after=[0.5])
        row("learner", id=43, participant_id=7, category="c")
    schema.upgrade(database)
    with database.engine.connect() as connection:
        presence = connection.execute(
            text("SELECT station_id, participant_id, utterance FROM room_presence")
        ).all()
        assert presence == [(1, 7, None)]
        assert connection.execute(text("SELECT id FROM prompt")).scalars().all() == [41]
        if database.is_sqlite:
            for table, highest in (("prompt", 41), ("answer", 42), ("learner", 43)):
                sql = connection.execute(
                    text("SELECT sql FROM sqlite_master WHERE name = :t"), {"t": table}
                ).scalar_one()
                assert "AUTOINCREMENT" in sql, sql
                seq = text("SELECT seq FROM sqlite_sequence WHERE name = :t")
                assert connection.execute(seq, {"t": table}).scalar_one() == highest
    for statement in ("UPDATE prompt SET question = 'x'", "DELETE FROM answer"):
        with database.engine.begin() as connection, pytest.raises(DBAPIError, match="append"):
            connection.execute(text(statement))
    schema.downgrade(database, "0020")
    with database.engine.connect() as connection:
        assert connection.execute(text("SELECT id FROM answer")).scalars().all() == [42]
        if database.is_sqlite:
            sql = connection.execute(
                text("SELECT sql FROM sqlite_master WHERE name = 'prompt'")
            ).scalar_one()
            assert "AUTOINCREMENT" not in sql
    with database.engine.begin() as connection, pytest.raises(DBAPIError, match="append"):
        connection.execute(text("DELETE FROM prompt"))
    database.dispose()


def test_0022_names_the_consent_texts_own_version_protocol_version(
    blank_database_url: str,
) -> None:
    """The consent answer ``version`` (the text's version as its protocol names it) becomes
    ``protocol_version``; other instruments' items of that name and the downgrade are kept."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0021")
    with database.engine.begin() as connection:
        row = partial(_insert_row, connection)
        row("study", id=1, name="s", status="open")
        row("participant", id=1, study_id=1, code="P1", status="active")
        row("response", participant_id=1, instrument="consent", item="version", value="1.0")
        row("response", participant_id=1, instrument="consent", item="consent_version", value="1")
        row("response", participant_id=1, instrument="device", item="version", value="7")

    def items() -> list[tuple[str, str]]:
        with database.engine.connect() as connection:
            rows = connection.execute(text("SELECT instrument, item FROM response ORDER BY id"))
            return [(r[0], r[1]) for r in rows]

    schema.upgrade(database, "0022")
    assert items() == [
        ("consent", "protocol_version"),
        ("consent", "consent_version"),
        ("device", "version"),
    ]
    schema.downgrade(database, "0021")
    assert items()[0] == ("consent", "version")
    database.dispose()


def _insert_row(connection: Connection, table_name: str, **values: object) -> None:
    """One row of a table as the schema has it at this revision: the values given, and a
    placeholder of the right type in every other column that needs one."""
    table = Table(table_name, MetaData(), autoload_with=connection)
    row = dict(values)
    for column in table.columns:
        if column.name in row or column.nullable or column.primary_key:
            continue
        if isinstance(column.type, JSON):
            row[column.name] = {}
        else:
            placeholder = {int: 0, float: 0.0, bool: False, str: "x"}
            kind = column.type.python_type
            row[column.name] = (
                datetime(2026, 1, 1, tzinfo=UTC) if kind is datetime else placeholder[kind]
            )
    connection.execute(table.insert().values(row))


@sqlite_only("SQLite's key enforcement is off during its migrations; PostgreSQL's never is")
def test_sqlite_migrations_check_every_key_and_leave_enforcement_on(
    blank_database_url: str,
) -> None:
    database = Database(blank_database_url)
    schema.upgrade(database, "0020")
    _insert_without_foreign_keys(
        database,
        "INSERT INTO learner (id, participant_id, category, kind, n_arms, config, "
        "initial_state, state, version, updated_at) "
        "VALUES (1, 99, 'c', 'exp3', 4, '{{}}', '{{}}', '{{}}', 0, CURRENT_TIMESTAMP)",
    )
    with pytest.raises(Conflict, match="1 rows' keys would point nowhere"):
        schema.upgrade(database)
    assert schema.current_revision(database) == "0020"
    with database.engine.connect() as connection:
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        connection.exec_driver_sql("DELETE FROM learner")
        connection.commit()
    schema.upgrade(database)
    assert schema.current_revision(database) == schema.head_revision()
    with database.engine.connect() as connection:
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    database.dispose()
