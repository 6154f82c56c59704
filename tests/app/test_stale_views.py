"""Views that must not lag behind the state (issue 21, defect 5)."""

from __future__ import annotations

from app.db import Database
from app.services import studies
from app.services.audit import Actor
from app.tables import Role, StudyStatus
from tests.conftest import Lab, UserClientFactory


def test_a_closed_empty_study_does_not_invite_enrolment(
    database: Database, exp3_study: str, user_client: UserClientFactory
) -> None:
    with database.writing() as db:
        studies.set_study_status(
            db, name=exp3_study, status=StudyStatus.CLOSED, actor=Actor.system()
        )
    admin = user_client(Role.ADMIN).get(f"/studies/{exp3_study}").text
    assert "Enrolment is closed: reopen it above to enrol the first participant." in admin
    assert "Enrol the first participant with the form above" not in admin
    analyst = user_client(Role.ANALYST).get(f"/studies/{exp3_study}").text
    assert "Nobody is enrolled yet. Enrolment is closed." in analyst


def test_the_console_does_not_wait_for_an_answer_after_the_session_ended(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.prompt("conation")
    assert "waiting for the answer" in lab.experimenter.get("/stations/lab-1").text
    ended = lab.experimenter.post("/stations/lab-1/session/end")
    assert ended.status_code == 200, ended.text
    page = lab.experimenter.get("/stations/lab-1").text
    assert "waiting for the answer" not in page
    assert "not answered: its run ended first" in page


def test_an_htmx_enrolment_updates_the_counts_beside_it(lab: Lab) -> None:
    response = lab.experimenter.post(
        f"/studies/{lab.study}/participants", data={"code": "P900"}, headers={"HX-Request": "true"}
    )
    assert response.status_code == 200
    assert 'id="enrolment-cards" hx-swap-oob="true"' in response.text
    plain = lab.experimenter.post(f"/studies/{lab.study}/participants", data={"code": "P901"})
    assert plain.text.count('id="enrolment-cards"') == 1  # JavaScript off: the page, once
