"""The session runtime over the robot API: timeline, order, exactly-once answers, verify."""

from __future__ import annotations

import threading
import uuid

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, func, select, text, update
from sqlalchemy.exc import DBAPIError

from app.services.sessions import verify
from app.tables import (
    Allocation,
    Answer,
    LearnerState,
    Participant,
    Prompt,
    StudySession,
)
from models.replies import exp3_belief, heard_probability
from tests.conftest import Lab


def _learner_versions(lab: Lab) -> dict[str, int]:
    with lab.database.read_session() as db:
        return {row.category: row.version for row in db.scalars(select(LearnerState))}


def _report(lab: Lab) -> verify.VerifyReport:
    with lab.database.read_session() as db:
        return verify.verify_study(db, study_name=lab.study)


def test_the_whole_timeline(lab: Lab) -> None:
    code = lab.enrol_and_assign()
    state = lab.robot.get("/api/v1/station").json()
    assert state["participant"] == code
    assert state["expected"]["action"] == "start_session"
    assert (
        state["expected"]["message"] == f"an experimenter starts the familiarisation run for {code}"
    )
    started = lab.start_session()
    assert started["session"]["familiarisation"] is True
    assert lab.run_session() == 3  # familiarisation: one run of three categories
    assert _learner_versions(lab) == {"conation": 0, "affection": 0, "cognition": 0}
    for number in range(1, 5):
        started = lab.start_session()
        assert started["session"]["number"] == number
        assert lab.run_session() == 9
    assert _learner_versions(lab) == {"conation": 12, "affection": 12, "cognition": 12}
    done = lab.robot.get("/api/v1/station").json()
    assert done["expected"] == {
        "action": "done",
        "message": f"{code} has finished every session",
        "categories": [],
        "step_id": None,
        "session": None,
    }
    with lab.database.read_session() as db:
        assert db.scalar(select(Participant.status)) == "completed"
        assert db.scalar(select(func.count()).select_from(Answer)) == 39
    report = _report(lab)
    assert report.ok, report.findings
    assert (report.learners, report.steps, report.answers) == (3, 39, 39)


