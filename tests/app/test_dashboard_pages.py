"""The experimenter's pages: roles on every page, the console's Wizard-of-Oz path, the live
dashboard's data (and blinding), the overview's warnings and the participant record."""

from __future__ import annotations

import re
from datetime import timedelta

from fastapi.testclient import TestClient
from sqlalchemy import select, update

from app.db import Database
from app.tables import Allocation, Device, Participant, Prompt, Response, Role, StudySession, utcnow
from tests.conftest import (
    CSRF_INPUT,
    TRUST_ANSWERS,
    Lab,
    UserClientFactory,
    create_blinded_study,
    postgres_for_some,
)

PAGES = [
    # (path, roles that may open it)
    ("/", {"analyst", "experimenter", "admin"}),
    ("/studies/rt", {"analyst", "experimenter", "admin"}),
    ("/studies/rt/dashboard", {"analyst", "experimenter", "admin"}),
    ("/studies/rt/dashboard.json", {"analyst", "experimenter", "admin"}),
    ("/studies/rt/participants/{code}", {"analyst", "experimenter", "admin"}),
    ("/stations", {"experimenter", "admin"}),
    ("/stations/lab-1", {"experimenter", "admin"}),
    ("/admin/users", {"admin"}),
    ("/admin/studies/new", {"admin"}),
]


@postgres_for_some(
    "role",
    ["anonymous", "analyst", "experimenter", "admin"],
    ids=["anonymous", "analyst", "experimenter", "admin"],
    postgres={"admin"},  # renders every page; who may see what is decided before any query
)
def test_who_may_open_each_page(
    lab: Lab, app: object, user_client: UserClientFactory, role: str
) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    client = TestClient(app) if role == "anonymous" else user_client(Role(role))  # type: ignore[arg-type]
    for path, allowed in PAGES:
        response = client.get(path.format(code=code), follow_redirects=False)
        if role in allowed:
            assert response.status_code == 200, (role, path, response.status_code)
        elif role == "anonymous":
            assert response.status_code == 303, (role, path)
            assert response.headers["location"].startswith("/login")
        else:
            assert response.status_code == 403, (role, path, response.status_code)


def _form_value(page: str, name: str) -> str:
    match = re.search(rf'name="{name}" value="([^"]+)"', page)
    assert match, f"no {name} on the page"
    return match.group(1)


def test_wizard_of_oz_goes_through_the_robot_path(lab: Lab) -> None:
    lab.enrol_and_assign()
    console = lab.experimenter.get("/stations/lab-1")
    assert "Start the familiarisation run" in console.text
    started = lab.experimenter.post("/stations/lab-1/session/start")
    assert "Trigger a category" in started.text
    prompted = lab.experimenter.post("/stations/lab-1/woz/prompt", data={"category": "cognition"})
    assert "Robot asks (cognition)" in prompted.text
    step_id = _form_value(prompted.text, "step_id")
    key = _form_value(prompted.text, "idempotency_key")
    answered = lab.experimenter.post(
        "/stations/lab-1/woz/answer",
        data={"step_id": step_id, "answer": "yes", "idempotency_key": key},
    )
    assert "participant: <strong>yes</strong>" in answered.text
    again = lab.experimenter.post(
        "/stations/lab-1/woz/answer",
        data={"step_id": step_id, "answer": "no", "idempotency_key": key},
    )
    assert again.status_code == 409
    assert "was used for the answer &#39;yes&#39;" in again.text  # shown beside the buttons
    with lab.database.read_session() as db:
        prompt = db.scalars(select(Prompt)).one()
    assert prompt.actor.startswith("experimenter")  # the step log says who did it
    state = lab.robot.get("/api/v1/station").json()
    assert state["run"]["answered"] == ["cognition"]  # the robot sees the same run
    bogus = lab.experimenter.post(
        "/stations/lab-1/woz/answer",
        data={"step_id": step_id, "answer": "maybe", "idempotency_key": "x"},
    )
    assert bogus.status_code == 422


