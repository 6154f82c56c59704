"""The robot's hot path writes rows exactly as the ORM would, and behaves like ORM work.

app.services.sessions.step_store runs hand-written SQL on the driver's cursor; everything else in
trustlab reads those rows through the ORM. These tests pin the contract on both engines: the stored
form of every column type, errors surfacing as SQLAlchemy's, one cursor per transaction, ORM objects
never served stale after a raw write, and the statement counts of a prompt and an answer.
"""

from __future__ import annotations

import threading
import uuid
from datetime import UTC, datetime, timedelta, timezone

import pytest
from sqlalchemy import event, select, text
from sqlalchemy.exc import IntegrityError

from app.services.sessions import step_store
from app.sql import Cursor, Statement
from app.tables import Answer, AuditEvent, LearnerState, Prompt, Run, Station, StudySession
from tests.conftest import Lab


def _answered_step(lab: Lab) -> tuple[dict[str, object], dict[str, object]]:
    lab.enrol_and_assign()
    lab.start_session()  # the familiarisation run
    step = lab.prompt("conation")
    reply = lab.answer(step["step_id"], "yes")
    return step, reply


def test_rows_written_by_the_store_read_back_through_the_orm(lab: Lab) -> None:
    before = datetime.now(UTC)
    step, reply = _answered_step(lab)
    after = datetime.now(UTC)
    with lab.database.read_session() as db:
        prompt = db.get(Prompt, step["step_id"])
        answer = db.scalar(select(Answer).where(Answer.prompt_id == step["step_id"]))
        audit = db.scalar(select(AuditEvent).where(AuditEvent.action == "answer.recorded"))
        run = db.scalar(select(Run))
        session = db.scalar(select(StudySession))
    assert prompt is not None and answer is not None and audit is not None
    assert run is not None and session is not None
    for stamp in (prompt.prompted_at, answer.answered_at, audit.occurred_at, run.started_at):
        assert stamp.tzinfo is not None and before <= stamp <= after
    assert session.started_at <= prompt.prompted_at <= answer.answered_at
    assert prompt.probabilities == step["probabilities"]
    assert all(isinstance(p, float) for p in prompt.probabilities)
    assert prompt.adapts is False and answer.answer is True
    assert answer.probabilities_after == reply["probabilities"]
    assert answer.reply == reply["reply"] and answer.confidence == reply["confidence"]
    assert audit.details == {"step_id": step["step_id"], "answer": True, "learner_version": 0}
    assert audit.actor == "lab-1/pepper" and audit.actor_kind == "device"


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)
def test_sqlite_timestamps_have_sqlalchemys_own_text_form(lab: Lab) -> None:
    """Ordering by a timestamp compares text on SQLite: ORM and store rows must sort together.
    (PostgreSQL stores timestamptz, which its driver converts.)"""
    _answered_step(lab)
    with lab.database.read_session() as db:
        raw = db.execute(text("SELECT answered_at FROM answer")).scalar_one()
        orm = db.execute(text("SELECT enrolled_at FROM participant")).scalar_one()
    assert len(raw) == len(orm) == len("2026-12-01 15:26:34.437738")
    assert raw[10] == orm[10] == " " and raw[19] == orm[19] == "."
    exact = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)  # no microseconds: still six digits
    with lab.database.read_session() as db:
        cursor = Cursor.of(db)
        assert cursor.timestamp(exact) == "2026-01-02 03:04:05.000000"
        elsewhere = exact.astimezone(timezone(timedelta(hours=2)))  # the same instant
        assert cursor.timestamp(elsewhere) == "2026-01-02 03:04:05.000000"


def test_driver_errors_surface_as_sqlalchemys(lab: Lab) -> None:
    step, _ = _answered_step(lab)
    with lab.database.writing() as db:
        cursor = Cursor.of(db)
        duplicate = step_store.NewAnswer(
            prompt_id=int(str(step["step_id"])),
            participant_id=1,
            answer=False,
            reward=0.0,
            probabilities_after=[0.25] * 4,
            p_preferred=None,
            probability=0.25,
            confidence_level=0,
            confidence="low",
            reply="x",
            learner_version=0,
            idempotency_key="duplicate",
            processing_ms=0.0,
            device_id=None,
            actor="test",
        )
        with pytest.raises(IntegrityError):
            step_store.insert_answer(cursor, duplicate)
        # SQLAlchemy's handler closed the driver cursor: the transaction gets a fresh one (on
        # SQLite it may go on after the failed statement; PostgreSQL needs the rollback first).
        after = Cursor.of(db)
        assert after is not cursor
        if lab.database.is_sqlite:
            assert after.row(Statement("SELECT count(*) FROM answer"), {})[0] == 1
        db.rollback()
    with lab.database.read_session() as db:
        assert len(db.scalars(select(Answer)).all()) == 1