def test_familiarisation_logs_but_never_adapts(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    step = lab.prompt("conation")
    assert step["adapts"] is False
    reply = lab.answer(step["step_id"], "yes")
    assert reply["probabilities"] == step["probabilities"]
    lab.run_session()
    lab.start_session()
    step = lab.prompt("conation")
    assert step["adapts"] is True
    reply = lab.answer(step["step_id"], "yes")
    assert reply["probabilities"] != step["probabilities"]
    # The shipped basis: the probability C1's Exp3 gave the yes it heard, through the slips.
    belief = exp3_belief(step["probabilities"][step["action"]], gamma=0.5, n_arms=4)
    assert reply["probability"] == pytest.approx(
        heard_probability(belief, said_yes=True, slip=0.05)
    )


def test_order_is_enforced_with_what_is_expected(lab: Lab) -> None:
    unassigned = lab.robot.post("/api/v1/station/prompts", json={"category": "conation"})
    assert unassigned.status_code == 409
    assert unassigned.json()["detail"] == (
        "no participant is assigned to station 'lab-1': an experimenter assigns one first"
    )
    code = lab.enrol_and_assign()
    early = lab.robot.post("/api/v1/station/prompts", json={"category": "conation"})
    assert early.status_code == 409
    assert early.json()["detail"] == (
        f"no session is running for {code}; expected: an experimenter starts the "
        f"familiarisation run for {code}"
    )
    lab.start_session()
    wrong = lab.robot.post("/api/v1/station/prompts", json={"category": "volition"})
    assert wrong.status_code == 422
    assert wrong.json()["detail"] == (
        "unknown category 'volition': expected one of conation, affection, cognition"
    )
    again = lab.experimenter.post("/api/v1/stations/lab-1/sessions")
    assert again.status_code == 409
    assert "the familiarisation run is already running" in again.json()["detail"]
    step = lab.prompt("affection")
    lab.answer(step["step_id"], "no")
    twice = lab.robot.post("/api/v1/station/prompts", json={"category": "affection"})
    assert twice.status_code == 409
    assert twice.json()["detail"] == (
        "affection was already answered in run 1 of the familiarisation run; "
        "expected one of: conation, cognition"
    )
    busy = lab.experimenter.post("/api/v1/stations/lab-1/runs")
    assert busy.status_code == 409
    assert "run 1 is still running (waiting for conation, cognition)" in busy.json()["detail"]


def test_open_prompt_is_handed_out_again(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    first = lab.robot.post("/api/v1/station/prompts", json={"category": "cognition"})
    second = lab.robot.post("/api/v1/station/prompts", json={"category": "cognition"})
    assert (first.status_code, second.status_code) == (201, 200)
    assert first.json()["step_id"] == second.json()["step_id"]
    assert second.json()["created"] is False
    state = lab.robot.get("/api/v1/station").json()
    assert [p["step_id"] for p in state["open_prompts"]] == [first.json()["step_id"]]
    assert state["expected"]["action"] == "answer"


def test_answers_are_applied_exactly_once(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    step = lab.prompt("conation")
    key = uuid.uuid4().hex
    first = lab.answer(step["step_id"], "yes", key)
    repeat = lab.answer(step["step_id"], "yes", key)
    assert first["replayed"] is False and repeat["replayed"] is True
    assert repeat["reply"] == first["reply"]
    assert repeat["probabilities"] == first["probabilities"]
    same_answer_new_key = lab.answer(step["step_id"], "yes")
    assert same_answer_new_key["replayed"] is True
    assert _learner_versions(lab)["conation"] == 1
    different = lab.robot.post(
        f"/api/v1/station/steps/{step['step_id']}/answer",
        json={"answer": "no", "idempotency_key": uuid.uuid4().hex},
    )
    assert different.status_code == 409
    assert different.json()["detail"] == (
        f"step {step['step_id']} was already answered 'yes'; a different answer is refused"
    )
    reused = lab.robot.post(
        f"/api/v1/station/steps/{step['step_id']}/answer",
        json={"answer": "no", "idempotency_key": key},
    )
    assert reused.status_code == 409
    assert "was used for the answer 'yes'" in reused.json()["detail"]
    assert _learner_versions(lab)["conation"] == 1


def test_simultaneous_duplicate_answers_update_once(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    step = lab.prompt("affection")
    key = uuid.uuid4().hex
    barrier = threading.Barrier(4)
    statuses: list[int] = []

    def post() -> None:
        barrier.wait(timeout=10)
        response = lab.robot.post(
            f"/api/v1/station/steps/{step['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": key},
        )
        statuses.append(response.status_code)

    threads = [threading.Thread(target=post) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=30)
    assert statuses == [200, 200, 200, 200]
    assert _learner_versions(lab)["affection"] == 1
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Answer)) == 4  # 3 familiarisation + 1


def test_runs_roll_over_and_can_end_early(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    for category in ("conation", "affection", "cognition"):
        lab.answer(lab.prompt(category)["step_id"], "no")
    assert lab.robot.get("/api/v1/station").json()["run"]["status"] == "completed"
    step = lab.prompt("cognition")  # starts run 2
    assert step["run"] == 2
    ended = lab.experimenter.post("/api/v1/stations/lab-1/runs/current/end")
    assert ended.json()["run"]["status"] == "ended_early"
    late = lab.robot.post(
        f"/api/v1/station/steps/{step['step_id']}/answer",
        json={"answer": "yes", "idempotency_key": "late"},
    )
    assert late.status_code == 409
    assert "which has ended" in late.json()["detail"]
    started = lab.experimenter.post("/api/v1/stations/lab-1/runs")
    assert started.json()["run"]["number"] == 3
    ended_session = lab.experimenter.post("/api/v1/stations/lab-1/sessions/current/end")
    assert ended_session.json()["session"]["status"] == "ended_early"
    assert lab.start_session()["session"]["number"] == 2
    report = _report(lab)
    assert report.ok, report.findings


def test_steps_of_other_stations_are_not_reachable(
    lab: Lab, app: object, user_client: object
) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    step = lab.prompt("conation")
    admin = lab.experimenter  # experimenters cannot issue keys; use the admin API via a new admin
    assert admin.post("/api/v1/stations", json={"name": "lab-2"}).status_code == 403
    from app.tables import Role  # local: keeps the fixture signature simple

    other_admin = user_client(Role.ADMIN)  # type: ignore[operator]
    other_admin.post("/api/v1/stations", json={"name": "lab-2"})
    other_key = other_admin.post("/api/v1/stations/lab-2/devices", json={}).json()["key"]
    with TestClient(app, headers={"Authorization": f"Bearer {other_key}"}) as other:  # type: ignore[arg-type]
        stolen = other.post(
            f"/api/v1/station/steps/{step['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": "x"},
        )
        assert stolen.status_code == 409  # lab-2 has nobody assigned
        lab.experimenter.post("/api/v1/studies/rt/participants", json={"code": "OTHER"})
        lab.experimenter.put(
            "/api/v1/stations/lab-2/participant", json={"study": "rt", "code": "OTHER"}
        )
        stolen = other.post(
            f"/api/v1/station/steps/{step['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": "x"},
        )
        assert stolen.status_code == 404
        assert stolen.json()["detail"] == (
            f"step {step['step_id']} is not a step of OTHER at station 'lab-2'"
        )


