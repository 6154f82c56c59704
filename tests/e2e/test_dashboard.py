"""An experimenter runs a session in Wizard-of-Oz mode in real Chromium and watches the console's
probability bars and the live dashboard change without reloading."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Browser, Page, expect

from app.db import Database
from app.tables import Role
from tests.conftest import PASSWORD, PRE_STUDY_ANSWERS, make_user
from tests.e2e.conftest import SECRET
from tests.servers import ServerProcess

del SECRET  # the server signs its own links; nothing here needs the secret


def _fill_tablet(server: ServerProcess, token: str) -> None:
    """The participant's consent and pre-study questionnaires (their part, not the test's)."""
    with httpx.Client(
        base_url=server.url, headers={"Authorization": f"Bearer {token}"}, timeout=30
    ) as tablet:
        assert tablet.post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
        for instrument, answers in PRE_STUDY_ANSWERS.items():
            tablet.post(f"/api/v1/tablet/questionnaires/{instrument}", json={"answers": answers})


def _meters(page: Page) -> list[str]:
    return page.locator('[role="meter"]').evaluate_all(
        "els => els.map(e => e.getAttribute('aria-valuenow'))"
    )


def _woz_step(page: Page) -> None:
    """Trigger the first pending category and answer yes, as the operator would."""
    page.locator("section.woz form button").first.click()
    expect(page.get_by_text("Robot asks")).to_be_visible()
    page.get_by_role("button", name="Participant said “yes”").click()
    expect(page.get_by_text("participant: yes")).to_be_visible()


@pytest.mark.e2e
def test_experimenter_runs_a_session_and_watches_it_live(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    exp3_study: str,
    artifacts: Path,
) -> None:
    make_user(database, "operator", Role.ADMIN)
    # A browser on the US west coast in 12-hour time: the page's times are UTC all the same.
    context = browser.new_context(
        viewport={"width": 1366, "height": 900}, locale="en-US", timezone_id="America/Los_Angeles"
    )
    page = context.new_page()
    page.goto(f"{live_server.url}/")
    expect(page).to_have_url(f"{live_server.url}/login?next=/")
    page.get_by_label("Username").fill("operator")
    page.get_by_label("Password").fill(PASSWORD)
    page.get_by_role("button", name="Sign in").click()
    page.get_by_role("link", name="Fast adaptation for trust modelling (Gao et al.)").click()
    page.screenshot(path=str(artifacts / "01-study.png"), full_page=True)
    for _ in range(2):
        page.get_by_role("button", name="Enrol and randomise").click()
        expect(page.get_by_role("status")).to_contain_text("allocated to")
    expect(page.locator("#participant-rows tbody tr")).to_have_count(2)
    page.screenshot(path=str(artifacts / "02-enrolled.png"), full_page=True)

    # Station, kiosk-free: issue P001's tablet link through the UI and let the tablet fill in.
    page.get_by_role("link", name="P001").click()
    page.get_by_role("button", name="Issue tablet link").click()
    link = page.locator("code.link").inner_text()
    page.screenshot(path=str(artifacts / "03-participant.png"), full_page=True)
    _fill_tablet(live_server, link.rsplit("/", 1)[1])

    page.goto(f"{live_server.url}/stations")
    page.get_by_label("New station").fill("lab-1")
    page.get_by_role("button", name="Create").click()
    page.get_by_role("link", name="Open console").click()
    page.get_by_role("textbox", name="Participant").fill("P001")
    page.get_by_role("button", name="Seat here").click()
    expect(page.get_by_text("P001", exact=True)).to_be_visible()

    dashboard = context.new_page()
    dashboard.goto(f"{live_server.url}/studies/{exp3_study}/dashboard")
    expect(dashboard.locator("#dashboard")).to_have_attribute("data-answers", "0")

    # The console's tab in front again, as the operator would have it: a click waits until its
    # button is stable over two drawn frames, and a tab behind another draws none (each click
    # waited about 2 s for that, 30 s of the test's 38).
    page.bring_to_front()
    page.get_by_role("button", name="Start the familiarisation run").click()
    for _ in range(3):
        _woz_step(page)
    page.get_by_role("button", name="Start session 1").click()
    before = _meters(page)
    page.screenshot(path=str(artifacts / "04-console-before.png"), full_page=True)
    for _ in range(3):
        _woz_step(page)
    after = _meters(page)
    assert before != after, "the probability bars did not move"
    page.screenshot(path=str(artifacts / "05-console-after.png"), full_page=True)
    # The dashboard in the other tab redraws by itself (server-sent events), no reload.
    dashboard.bring_to_front()
    # The page has no timer: only the server's event makes it fetch (the default wait bounds it).
    expect(dashboard.locator("#dashboard")).to_have_attribute("data-answers", "3")
    expect(dashboard.locator("#adaptation .main-svg").first).to_be_visible()
    expect(dashboard.locator("#dashboard-status")).to_have_text(
        re.compile(r"· updated \d{2}:\d{2}:\d{2} UTC$")
    )
    dashboard.screenshot(path=str(artifacts / "06-dashboard.png"), full_page=True)
    context.close()


@pytest.mark.e2e
@pytest.mark.parametrize("engine_name", ["postgresql"])
def test_a_dashboard_on_one_worker_updates_from_an_answer_posted_to_another(
    browser: Browser,
    database: Database,
    database_url: str,
    exp3_study: str,
    tmp_path: Path,
    artifacts: Path,
    engine_name: str,
) -> None:
    make_user(database, "operator", Role.ADMIN)
    first = ServerProcess(database_url, tmp_path / "a")
    second = ServerProcess(database_url, tmp_path / "b")
    first.start()
    second.start()
    try:
        with httpx.Client(base_url=second.url, timeout=30) as api:
            signed = api.post(
                "/api/v1/session", json={"username": "operator", "password": PASSWORD}
            )
            api.headers["X-CSRF-Token"] = signed.json()["csrf_token"]
            code = api.post(f"/api/v1/studies/{exp3_study}/participants", json={}).json()["code"]
            token = api.post(f"/api/v1/studies/{exp3_study}/participants/{code}/link").json()[
                "token"
            ]
            _fill_tablet(second, token)
            api.post("/api/v1/stations", json={"name": "lab-9"})
            api.put("/api/v1/stations/lab-9/participant", json={"study": exp3_study, "code": code})
            api.post("/api/v1/stations/lab-9/sessions")  # familiarisation
            context = browser.new_context()
            page = context.new_page()
            page.goto(f"{first.url}/login")
            page.get_by_label("Username").fill("operator")
            page.get_by_label("Password").fill(PASSWORD)
            page.get_by_role("button", name="Sign in").click()
            page.goto(f"{first.url}/studies/{exp3_study}/dashboard")
            expect(page.locator("#dashboard")).to_have_attribute("data-answers", "0")
            expected = api.get("/api/v1/stations/lab-9/state").json()["expected"]
            while expected["action"] in ("prompt", "start_session"):
                if expected["action"] == "start_session":
                    expected = api.post("/api/v1/stations/lab-9/sessions").json()["expected"]
                    if expected["session"] == 1 and expected["action"] == "prompt":
                        break
                    continue
                step = api.post(
                    "/api/v1/stations/lab-9/prompts", json={"category": expected["categories"][0]}
                ).json()
                expected = api.post(
                    f"/api/v1/stations/lab-9/steps/{step['step_id']}/answer",
                    json={"answer": "yes", "idempotency_key": f"k{step['step_id']}"},
                ).json()["expected"]
            step = api.post("/api/v1/stations/lab-9/prompts", json={"category": "conation"}).json()
            api.post(
                f"/api/v1/stations/lab-9/steps/{step['step_id']}/answer",
                json={"answer": "yes", "idempotency_key": "adapting-1"},
            )
            # Posted to the second server; the first server's page learns of it via NOTIFY.
            expect(page.locator("#dashboard")).to_have_attribute("data-answers", "1")
            page.screenshot(path=str(artifacts / "dashboard-other-worker.png"), full_page=True)
            context.close()
    finally:
        first.stop()
        second.stop()
