"""Changes to one participant's timeline that meet: each waits for the other and then sees what it
committed (step_store.lock_timeline). On PostgreSQL the second transaction is held at its lock
until the first commits; on SQLite it queues for the write lock. Either way the outcome must be
the one a serial order gives."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from sqlalchemy import event, select, text
from sqlalchemy.orm import Session

from app.errors import Conflict
from app.services.audit import Actor
from app.services.sessions import runtime, verify
from app.tables import AuditEvent, Run, StudySession
from tests.conftest import Lab

ROBOT, EXPERIMENTER = Actor.system("robot"), Actor.system("experimenter")


def _wait_until_blocked(lab: Lab, deadline: float) -> None:
    """PostgreSQL: until a transaction waits for a row lock (the second one, at its lock).
    SQLite: the second one cannot begin before the first commits, so there is nothing to wait
    for."""
    if lab.database.is_sqlite:
        return
    while time.monotonic() < deadline:
        with lab.database.engine.connect() as connection:
            waiting = connection.execute(
                text(
                    "SELECT count(*) FROM pg_stat_activity "
                    "WHERE wait_event_type = 'Lock' AND datname = current_database()"
                )
            ).scalar_one()
        if waiting:
            return
        time.sleep(0.01)
    raise AssertionError("the second transaction never waited for the lock")


def _meet(lab: Lab, first: Callable[[Session], Any], second: Callable[[Session], Any]) -> dict:
    """Run ``first`` until its commit, start ``second``, and let ``first`` commit only once
    ``second`` waits for it; what each returned (or the exception it raised)."""
    at_commit, go = threading.Event(), threading.Event()
    out: dict[str, Any] = {}

    def run(name: str, work: Callable[[Session], Any], hold: bool) -> None:
        with lab.database.writing() as db:
            if hold:

                @event.listens_for(db, "before_commit")
                def _hold(_session: Session) -> None:
                    at_commit.set()
                    go.wait(10)

            try:
                out[name] = work(db)
            except Exception as exc:  # reported to the test
                out[name] = exc

    a = threading.Thread(target=run, args=("first", first, True))
    a.start()
    assert at_commit.wait(10)
    b = threading.Thread(target=run, args=("second", second, False))
    b.start()
    try:
        _wait_until_blocked(lab, time.monotonic() + 60)
    finally:
        go.set()
        a.join(10)
        b.join(10)
    return out


def _complete_first_run_of_session_1(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()  # familiarisation
    lab.start_session()
    for category in ("conation", "affection", "cognition"):
        lab.answer(lab.prompt(category)["step_id"], "no")


def _prompt(category: str) -> Callable[[Session], Any]:
    return lambda db: runtime.request_prompt(
        db, station_name="lab-1", category=category, actor=ROBOT
    )


def _end_session(db: Session) -> Any:
    return runtime.end_session(db, station_name="lab-1", actor=EXPERIMENTER)


def _timeline(lab: Lab) -> tuple[list[tuple[int, str]], list[tuple[int, int, str]]]:
    with lab.database.read_session() as db:
        sessions = [(s.number, str(s.status)) for s in db.scalars(select(StudySession))]
        runs = [(r.session_id, r.number, str(r.status)) for r in db.scalars(select(Run))]
    return sessions, runs


def _verify_clean(lab: Lab) -> None:
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    assert report.ok, report.findings


def test_ending_a_session_while_a_prompt_opens_its_next_run_ends_that_run(lab: Lab) -> None:
    _complete_first_run_of_session_1(lab)
    out = _meet(lab, _prompt("conation"), _end_session)
    assert out["first"].run_number == 2 and out["first"].created
    assert not isinstance(out["second"], Exception), out["second"]
    sessions, runs = _timeline(lab)
    assert sessions[-1] == (1, "ended_early")
    assert [status for _, number, status in runs if number == 2] == ["ended_early"]
    _verify_clean(lab)
    late = lab.robot.post(
        f"/api/v1/station/steps/{out['first'].prompt.id}/answer",
        json={"answer": "yes", "idempotency_key": "late"},
    )
    assert late.status_code == 409, late.text  # the run has ended: no more learning


def test_ending_a_session_while_its_last_answer_commits_leaves_it_completed(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()  # familiarisation: one run of three categories
    for category in ("conation", "affection"):
        lab.answer(lab.prompt(category)["step_id"], "no")
    last = lab.prompt("cognition")

    def answer(db: Session) -> Any:
        return runtime.record_answer(
            db,
            station_name="lab-1",
            step_id=int(str(last["step_id"])),
            answer=True,
            idempotency_key="last",
            actor=ROBOT,
        )

    out = _meet(lab, answer, _end_session)
    assert out["first"].session_completed
    assert isinstance(out["second"], Conflict), out["second"]
    sessions, _ = _timeline(lab)
    assert sessions == [(0, "completed")]
    with lab.database.read_session() as db:
        ended = db.scalars(select(AuditEvent).where(AuditEvent.action == "session.ended")).all()
    assert len(ended) == 1
    _verify_clean(lab)


def test_two_prompts_for_a_category_at_a_run_boundary_get_the_same_step(lab: Lab) -> None:
    _complete_first_run_of_session_1(lab)
    out = _meet(lab, _prompt("conation"), _prompt("conation"))
    assert not isinstance(out["second"], Exception), out["second"]
    assert out["first"].created and not out["second"].created
    assert out["second"].prompt.id == out["first"].prompt.id
    assert out["second"].run_number == out["first"].run_number == 2
    _verify_clean(lab)