def test_device_keys_authenticate_and_revoke(lab: Lab, app: object, user_client: object) -> None:
    with TestClient(app) as anonymous:  # type: ignore[arg-type]
        missing = anonymous.get("/api/v1/station")
        assert missing.status_code == 401
        assert missing.json()["detail"] == (
            "send the device key as the header 'Authorization: Bearer tlk_…'"
        )
        wrong = anonymous.get("/api/v1/station", headers={"Authorization": "Bearer tlk_nope"})
        assert wrong.json()["detail"] == "unknown or revoked device key"
    from app.tables import Role

    admin = user_client(Role.ADMIN)  # type: ignore[operator]
    device_id = admin.get("/api/v1/stations").json()[0]["devices"][0]["id"]
    assert admin.post(f"/api/v1/devices/{device_id}/revoke").status_code == 200
    assert lab.robot.get("/api/v1/station").status_code == 401


def test_assignment_rules(lab: Lab) -> None:
    code = lab.enrol_and_assign()
    lab.start_session()
    other = lab.experimenter.post("/api/v1/studies/rt/participants", json={}).json()["code"]
    refused = lab.experimenter.put(
        "/api/v1/stations/lab-1/participant", json={"study": "rt", "code": other}
    )
    assert refused.status_code == 409
    assert refused.json()["detail"] == (
        f"station 'lab-1' is running a session with {code!r}: end that session first"
    )
    assert lab.experimenter.delete("/api/v1/stations/lab-1/participant").status_code == 409
    lab.experimenter.post(f"/api/v1/studies/rt/participants/{other}/withdraw", json={})
    withdrawn = lab.experimenter.put(
        "/api/v1/stations/lab-1/participant", json={"study": "rt", "code": other}
    )
    assert withdrawn.status_code == 409


def test_verify_finds_tampered_learners_and_allocations(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    lab.run_session()
    assert _report(lab).ok
    with lab.database.writing() as db:
        row = db.scalars(select(LearnerState).where(LearnerState.category == "cognition")).one()
        state = dict(row.state)
        db.execute(
            update(LearnerState)
            .where(LearnerState.id == row.id)
            .values(state={**state, "tampered": True})
        )
        db.commit()
    findings = _report(lab).findings
    assert [(f.check, f.detail) for f in findings] == [
        ("replay", "cognition learner: stored state differs from the replayed one")
    ]
    with lab.database.writing() as db:
        allocation = db.scalars(select(Allocation)).one()
        flipped = "C2" if allocation.condition == "C1" else "C1"
        db.execute(update(Allocation).values(condition=flipped))
        db.commit()
    checks = {f.check for f in _report(lab).findings}
    assert "allocation" in checks


def test_step_log_is_append_only(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.answer(lab.prompt("conation")["step_id"], "yes")
    for table in ("prompt", "answer"):
        with lab.database.writing() as db, pytest.raises(DBAPIError, match="append-only"):
            db.execute(text(f"DELETE FROM {table}"))
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Prompt)) == 1
        assert db.scalar(select(func.count()).select_from(StudySession)) == 1


