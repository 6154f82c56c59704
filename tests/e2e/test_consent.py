"""A new version of the consent text, through a real tablet in Chromium: the participant
accepted version 1, an admin adds version 2 on the study page, the next session waits until the
tablet has shown it and the participant accepted it."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Browser, expect
from sqlalchemy import select

from app.db import Database
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.participants import enrolment
from app.services.sessions import stations
from app.tables import ConsentRecord
from tests.conftest import EXP3_ONLY, PRE_STUDY_ANSWERS, protocol_text
from tests.e2e.conftest import sign_in_page
from tests.e2e.test_tablet import SYSTEM, _Lab, _participant_with_link
from tests.servers import ServerProcess

RECONSENT = {
    '[questionnaires.consent]\nversion = "1.0"': (
        '[questionnaires.consent]\nreconsent_before_next_session = true\nversion = "1.0"'
    )
}
NEW_TEXT = "Version two: we now also keep your answers for ten years."


@pytest.mark.e2e
def test_a_participant_accepts_a_new_consent_text_before_the_next_session(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    with database.writing() as db:
        loaded = parse_protocol(protocol_text(**EXP3_ONLY, **RECONSENT))
        studies.create_study(db, name="amended", loaded=loaded, actor=SYSTEM)
    token = _participant_with_link(database, "amended", "C1")
    with database.writing() as db:
        stations.create_station(db, name="consent-test", actor=SYSTEM)
    with database.writing() as db:
        participant = enrolment.get_participant(
            db, studies.get_study(db, "amended"), "C1", actor=Actor.system()
        )
        stations.assign_participant(
            db, station_name="consent-test", participant=participant, actor=SYSTEM
        )
    lab = _Lab(live_server, database, "consent-test")  # signs in as e2e-admin

    tablet = browser.new_context(viewport={"width": 768, "height": 1024}, has_touch=True)
    page = tablet.new_page()
    page.goto(f"{live_server.url}/t/{token}")
    expect(page).to_have_url(f"{live_server.url}/tablet/consent")
    expect(page.locator(".consent-text")).to_contain_text("You are invited to take part")
    page.get_by_label("I have read the text above and I agree to take part.").check()
    page.get_by_role("button", name="Continue").click()
    expect(page).to_have_url(f"{live_server.url}/tablet/q/demographics")
    # The pre-study questionnaires (tested page by page in test_tablet.py) through the JSON
    # tablet, with the same link.
    api = httpx.Client(
        base_url=live_server.url, headers={"Authorization": f"Bearer {token}"}, timeout=30
    )
    for instrument, answers in PRE_STUDY_ANSWERS.items():
        assert api.post(f"/api/v1/tablet/questionnaires/{instrument}", json={"answers": answers})
    page.goto(f"{live_server.url}/tablet")
    expect(page).to_have_url(f"{live_server.url}/tablet/wait")
    lab.run_session()  # the familiarisation run

    staff = browser.new_context()
    admin = staff.new_page()
    sign_in_page(admin, live_server, "/studies/amended", username="e2e-admin")
    admin.locator("#consent summary").click()
    admin.get_by_role("textbox", name="Text", exact=True).fill(NEW_TEXT)
    admin.get_by_label("Reason (kept in the audit log)").fill("amendment approved")
    admin.get_by_label("I confirm this is the approved text").check()
    admin.get_by_role("button", name="Add version 2").click()
    expect(admin.get_by_role("status").first).to_contain_text(
        "Added version 2 (2) of the consent text."
    )
    admin.screenshot(path=str(artifacts / "01-study-consent-versions.png"), full_page=True)

    refused = lab.experimenter.post("/api/v1/stations/consent-test/sessions")
    assert refused.status_code == 409
    assert refused.json()["detail"] == (
        "cannot start a session for C1: waiting for C1 to accept version 2 of the consent text "
        "on the tablet (they accepted version 1)"
    )
    admin.goto(f"{live_server.url}/studies/amended")
    expect(admin.locator("#participant-rows")).to_contain_text(
        "re-consent needed (accepted version 1 of 2)"
    )

    # The waiting tablet moves on to the new text by itself.
    expect(page).to_have_url(f"{live_server.url}/tablet/consent")
    expect(page.get_by_role("status").first).to_contain_text("The text below has changed")
    expect(page.locator(".consent-text")).to_have_text(NEW_TEXT)
    page.screenshot(path=str(artifacts / "02-tablet-new-consent.png"), full_page=True)
    page.get_by_label("I have read the text above and I agree to take part.").check()
    page.get_by_role("button", name="Continue").click()
    expect(page).to_have_url(f"{live_server.url}/tablet/wait")

    started = lab.experimenter.post("/api/v1/stations/consent-test/sessions")
    assert started.status_code == 201, started.text
    with database.read_session() as db:
        held = db.execute(
            select(ConsentRecord.version, ConsentRecord.accepted).order_by(ConsentRecord.id)
        ).all()
    assert [tuple(row) for row in held] == [(1, True), (2, True)]
    tablet.close()
    staff.close()