def test_one_cursor_per_transaction(lab: Lab) -> None:
    lab.enrol_and_assign()
    with lab.database.writing() as db:
        first = Cursor.of(db)
        assert Cursor.of(db) is first
        db.commit()
        second = Cursor.of(db)
        assert second is not first and Cursor.of(db) is second
        db.rollback()
        assert Cursor.of(db) is not second


def test_a_store_write_expires_what_the_orm_loaded(lab: Lab) -> None:
    lab.enrol_and_assign()
    with lab.database.writing() as db:
        learner = db.scalars(select(LearnerState)).first()
        assert learner is not None and learner.version == 0
        row = step_store.learner(
            Cursor.of(db), participant_id=learner.participant_id, category=learner.category
        )
        assert row is not None
        assert step_store.save_learner(Cursor.of(db), row=row, state={"moved": True}).count == 1
        assert learner.version == 1  # reloaded, not the stale 0
        again = step_store.save_learner(Cursor.of(db), row=row, state={"moved": True})
        assert again.count == 0  # the stored version is no longer the one it started from
        db.rollback()


def test_statements_are_written_once_in_both_parameter_styles() -> None:
    statement = Statement(
        "SELECT a FROM t WHERE x = :x AND y = :y_name AND z = CAST(0 AS text) {lock}",
        lock_of="t",
    )
    assert statement.text(postgres=False) == (
        "SELECT a FROM t WHERE x = :x AND y = :y_name AND z = CAST(0 AS text)"
    )
    assert statement.text(postgres=True) == (
        "SELECT a FROM t WHERE x = %(x)s AND y = %(y_name)s AND z = CAST(0 AS text)"
    )
    assert statement.text(postgres=True, lock=True).endswith("FOR UPDATE OF t")
    assert statement.text(postgres=False, lock=True) == statement.text(postgres=False)


def _statements_of(lab: Lab, request: object) -> list[str]:
    database = lab.app.state.database
    statements: list[str] = []

    def count(_conn: object, _cursor: object, statement: str, *_: object) -> None:
        if threading.current_thread().name != "trustlab-activity" and statement != "BEGIN":
            statements.append(statement)

    event.listen(database.engine, "before_cursor_execute", count)
    try:
        assert callable(request)
        request()
    finally:
        event.remove(database.engine, "before_cursor_execute", count)
    return [s for s in statements if not s.startswith("BEGIN")]


def test_a_prompt_takes_a_fixed_small_number_of_statements(lab: Lab) -> None:
    """The device with its seat; the latest run and its prompts; the learner; INSERT prompt;
    PostgreSQL adds the timeline lock and one pg_notify. BEGIN/COMMIT not counted; the
    learner's state is read only when this process has no live copy (not here: warmed up)."""
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()  # the familiarisation run: every learner is now live in this process
    lab.start_session()
    responses = []
    sql = _statements_of(
        lab,
        lambda: responses.append(
            lab.robot.post("/api/v1/station/prompts", json={"category": "affection"})
        ),
    )
    assert responses[0].status_code == 201, responses[0].text
    expected = 5 if lab.database.is_sqlite else 7
    assert len(sql) == expected, "\n".join(sql)


def test_a_repeated_answer_changes_nothing_and_takes_no_write(lab: Lab) -> None:
    step, reply = _answered_step(lab)
    responses = []
    sql = _statements_of(
        lab,
        lambda: responses.append(
            lab.robot.post(
                f"/api/v1/station/steps/{step['step_id']}/answer",
                json={"answer": "yes", "idempotency_key": uuid.uuid4().hex},
            )
        ),
    )
    again = responses[0].json()
    assert again["replayed"] is True and again["reply"] == reply["reply"]
    assert not [s for s in sql if s.lstrip().upper().startswith(("INSERT", "UPDATE"))], sql


def test_store_statements_see_and_keep_the_sessions_pending_orm_changes(lab: Lab) -> None:
    """Like the ORM's autoflush: pending changes are flushed before a statement, so the
    statement sees them and a write's expiry cannot discard them (PostgreSQL's events at commit
    run on this cursor after ORM work)."""
    lab.enrol_and_assign()
    with lab.database.writing() as db:
        station = db.scalars(select(Station)).one()
        station.name = "renamed"  # dirty, not flushed
        assert step_store.station_seat(Cursor.of(db), name="renamed") is not None
        station.name = "renamed again"
        row = step_store.learner(Cursor.of(db), participant_id=1, category="conation")
        assert row is not None
        step_store.save_learner(Cursor.of(db), row=row, state={"moved": True})
        db.commit()
    with lab.database.read_session() as db:
        assert db.scalars(select(Station.name)).one() == "renamed again"