def test_a_withdrawn_participant_gets_no_more_prompts_or_updates(lab: Lab) -> None:
    code = lab.enrol_and_assign()
    lab.start_session()
    step = lab.robot.post("/api/v1/station/prompts", json={"category": "conation"}).json()
    answered = {"answer": "yes", "idempotency_key": "before-withdrawal"}
    first = lab.robot.post(f"/api/v1/station/steps/{step['step_id']}/answer", json=answered)
    assert first.status_code == 200
    open_step = lab.robot.post("/api/v1/station/prompts", json={"category": "affection"}).json()
    lab.experimenter.post(f"/api/v1/studies/rt/participants/{code}/withdraw", json={})
    refused = lab.robot.post("/api/v1/station/prompts", json={"category": "cognition"})
    assert refused.status_code == 409
    assert refused.json()["detail"].startswith(f"{code} has withdrawn")
    late = lab.robot.post(
        f"/api/v1/station/steps/{open_step['step_id']}/answer",
        json={"answer": "no", "idempotency_key": "after-withdrawal"},
    )
    assert late.status_code == 409
    replay = lab.robot.post(f"/api/v1/station/steps/{step['step_id']}/answer", json=answered)
    assert replay.status_code == 200 and replay.json()["reply"] == first.json()["reply"]


def test_an_answer_takes_a_fixed_small_number_of_statements(lab: Lab) -> None:
    """Guards the hot path (docs/performance.md, "Robot API round trip"): the device with its
    station, participant and study; the step's session and run; the run's prompts with their
    answers' ids; the learner; then UPDATE learner, INSERT audit row, INSERT answer; PostgreSQL
    adds the timeline lock (before the run is read) and one pg_notify for all events.
    BEGIN/COMMIT not counted."""
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()  # the familiarisation run: its answers do not adapt
    lab.start_session()
    step = lab.prompt("conation")
    database = lab.app.state.database
    statements: list[str] = []

    def count(_conn: object, _cursor: object, statement: str, *_: object) -> None:
        if threading.current_thread().name != "trustlab-activity" and statement != "BEGIN":
            statements.append(statement)

    event.listen(database.engine, "before_cursor_execute", count)
    try:
        reply = lab.robot.post(
            f"/api/v1/station/steps/{step['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": uuid.uuid4().hex},
        )
    finally:
        event.remove(database.engine, "before_cursor_execute", count)
    assert reply.status_code == 200, reply.text
    assert reply.json()["run_completed"] is False
    sql = [s for s in statements if not s.startswith("BEGIN")]
    assert len(sql) == (7 if database.is_sqlite else 9), "\n".join(sql)


def test_values_the_database_cannot_hold_get_a_clear_4xx_and_change_nothing(lab: Lab) -> None:
    """An id beyond 64 bits (sqlite3 raised OverflowError: a 500) and a NUL character
    (PostgreSQL's text refuses it: a 500) are refused on every engine, naming the problem."""
    lab.enrol_and_assign()
    lab.start_session()
    step = lab.prompt("conation")
    too_big = lab.robot.post(
        "/api/v1/station/steps/99999999999999999999/answer",
        json={"answer": "yes", "idempotency_key": "k"},
    )
    assert too_big.status_code == 422 and "step_id" in too_big.json()["detail"], too_big.text
    nul_key = lab.robot.post(
        f"/api/v1/station/steps/{step['step_id']}/answer",
        json={"answer": "yes", "idempotency_key": "a\u0000"},
    )
    assert nul_key.status_code == 422 and "printable" in nul_key.json()["detail"], nul_key.text
    nul_station = lab.experimenter.post("/api/v1/stations/x%00/runs")
    assert 400 <= nul_station.status_code < 500, nul_station.text
    assert nul_station.json()["detail"]
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Answer)) == 0
    assert lab.answer(step["step_id"], "yes")["reply"]  # the step is still open and answerable
