"""The staff pages at a laptop's and a tablet's width in real Chromium (issue 21, defects 4 and
9): the console asks before seating a participant who finished, the overview table fits, audit
entries read as one line of time and key/value details, timelines show item texts, a new user is
an experimenter unless chosen otherwise."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from playwright.sync_api import Browser, Page, expect

from app.db import Database
from app.protocol import shipped_protocol
from app.services import studies
from app.services.audit import Actor
from app.tables import Participant, ParticipantStatus, Role
from tests.conftest import Lab, create_blinded_study, make_user
from tests.e2e.conftest import sign_in_page
from tests.e2e.test_refusals import SIZES
from tests.servers import ServerProcess


def _overflow(page: Page, selector: str) -> list[str]:
    """Each element matching ``selector`` that reaches past its card, or a page wider than the
    window (a cut column is either)."""
    return page.evaluate(
        """(selector) => {
             const wide = document.documentElement.scrollWidth > window.innerWidth + 1
               ? [`page ${document.documentElement.scrollWidth} > ${window.innerWidth}`] : [];
             return wide.concat(Array.from(document.querySelectorAll(selector)).flatMap((el) => {
               const box = el.getBoundingClientRect();
               const card = (el.closest('.card') || document.querySelector('main'))
                 .getBoundingClientRect();
               const cut = box.right > card.right + 1;
               return cut ? [`${selector}: ${box.right} > ${card.right}`] : [];
             }));
           }""",
        selector,
    )


def _wrapped(page: Page, selector: str) -> list[str]:
    """The text of each element matching ``selector`` that runs over more than one line."""
    return page.evaluate(
        """(selector) => Array.from(document.querySelectorAll(selector)).flatMap((el) => {
             const range = document.createRange();
             range.selectNodeContents(el);
             const tops = new Set(Array.from(range.getClientRects(), (r) => Math.round(r.top)));
             return tops.size > 1 ? [el.textContent.trim()] : [];
           })""",
        selector,
    )


@pytest.mark.e2e
@pytest.mark.parametrize(("width", "height"), SIZES)
def test_the_staff_pages_fit_and_read(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    lab: Lab,
    artifacts: Path,
    width: int,
    height: int,
) -> None:
    make_user(database, "operator", Role.ADMIN)
    running = lab.enrol_and_assign("P-RUNNING-01")
    lab.start_session()  # the longest overview row: a running session's badge
    for code in ("P-DONE-02", "P-WAIT-03"):
        assert (
            lab.experimenter.post(
                f"/api/v1/studies/{lab.study}/participants", json={"code": code}
            ).status_code
            == 201
        )
    with database.writing() as db:
        finished = db.query(Participant).filter_by(code="P-DONE-02").one()
        finished.status = ParticipantStatus.COMPLETED
        db.commit()
    context = browser.new_context(viewport={"width": width, "height": height})
    page = context.new_page()

    sign_in_page(page, live_server, f"/studies/{lab.study}")
    expect(page.get_by_role("link", name="Withdraw…").first).to_be_visible()
    page.screenshot(path=str(artifacts / f"overview-{width}.png"), full_page=True)
    assert _overflow(page, "#participant-rows") == []
    assert _wrapped(page, ".heading .actions .button, .heading .actions button") == []

    # The withdraw form (issue 48 item 5): each radio small and beside its words, the code's
    # caption on one line.
    page.goto(f"{live_server.url}/studies/{lab.study}/participants/P-WAIT-03/withdraw")
    choices = page.locator("fieldset label:has(input[type=radio])")
    expect(choices).to_have_count(2)
    for index in range(2):
        radio = choices.nth(index).locator("input[type=radio]").bounding_box()
        words = choices.nth(index).locator("span").bounding_box()
        assert radio is not None and words is not None
        assert radio["width"] <= 28 and radio["height"] <= 28, radio  # as every check box
        assert radio["x"] + radio["width"] <= words["x"], "the radio is not beside its words"
        assert radio["y"] <= words["y"] + 24, "the radio is not on the first line of its words"
    assert _wrapped(page, "label:has(input[name=confirm_code]) > span") == []
    page.screenshot(path=str(artifacts / f"withdraw-{width}.png"), full_page=True)

    page.goto(f"{live_server.url}/studies/{lab.study}/participants/{running}")
    demographics = page.locator("details.questionnaire", has_text="About you")
    demographics.locator("summary").click()
    expect(demographics).to_contain_text("How old are you (in years)?")  # the text beside "age"
    expect(demographics).to_contain_text("female (Female)")  # a choice with its label
    page.screenshot(path=str(artifacts / f"timeline-{width}.png"), full_page=True)

    # A second console, free: typing the code of someone who finished asks first.
    page.goto(f"{live_server.url}/stations")
    page.get_by_label("New station").fill("lab-2")
    page.get_by_role("button", name="Create").click()
    expect(page.get_by_role("heading", name="lab-2")).to_be_visible()
    page.goto(f"{live_server.url}/stations/lab-2")
    page.get_by_role("textbox", name="Participant").fill("P-DONE-02")
    page.get_by_role("button", name="Seat here").click()
    question = page.get_by_role("alertdialog")
    expect(question).to_contain_text("Seat P-DONE-02 here?")
    expect(question).to_contain_text("has finished the study")
    page.screenshot(path=str(artifacts / f"console-asks-{width}.png"), full_page=True)
    assert _overflow(page, "[role=alertdialog]") == []
    question.get_by_role("button", name="Seat P-DONE-02 anyway").click()
    expect(page.locator("#console")).to_contain_text("P-DONE-02")
    expect(page.get_by_role("alertdialog")).to_have_count(0)

    page.goto(f"{live_server.url}/admin/audit")
    when = page.locator("table.audit tbody td:first-child").first
    line = float(when.evaluate("el => parseFloat(getComputedStyle(el).lineHeight)"))
    inner = when.locator("time").bounding_box()
    assert inner is not None and inner["height"] < 1.5 * line, "a timestamp wraps"
    expect(page.locator("table.audit dl.kv").first).to_be_visible()
    assert "{" not in page.locator("table.audit").inner_text()  # no raw JSON
    page.screenshot(path=str(artifacts / f"audit-{width}.png"), full_page=True)
    assert _overflow(page, "table.audit") == []

    page.goto(f"{live_server.url}/admin/users")
    assert page.get_by_label("Role").input_value() == "experimenter"
    context.close()


@pytest.mark.e2e
def test_a_blinded_study_shows_what_is_sealed_without_empty_or_dead_controls(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    """Issue 35: the dashboard's adaptation chart is not an empty box while the learners are
    sealed, and the sealed downloads are visibly disabled, with the reason and no link."""
    create_blinded_study(database, "blind")
    make_user(database, "operator", Role.ADMIN)
    context = browser.new_context(viewport={"width": 1366, "height": 900})
    page = context.new_page()
    sign_in_page(page, live_server, "/studies/blind/dashboard")
    expect(page.locator("#dashboard")).to_have_attribute("data-drawn", re.compile(r"[1-9]"))
    expect(page.locator("#adaptation-hidden")).to_contain_text("this study is blinded")
    expect(page.get_by_test_id("adaptation")).to_be_hidden()
    card = page.locator("#adaptation-hidden").locator("xpath=..").bounding_box()
    assert card is not None and card["height"] < 150, card  # the note, not a 380 px chart area
    page.screenshot(path=str(artifacts / "blinded-dashboard.png"), full_page=True)

    page.goto(f"{live_server.url}/studies/blind/analysis")
    downloads = page.locator("ul.downloads li")
    for sealed in ("adaptation_steps.csv", "adaptation_trust.csv"):
        item = downloads.filter(has_text=sealed)
        expect(item.get_by_role("link")).to_have_count(0)
        control = item.locator("[aria-disabled=true]")
        expect(control).to_have_css("cursor", "not-allowed")
        assert float(control.evaluate("el => getComputedStyle(el).opacity")) <= 0.6
        expect(item).to_contain_text("not until the study is unblinded (it would show which group")
    expect(downloads.filter(has_text="answers_long.csv").get_by_role("link")).to_have_count(1)
    page.screenshot(path=str(artifacts / "blinded-downloads.png"), full_page=True)
    context.close()


@pytest.mark.e2e
def test_a_live_refresh_keeps_what_the_experimenter_is_typing(
    browser: Browser, live_server: ServerProcess, database: Database, lab: Lab
) -> None:
    """The console refreshes itself whenever its station changes (and once more when it opens
    after a change): a code half typed into its form stays there, with the caret."""
    make_user(database, "operator", Role.ADMIN)
    page = browser.new_context().new_page()
    sign_in_page(page, live_server, f"/stations/{lab.station}")
    field = page.get_by_role("textbox", name="Participant")
    field.fill("P-TYP")
    page.evaluate(
        """() => {
             window.__before = document.getElementById('console');
             htmx.trigger(window.__before, 'trustlab:refresh');
           }"""
    )
    page.wait_for_function("() => document.getElementById('console') !== window.__before")
    expect(field).to_have_value("P-TYP")
    expect(field).to_be_focused()
    page.context.close()


@pytest.mark.e2e
@pytest.mark.parametrize(("width", "height"), SIZES)
def test_a_new_study_starts_from_a_shipped_protocol_by_keyboard(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    artifacts: Path,
    width: int,
    height: int,
) -> None:
    """Issue 50 item 1: the shipped protocols are named, described and chosen without a file."""
    make_user(database, "operator", Role.ADMIN)
    page = browser.new_context(viewport={"width": width, "height": height}).new_page()
    sign_in_page(page, live_server, "/admin/studies/new")
    assert _overflow(page, "fieldset label") == []
    page.screenshot(path=str(artifacts / f"new-study-{width}.png"), full_page=True)
    page.get_by_label("Name").fill("sv-pilot")
    swedish = page.get_by_role("radio", name=re.compile("fast_adaptation_trust_sv.toml"))
    swedish.focus()
    page.keyboard.press("Space")
    expect(swedish).to_be_checked()
    page.get_by_role("button", name="Create study").press("Enter")
    expect(page).to_have_url(f"{live_server.url}/studies/sv-pilot")
    expect(page.get_by_text("Study created.")).to_be_visible()
    page.goto(f"{live_server.url}/admin/studies/new")  # now a study can be copied too
    page.get_by_role("radio", name=re.compile("A copy of a study")).check()
    page.get_by_label("Study to copy").select_option("sv-pilot")
    assert _overflow(page, "fieldset label") == []
    page.screenshot(path=str(artifacts / f"new-study-copy-{width}.png"), full_page=True)
    page.context.close()


@pytest.mark.e2e
@pytest.mark.parametrize(("width", "height"), SIZES)
def test_a_study_is_previewed_as_a_participant_sees_it(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    artifacts: Path,
    width: int,
    height: int,
) -> None:
    """Issue 50 item 3: the tablet's pages in the study's other language, checked as the
    tablet checks them, with a banner saying nothing is stored."""
    make_user(database, "operator", Role.ADMIN)
    with database.writing() as db:
        studies.create_study(
            db,
            name="sv-preview",
            loaded=shipped_protocol("fast_adaptation_trust_sv.toml"),
            actor=Actor.system("test"),
        )
    page = browser.new_context(viewport={"width": width, "height": height}).new_page()
    sign_in_page(page, live_server, "/studies/sv-preview")
    page.get_by_role("link", name="Preview as a participant").click()
    page.get_by_role("link", name="svenska").click()
    page.get_by_role("link", name="Start the preview").click()
    expect(page.locator("html")).to_have_attribute("lang", "sv")
    expect(page.get_by_role("note")).to_contain_text("nothing entered here is stored")
    page.get_by_role("button").first.click()  # sent without the box ticked
    expect(page.locator("#err-accept")).to_be_visible()
    page.screenshot(path=str(artifacts / f"preview-consent-{width}.png"), full_page=True)
    page.get_by_role("checkbox").check()
    page.get_by_role("button").first.click()
    expect(page).to_have_url(f"{live_server.url}/studies/sv-preview/preview/sv/2")
    page.screenshot(path=str(artifacts / f"preview-questionnaire-{width}.png"), full_page=True)
    page.context.close()


@pytest.mark.e2e
def test_a_protocol_is_checked_as_it_is_typed(
    browser: Browser, live_server: ServerProcess, database: Database, artifacts: Path
) -> None:
    """Issue 50 item 2's first step: a mistake typed into the protocol's text is named with its
    key beside it, without sending the form; put right, the list says so."""
    make_user(database, "operator", Role.ADMIN)
    page = browser.new_context(viewport={"width": 1366, "height": 768}).new_page()
    sign_in_page(page, live_server, "/admin/studies/new")
    page.get_by_role("button", name="Edit its text").click()
    text = page.get_by_role("textbox", name="Protocol")
    original = text.input_value()
    text.fill(original.replace("sessions = 4", "sessions = 0"))
    problems = page.locator("#protocol-problems")
    expect(problems).to_contain_text("schedule.sessions")
    page.screenshot(path=str(artifacts / "protocol-problem-1366.png"), full_page=False)
    text.fill(original.replace("sessions = 4", "sessions = 3"))
    expect(problems).to_contain_text("No problems")
    page.get_by_label("Name").fill("three-sessions")
    page.get_by_role("button", name="Create study").click()
    expect(page).to_have_url(f"{live_server.url}/studies/three-sessions")
    page.context.close()
