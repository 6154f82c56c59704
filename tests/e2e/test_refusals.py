"""Refused htmx requests in real Chromium (issue 21, defect 1): the server's message appears
next to the control, in the server's words, and a region that reloads itself shows the state the
refusal is about. Also: staff pages are not stored, so Back after signing out shows sign-in."""

from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import Browser, expect

from app.db import Database
from app.tables import Role
from tests.conftest import Lab, make_user
from tests.e2e.conftest import sign_in_page
from tests.servers import ServerProcess

SIZES = ((1366, 900), (768, 1024))


@pytest.mark.e2e
@pytest.mark.parametrize(("width", "height"), SIZES)
def test_refusals_are_shown_next_to_their_control(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    lab: Lab,
    artifacts: Path,
    width: int,
    height: int,
) -> None:
    make_user(database, "operator", Role.ADMIN)
    taken = lab.enrol_and_assign("P777")
    context = browser.new_context(viewport={"width": width, "height": height})
    page = context.new_page()
    sign_in_page(page, live_server, f"/studies/{lab.study}")

    # Enrolling a code that is taken (409): the message beside the form, the page unchanged.
    form = page.locator(f'form[action="/studies/{lab.study}/participants"]')
    form.get_by_label("Code").fill(taken)
    form.get_by_role("button", name="Enrol and randomise").click()
    refusal = page.locator("form + p.refusal")
    expect(refusal).to_have_text(f"participant code '{taken}' is already used in study 'rt'")
    expect(page.locator("#participant-rows tbody tr")).to_have_count(1)
    page.screenshot(path=str(artifacts / f"enrol-taken-{width}.png"), full_page=True)
    # The next request clears it.
    form.get_by_label("Code").fill("P778")
    form.get_by_role("button", name="Enrol and randomise").click()
    expect(page.get_by_role("status")).to_contain_text("allocated to")
    expect(page.locator("p.refusal")).to_have_count(0)
    # A refusal next: the earlier success goes, so it cannot read as this one's outcome (issue 35).
    form.get_by_label("Code").fill("P778")
    form.get_by_role("button", name="Enrol and randomise").click()
    expect(refusal).to_contain_text("'P778' is already used")
    expect(page.locator("p.notice")).to_have_count(0)
    # Issue 21, defect 5: the enrolment cards count the new participant without a reload.
    counts = page.locator("#enrolment-cards .stat-value").all_inner_texts()
    assert sum(int(n) for n in counts) == 2, counts

    # A console whose live updates are cut, so its buttons go out of date.
    page.route("**/stations/lab-1/events", lambda route: route.abort())
    page.goto(f"{live_server.url}/stations/lab-1")
    start = page.get_by_role("button", name="Start the familiarisation run")
    expect(start).to_be_visible()
    lab.start_session()  # someone else starts it meanwhile
    start.click()
    refusal = page.locator("#console p.refusal")
    expect(refusal).to_contain_text("already")
    # The console reloaded: it shows the running session, and the stale button is gone.
    expect(page.get_by_role("button", name="Start the familiarisation run")).to_have_count(0)
    expect(page.locator("#console")).to_contain_text("running")
    page.screenshot(path=str(artifacts / f"console-stale-{width}.png"), full_page=True)
    context.close()


@pytest.mark.e2e
def test_an_unknown_code_and_a_dead_server_are_explained(
    browser: Browser, live_server: ServerProcess, database: Database, lab: Lab, artifacts: Path
) -> None:
    make_user(database, "operator", Role.ADMIN)
    context = browser.new_context(viewport={"width": 1366, "height": 900})
    page = context.new_page()
    sign_in_page(page, live_server, "/stations/lab-1")
    seat = page.locator('form[action="/stations/lab-1/assign"]')
    seat.get_by_label("Participant").fill("NOPE1")
    seat.get_by_role("button", name="Seat here").click()
    expect(page.locator("#console p.refusal")).to_have_text("study 'rt' has no participant 'NOPE1'")
    page.route("**/stations/lab-1/assign", lambda route: route.abort())
    seat.get_by_role("button", name="Seat here").click()
    expect(page.locator("#console p.refusal")).to_contain_text("could not be reached")
    page.screenshot(path=str(artifacts / "console-unreachable.png"), full_page=True)
    # A server fault may come after the change was stored (issue 35, item 1): no "nothing changed".
    page.unroute("**/stations/lab-1/assign")
    page.route("**/stations/lab-1/assign", lambda route: route.fulfill(status=500, body="fault"))
    seat.get_by_role("button", name="Seat here").click()
    expect(page.locator("#console p.refusal")).to_have_text(
        "The server failed (HTTP 500); reload the page to see whether the change was made."
    )
    context.close()


@pytest.mark.e2e
def test_back_after_signing_out_shows_the_sign_in_page(
    browser: Browser, live_server: ServerProcess, database: Database, exp3_study: str
) -> None:
    make_user(database, "operator", Role.ADMIN)
    context = browser.new_context(viewport={"width": 1366, "height": 900})
    page = context.new_page()
    sign_in_page(page, live_server, f"/studies/{exp3_study}")
    response = page.request.get(f"{live_server.url}/studies/{exp3_study}")
    assert response.headers["cache-control"] == "no-store"
    page.get_by_role("button", name="Sign out").click()
    expect(page).to_have_url(f"{live_server.url}/login")
    page.go_back()
    expect(page).to_have_url(f"{live_server.url}/login?next=/studies/{exp3_study}")
    expect(page.get_by_text("operator")).to_have_count(0)
    context.close()
