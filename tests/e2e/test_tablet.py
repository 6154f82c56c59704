"""A participant completes every instrument on a tablet in real Chromium, at both orientations."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Browser, Page, expect

from app.db import Database
from app.services import studies
from app.services.audit import Actor
from app.services.participants import enrolment, tablet_tokens
from app.services.sessions import stations
from app.tables import Role
from tests.conftest import PASSWORD, make_user
from tests.e2e.conftest import SECRET
from tests.servers import ServerProcess

SYSTEM = Actor.system("e2e")


def _participant_with_link(database: Database, study: str, code: str) -> str:
    with database.writing() as db:
        result = enrolment.enroll_participant(db, study_name=study, actor=SYSTEM, code=code)
    with database.writing() as db:
        return tablet_tokens.issue_participant_token(
            db, participant=db.merge(result.participant), secret=SECRET, actor=SYSTEM
        )


class _Lab:
    """The robot and the experimenter, driving sessions through the server's API."""

    def __init__(self, server: ServerProcess, database: Database, station: str) -> None:
        make_user(database, "e2e-admin", Role.ADMIN)
        with database.writing() as db:
            key = stations.issue_device_key(
                db, station_name=station, label="robot", actor=SYSTEM
            ).key
        self.station = station
        # Not httpx's 5 s default: an answer's learner update on a loaded machine may take longer.
        self.robot = httpx.Client(
            base_url=server.url, headers={"Authorization": f"Bearer {key}"}, timeout=30
        )
        self.experimenter = httpx.Client(base_url=server.url, timeout=30)
        signed_in = self.experimenter.post(
            "/api/v1/session", json={"username": "e2e-admin", "password": PASSWORD}
        )
        self.experimenter.headers["X-CSRF-Token"] = signed_in.json()["csrf_token"]

    def run_session(self) -> None:
        started = self.experimenter.post(f"/api/v1/stations/{self.station}/sessions")
        assert started.status_code == 201, started.text
        expected = started.json()["expected"]
        while expected["action"] == "prompt":
            step = self.robot.post(
                "/api/v1/station/prompts", json={"category": expected["categories"][0]}
            ).json()
            reply = self.robot.post(
                f"/api/v1/station/steps/{step['step_id']}/answer",
                json={"answer": "yes", "idempotency_key": f"k{step['step_id']}"},
            )
            expected = reply.json()["expected"]


def _check_layout(page: Page, shot: Path) -> None:
    """No sideways scrolling, touch targets of at least 44 px, and a screenshot."""
    page.screenshot(path=str(shot), full_page=True)
    overflow = page.evaluate("document.documentElement.scrollWidth - window.innerWidth")
    assert overflow <= 0, f"{shot.name}: {overflow}px of horizontal scrolling"
    for target in page.locator("button, .point, .option, .check").all():
        box = target.bounding_box()
        assert box is not None and box["height"] >= 44, f"{shot.name}: a target under 44px"


def _answer_likert(page: Page, name: str, value: int) -> None:
    page.locator(f'input[name="{name}"][value="{value}"]').check()