def test_console_bars_follow_the_learner(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    before = lab.experimenter.get("/stations/lab-1").text
    assert before.count('role="meter"') == 12  # 3 categories × 4 questions
    assert "(0 answers learned)" in before
    lab.run_session(preferred=0)
    after = lab.experimenter.get("/stations/lab-1").text
    assert "(3 answers learned)" in after
    assert "(1 answer learned)" not in before
    assert before != after


def test_dashboard_data_aggregates_and_blinds(
    lab: Lab, app: object, user_client: UserClientFactory
) -> None:
    empty = lab.experimenter.get("/studies/rt/dashboard.json").json()
    assert (empty["answers"], empty["questionnaires"]) == (0, 0)
    code = lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    lab.run_session(preferred=0)
    lab.fill_pending_questionnaires()
    data = lab.experimenter.get("/studies/rt/dashboard.json").json()
    assert data["answers"] == 9  # adapting answers only: session 1's three runs
    assert data["questionnaires"] == 5  # the five trust items after session 1
    assert [m["item"] for m in data["measures"]] == [f"trust_{n}" for n in range(1, 6)]
    trust_1 = data["measures"][0]["payload"]
    assert {trace["name"] for trace in trust_1["data"]} == {
        lab.experimenter.get("/api/v1/studies/rt/participants").json()[0]["condition"]
    }
    answered = int(TRUST_ANSWERS["trust_1"])
    assert trust_1["data"][0]["y"] == [answered]
    reverse = data["measures"][4]["payload"]["data"][0]["y"]
    assert reverse == [6 - int(TRUST_ANSWERS["trust_5"])]  # reverse-scored on a 1-5 scale
    adaptation = data["adaptation"]["data"]
    assert {trace["name"] for trace in adaptation if trace.get("showlegend", True)}
    assert code


def test_blinded_dashboard_shows_neutral_labels_to_experimenters(
    database: Database, user_client: UserClientFactory
) -> None:
    create_blinded_study(database, "blind")
    experimenter = user_client(Role.EXPERIMENTER)
    analyst = user_client(Role.ANALYST)
    for _ in range(2):
        experimenter.post("/api/v1/studies/blind/participants", json={})
    exp_groups = {c["label"] for c in experimenter.get("/api/v1/studies/blind").json()["enrolment"]}
    assert exp_groups == {"Group A", "Group B"}
    # the CSRF tokens are random text, in which "C1" turns up now and then
    page = CSRF_INPUT.sub("", experimenter.get("/studies/blind").text)
    assert "Group A" in page and "C1" not in page.split("Participants")[1]
    analyst_page = analyst.get("/studies/blind").text
    assert "C1" in analyst_page or "C2" in analyst_page


def test_overview_warns_about_stalled_sessions_and_missing_questionnaires(lab: Lab) -> None:
    code = lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    lab.run_session()
    with lab.database.writing() as db:
        db.execute(update(StudySession).values(ended_at=utcnow() - timedelta(hours=1)))
        db.commit()
    page = lab.experimenter.get("/studies/rt").text
    assert f"{code}: the questionnaire after session 1 is still missing" in page
    lab.fill_pending_questionnaires()
    lab.start_session()
    with lab.database.writing() as db:
        db.execute(
            update(StudySession)
            .where(StudySession.ended_at.is_(None))
            .values(started_at=utcnow() - timedelta(hours=1))
        )
        db.commit()
    # the stall is measured from the last activity: answers and questionnaires are recent
    assert "has had no answer" not in lab.experimenter.get("/studies/rt").text


def test_the_group_cards_list_the_conditions_in_protocol_order(lab: Lab) -> None:
    """C1 before C2 even when the first participant was allocated to C2 (the cards followed the
    order in which each group's first participant enrolled)."""
    code = lab.enrol_and_assign()
    with lab.database.writing() as db:
        participant = db.scalars(select(Participant).where(Participant.code == code)).one()
        db.execute(
            update(Allocation)
            .where(Allocation.participant_id == participant.id)
            .values(condition="C2")
        )
        db.commit()
    page = lab.experimenter.get("/studies/rt").text
    cards = page.split('id="enrolment-cards"')[1].split("</div>\n</div>")[0]
    labels = re.findall(r'<div class="stat-label">([^<]+)</div>', cards)
    assert labels == ["C1", "C2"]


def test_overview_names_the_familiarisation_run_not_session_0(lab: Lab) -> None:
    code = lab.enrol_and_assign()
    lab.start_session()  # the familiarisation run: session number 0
    long_ago = utcnow() - timedelta(hours=1)
    with lab.database.writing() as db:
        db.execute(update(StudySession).values(started_at=long_ago))
        db.execute(update(Response).values(answered_at=long_ago))
        db.execute(update(Participant).values(enrolled_at=long_ago))
        db.execute(update(Device).values(connected_at=None, last_seen_at=long_ago))
        db.commit()
    page = lab.experimenter.get("/studies/rt").text
    assert f"{code}: the familiarisation run has had no answer for 60 minutes" in page
    assert "station lab-1: no device has been heard from during the familiarisation run" in page
    assert "familiarisation running" in page
    assert "session 0" not in page


def test_overview_warns_about_a_station_without_devices(
    lab: Lab, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    admin.post("/api/v1/stations", json={"name": "lab-2"})
    code = lab.experimenter.post("/api/v1/studies/rt/participants", json={}).json()["code"]
    lab.experimenter.put("/api/v1/stations/lab-2/participant", json={"study": "rt", "code": code})
    page = lab.experimenter.get("/studies/rt").text
    assert f"station lab-2 has {code} but no device key" in page


def test_participant_record_shows_steps_questionnaires_and_the_qr(lab: Lab) -> None:
    code = lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    page = lab.experimenter.get(f"/studies/rt/participants/{code}").text
    assert "<svg" in page and "/t/tlp_" in page  # the tablet link with its QR code
    assert "Familiarisation run" in page
    assert page.count("<td>conation</td>") == 1
    assert "Ten-Item Personality Inventory" in page
