"""The protocol designer, the room's preview and the study's phases in Chromium (issue 50,
items 2, 3 and 4), at a laptop's and a tablet's width, by keyboard where a person would: a
mistake is said beside its field as it is typed and put right; a section is saved as a version;
translations stand beside the first language; a second editor's stale save is refused with what
changed; the room is walked in preview; a draft is piloted with a marked pilot participant and
taken live."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from playwright.sync_api import Browser, Page, expect

from app.db import Database
from app.protocol import shipped_protocol
from app.services import studies
from app.services.audit import Actor
from app.tables import Role, StudyPhase
from tests.app.test_preview import _rows
from tests.conftest import make_user
from tests.e2e import room_driver as drive
from tests.e2e.conftest import sign_in_page
from tests.e2e.test_refusals import SIZES
from tests.e2e.test_staff_pages import _overflow
from tests.servers import ServerProcess

NAME = "designed"
WHO = "designer"


def _at_each_size(
    page: Page, artifacts: Path, name: str, *, fits: str = "", full_page: bool = False
) -> None:
    """Look at the page as it is at a laptop's and at a tablet's width (``fits``: elements that
    must stay inside their card at each), one screenshot each, then back to the first width:
    one walk through a flow serves both sizes."""
    for width, height in SIZES:
        page.set_viewport_size({"width": width, "height": height})
        if fits:
            assert _overflow(page, fits) == [], (name, width)
        page.screenshot(path=str(artifacts / f"{name}-{width}.png"), full_page=full_page)
    width, height = SIZES[0]
    page.set_viewport_size({"width": width, "height": height})


def _draft(database: Database) -> None:
    with database.writing() as db:
        studies.create_study(
            db,
            name=NAME,
            loaded=shipped_protocol("fast_adaptation_trust_sv.toml"),
            actor=Actor.system("test"),
            phase=StudyPhase.DRAFT,
        )


@pytest.mark.e2e
def test_a_draft_is_designed_section_by_section(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    make_user(database, WHO, Role.ADMIN)
    _draft(database)
    width, height = SIZES[0]
    page = browser.new_context(viewport={"width": width, "height": height}).new_page()
    sign_in_page(page, live_server, f"/studies/{NAME}", username=WHO)
    expect(page.locator("#study-phase")).to_contain_text("Nobody can enrol")
    fits = ".heading .actions .button, #study-phase .button"
    _at_each_size(page, artifacts, "draft-study", fits=fits, full_page=True)
    page.get_by_role("link", name="Design the protocol").click()
    expect(page.get_by_role("heading", name="Study and consent")).to_be_visible()
    sessions = page.get_by_label("sessions", exact=True)
    sessions.fill("0")  # no form is sent: the check runs as it is typed
    beside = page.locator("#problems-f-schedule_sessions")
    expect(beside).to_contain_text("greater than or equal to 1")
    expect(page.locator("#section-problems")).to_contain_text("1 problem")
    _at_each_size(page, artifacts, "designer-problem", fits=".design-form input")
    sessions.fill("3")
    expect(page.locator("#section-problems")).to_contain_text("No problems")
    expect(beside).to_be_empty()
    page.get_by_label("What changed, and why").fill("three sessions fit one afternoon")
    page.get_by_label("What changed, and why").press("Enter")
    expect(page.get_by_text("Saved as version 2.")).to_be_visible()
    expect(page.get_by_label("sessions", exact=True)).to_have_value("3")
    _at_each_size(
        page, artifacts, "designer-saved", fits=".design-form input, .design-form textarea"
    )

    page.get_by_role("link", name="Languages and translations").click()
    expect(page.get_by_text("Vill du ta dig ut ur rummet?")).to_be_visible()
    _at_each_size(page, artifacts, "designer-translations", fits=".translation")

    page.get_by_role("link", name="Conditions and learners").click()
    page.get_by_role("button", name="Add to conditions").click()
    new = page.locator("details.design-entry[open]").filter(has_text="new")
    expect(new).to_be_visible()
    new.get_by_label("id", exact=True).fill("C3")
    new.get_by_label("label", exact=True).fill("Exact filter")
    new.get_by_label("learner").select_option("bayes")
    expect(page.locator("#section-problems")).to_contain_text("allocation.block_sizes")
    _at_each_size(page, artifacts, "designer-conditions", fits=".design-entry")
    page.context.close()


@pytest.mark.e2e
def test_the_second_editor_sees_what_changed_and_keeps_their_text(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    make_user(database, "ada", Role.ADMIN)
    make_user(database, "bo", Role.ADMIN)
    _draft(database)
    pages: list[Page] = []
    for who in ("ada", "bo"):
        page = browser.new_context(viewport={"width": 1366, "height": 900}).new_page()
        sign_in_page(page, live_server, f"/admin/studies/{NAME}/design/speech", username=who)
        pages.append(page)
    ada, bo = pages
    ada.get_by_label("reprompt", exact=True).fill("Sorry? Yes or no, please.")
    ada.get_by_role("button", name="Save speech").click()
    expect(ada.get_by_text("Saved as version 2.")).to_be_visible()
    bo.get_by_label("attempts", exact=True).fill("2")
    bo.get_by_role("button", name="Save speech").click()
    expect(bo.locator("#section-error")).to_contain_text("changed while you edited it")
    expect(bo.locator("#protocol-changes")).to_contain_text("Sorry? Yes or no, please.")
    expect(bo.get_by_label("attempts", exact=True)).to_have_value("2")
    # Carried over: ada's line is in bo's form now, so bo's second save keeps both changes.
    expect(bo.get_by_label("reprompt", exact=True)).to_have_value("Sorry? Yes or no, please.")
    bo.screenshot(path=str(artifacts / "designer-conflict-1366.png"), full_page=False)
    bo.get_by_role("button", name="Save speech").click()
    expect(bo.get_by_text("Saved as version 3.")).to_be_visible()
    expect(bo.get_by_label("attempts", exact=True)).to_have_value("2")
    expect(bo.get_by_label("reprompt", exact=True)).to_have_value("Sorry? Yes or no, please.")
    for page in pages:
        page.context.close()


@pytest.mark.e2e
def test_a_draft_is_piloted_and_taken_live(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    make_user(database, WHO, Role.ADMIN)
    _draft(database)
    width, height = SIZES[0]
    page = browser.new_context(viewport={"width": width, "height": height}).new_page()
    sign_in_page(page, live_server, f"/studies/{NAME}", username=WHO)
    page.get_by_role("link", name="Start the pilot…").click()
    page.get_by_role("button", name="Start the pilot").press("Enter")
    expect(page.get_by_text("Pilot started")).to_be_visible()
    page.get_by_role("button", name="Enrol a pilot participant").click()
    row = page.locator("#participant-rows tr", has_text="pilot-001")
    expect(row.locator(".badge", has_text=re.compile("^pilot$"))).to_be_visible()
    expect(page.locator("#study-phase")).to_contain_text("(1 so far)")  # updated beside it
    expect(page.get_by_role("link", name="Back to draft…")).to_have_count(0)
    _at_each_size(page, artifacts, "pilot-study", fits="#participant-rows", full_page=True)
    page.get_by_role("link", name="Go live…").click()
    expect(page.get_by_text("This cannot be undone")).to_be_visible()
    _at_each_size(page, artifacts, "go-live", fits="#phase-confirmation button")
    page.get_by_role("button", name="Go live").click()
    expect(page.get_by_text("The study is live")).to_be_visible()
    expect(page.locator("#study-phase")).to_contain_text("Pilot participants")
    page.get_by_role("button", name="Enrol and randomise").click()
    expect(page.locator("#participant-rows")).to_contain_text("P001")
    page.get_by_role("link", name="Reset the pilot…").click()
    page.get_by_role("button", name="Delete 1 pilot participant").click()
    expect(page.get_by_text("Reset the pilot of")).to_be_visible()
    expect(page.locator("#participant-rows")).not_to_contain_text("pilot-001")
    expect(page.locator("#study-phase")).to_have_count(0)
    page.context.close()


@pytest.mark.e2e
def test_the_room_is_previewed_as_a_participant_walks_it(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    """Issue 50 item 3's room: walk into a zone, hear and answer its question in Swedish, hear
    the reply; every reply line listed to hear; nothing stored."""
    make_user(database, WHO, Role.EXPERIMENTER)
    _draft(database)
    width, height = SIZES[0]
    page = browser.new_context(viewport={"width": width, "height": height}).new_page()
    page.add_init_script("window.speechSynthesis && (window.speechSynthesis.speak = () => {});")
    sign_in_page(page, live_server, f"/studies/{NAME}/preview?language=sv", username=WHO)
    before = _rows(database)  # signed in: from here on nothing may be stored
    page.get_by_role("link", name="Walk the room").click()
    drive.wait_ready(page)
    expect(page.get_by_role("note")).to_contain_text("nothing is stored")
    swedish = shipped_protocol("fast_adaptation_trust_sv.toml").protocol.in_language("sv")
    drive.walk(page, drive.TO_CONATION)
    question = drive.wait_question(page, "conation")
    assert question in swedish.category("conation").questions
    expect(page.locator("#caption-text")).to_have_text(question)
    page.keyboard.press("KeyJ")  # Swedish: J for ja
    drive.wait_reply(page)
    replies = {level.line(True) for level in swedish.replies.levels}
    reply = page.locator("#caption-text").inner_text()
    assert any(reply.startswith(line) for line in replies), reply
    _at_each_size(page, artifacts, "room-preview", fits=".room-preview")
    page.get_by_text("Every reply, by level").click()
    expect(page.locator(".room-preview audio")).to_have_count(2 * len(swedish.replies.levels))
    page.context.close()
    assert _rows(database) == before