@pytest.mark.e2e
@pytest.mark.parametrize("viewport", [(768, 1024), (1024, 768)], ids=["portrait", "landscape"])
def test_a_participant_completes_every_instrument(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    exp3_study: str,
    artifacts: Path,
    viewport: tuple[int, int],
) -> None:
    token = _participant_with_link(database, exp3_study, "T1")
    other_token = _participant_with_link(database, exp3_study, "T2")
    with database.writing() as db:
        stations.create_station(db, name="tablet-test", actor=SYSTEM)
    with database.writing() as db:
        participant = enrolment.get_participant(
            db, studies.get_study(db, exp3_study), "T1", actor=Actor.system()
        )
        stations.assign_participant(
            db, station_name="tablet-test", participant=participant, actor=SYSTEM
        )
    width, height = viewport
    context = browser.new_context(viewport={"width": width, "height": height}, has_touch=True)
    page = context.new_page()
    page.goto(f"{live_server.url}/t/{token}")
    expect(page).to_have_url(f"{live_server.url}/tablet/consent")
    _check_layout(page, artifacts / "01-consent.png")
    expect(page.locator(".tablet-progress")).to_contain_text("Page 1 of 5")
    page.get_by_role("button", name="Continue").click()
    expect(page.get_by_role("alert").first).to_contain_text("Please tick the box to take part.")
    page.get_by_label("I have read the text above and I agree to take part.").check()
    page.get_by_role("button", name="Continue").click()

    # Demographics: skip a required item, then reload mid-form: what was typed survives.
    expect(page).to_have_url(f"{live_server.url}/tablet/q/demographics")
    page.get_by_label("1. How old are you (in years)?").fill("31")
    page.get_by_role("button", name="Continue").click()
    expect(page.locator("#err-gender")).to_have_text("Please answer this question.")
    expect(page.locator('input[name="gender"]').first).to_be_focused()  # the first one missing
    expect(page.locator(".tablet-progress")).to_contain_text("Page 2 of 5")
    _check_layout(page, artifacts / "02-demographics-error.png")
    page.get_by_label("Prefer not to say").check()
    page.reload()
    expect(page.get_by_label("Prefer not to say")).to_be_checked()
    expect(page.get_by_label("1. How old are you (in years)?")).to_have_value("31")
    page.get_by_role("button", name="Continue").click()

    expect(page).to_have_url(f"{live_server.url}/tablet/q/background")
    _check_layout(page, artifacts / "03-background.png")
    for name in ("bg_robot_experience", "bg_vr_familiarity", "bg_digital_skills"):
        _answer_likert(page, name, 3)
    page.get_by_role("button", name="Continue").click()

    expect(page).to_have_url(f"{live_server.url}/tablet/q/tipi")
    _check_layout(page, artifacts / "04-tipi.png")
    fieldset = page.get_by_role("group", name="1. Extraverted, enthusiastic.")
    fieldset.get_by_role("radio", name="6 Agree moderately").check()  # labels read correctly
    for n in range(2, 11):
        _answer_likert(page, f"tipi_{n}", 4)
    page.get_by_role("button", name="Continue").click()

    expect(page).to_have_url(f"{live_server.url}/tablet/q/nars")
    _check_layout(page, artifacts / "05-nars.png")
    for n in range(1, 15):
        _answer_likert(page, f"nars_{n}", 2)
    page.keyboard.press("Tab")  # keyboard users can reach the form
    page.get_by_role("button", name="Continue").click()

    expect(page).to_have_url(f"{live_server.url}/tablet/wait")
    _check_layout(page, artifacts / "06-wait.png")
    lab = _Lab(live_server, database, "tablet-test")
    lab.run_session()  # familiarisation
    for session in (1, 2, 3, 4):
        lab.run_session()
        # The wait page moves on by itself (server-sent event) to the session questionnaire.
        expect(page).to_have_url(f"{live_server.url}/tablet/q/trust/{session}")
        if session == 1:
            _check_layout(page, artifacts / "07-trust.png")
        for n in range(1, 6):
            _answer_likert(page, f"trust_{n}", 4)
        page.get_by_role("button", name="Continue").click()
        if session < 4:
            expect(page).to_have_url(f"{live_server.url}/tablet/wait")

    expect(page).to_have_url(f"{live_server.url}/tablet/q/overall")
    _check_layout(page, artifacts / "08-overall.png")
    _answer_likert(page, "overall_experience", 5)
    _answer_likert(page, "interaction_quality", 4)
    page.get_by_label("3. Is there anything else you would like to tell us? (optional)").fill(
        "The robot was friendly."
    )
    page.get_by_role("button", name="Continue").click()
    expect(page).to_have_url(f"{live_server.url}/tablet/done")
    _check_layout(page, artifacts / "09-done.png")
    colours = page.evaluate(
        """() => [document.documentElement, document.body].map(
             (el) => getComputedStyle(el).backgroundColor)"""
    )
    assert colours[0] == colours[1], f"the page's background shows below the tablet's: {colours}"

    # Another participant's link on the same tablet shows that participant's own first page,
    # and nothing of T1's.
    page.goto(f"{live_server.url}/t/{other_token}")
    expect(page).to_have_url(f"{live_server.url}/tablet/consent")
    page.goto(f"{live_server.url}/tablet/q/overall")
    expect(page).to_have_url(f"{live_server.url}/tablet/consent")
    page.goto(f"{live_server.url}/t/tlp_not-a-real-token")
    expect(page.get_by_role("alert")).to_contain_text("This tablet link is not valid")
    expect(page.get_by_text("Please hand the tablet to the experimenter.")).to_be_visible()
    expect(page.locator(".topbar, a[href^='/login']")).to_have_count(0)  # no way into staff pages
    _check_layout(page, artifacts / "10-invalid-link.png")
    context.close()
