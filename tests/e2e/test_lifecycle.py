"""A participant's change reaches every open view without a reload, in real Chromium (issue 48,
item 1): a Swedish participant between two sessions, with the operator console, the room and
their tablet open, is erased; or, reading the consent page, withdrawn keeping their data."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from importlib import resources
from pathlib import Path

import pytest
from playwright.sync_api import Browser, BrowserContext, Page, expect

from app.db import Database
from app.protocol import parse_protocol
from app.services import studies
from app.services.participants import enrolment, languages, questionnaires, tablet_tokens
from app.tables import Participant
from tests.conftest import EXP3_ONLY, TRUST_ANSWERS
from tests.e2e import room_driver as drive
from tests.e2e.conftest import SECRET, SSE_OPEN, sign_in_page
from tests.servers import ServerProcess

STUDY = "sv"
ONE_RUN_SESSIONS = {"runs_per_session = 3": "runs_per_session = 1"}
ONE_RUN_SESSIONS |= {"familiarisation_run = true": "familiarisation_run = false"}
"""Sessions of one run and no practice run: session 2 comes next after three answers."""
TABLET = {"width": 768, "height": 1024}
DESKTOP = {"width": 1366, "height": 768}
THANKS = "Tack för din tid"  # the withdrawn page's heading in Swedish (app/i18n/locales/sv)


def _swedish_study(database: Database) -> None:
    text = resources.files("app.protocols").joinpath("fast_adaptation_trust_sv.toml").read_text()
    for old, new in {**EXP3_ONLY, **ONE_RUN_SESSIONS}.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    with database.writing() as db:
        studies.create_study(db, name=STUDY, loaded=parse_protocol(text), actor=drive.SYSTEM)


def _swedish_participant(database: Database, code: str) -> Participant:
    with database.writing() as db:
        return enrolment.enroll_participant(
            db, study_name=STUDY, actor=drive.SYSTEM, code=code, language="sv"
        ).participant


def _tablet_link(database: Database, participant: Participant) -> str:
    with database.writing() as db:
        return tablet_tokens.issue_participant_token(
            db, participant=db.merge(participant), secret=SECRET, actor=drive.SYSTEM
        )


def _tablet_listening(tablet: Page) -> None:
    """Until the tablet's event stream is open (static/js/tablet.js marks its page)."""
    expect(tablet.locator("body")).to_have_attribute("data-listening", "yes")


@pytest.fixture
def context_of(browser: Browser) -> Iterator[Callable[..., BrowserContext]]:
    """New browser contexts (their own cookies: console, room and tablet are three devices),
    closed when the test ends (an open page's streams would hold the server's shutdown)."""
    made: list[BrowserContext] = []

    def make(**options: object) -> BrowserContext:
        made.append(browser.new_context(**options))  # type: ignore[arg-type]
        return made[-1]

    yield make
    for context in made:
        context.close()


def _session_one_done(database: Database, lab: drive.RoomLab, participant: Participant) -> None:
    """Session 1 answered by Wizard-of-Oz, and its questionnaire: session 2 comes next."""
    lab.start_session()
    for category, _ in drive.PAPER_ORDER:
        lab.wizard_answer(lab.wizard_prompt(category))
    with database.writing() as db:
        participant = db.merge(participant)
        protocol = languages.protocol_for("sv", studies.protocol_of(studies.get_study(db, STUDY)))
        questionnaires.submit(
            db,
            participant=participant,
            protocol=protocol,
            instrument_key="trust",
            session=1,
            answers=TRUST_ANSWERS,
            actor=drive.SYSTEM,
        )


@pytest.mark.e2e
def test_erasing_a_seated_participant_reaches_the_console_the_room_and_the_tablet(
    live_server: ServerProcess,
    database: Database,
    context_of: Callable[..., BrowserContext],
    artifacts: Path,
) -> None:
    _swedish_study(database)
    lab = drive.seat_participant(database, live_server.url, STUDY, station="rum-1", code="S1")
    with database.writing() as db:
        participant = enrolment.get_participant(
            db, studies.get_study(db, STUDY), "S1", actor=drive.SYSTEM
        )
        languages.set_language(
            db,
            participant=participant,
            protocol=studies.protocol_of(studies.get_study(db, STUDY)),
            study_name=STUDY,
            language="sv",
            actor=drive.SYSTEM,
        )
    _session_one_done(database, lab, participant)
    token = _tablet_link(database, participant)

    console = context_of(viewport=DESKTOP).new_page()
    console.add_init_script(SSE_OPEN)
    sign_in_page(console, live_server, "/stations/rum-1", username=lab.admin)
    console.wait_for_function("() => window.__sseOpen")
    start = console.get_by_role("button", name="Start session 2")
    expect(start).to_be_visible()
    room = context_of(viewport=DESKTOP).new_page()
    drive.open_room(room, lab, query="?voice=off")
    expect(room.locator("#notice")).to_contain_text("Session 2 kommer härnäst")
    tablet = context_of(viewport=TABLET, has_touch=True).new_page()
    tablet.goto(f"{live_server.url}/t/{token}")
    expect(tablet).to_have_url(f"{live_server.url}/tablet/wait")
    expect(tablet.locator("html")).to_have_attribute("lang", "sv")
    _tablet_listening(tablet)

    erased = lab.experimenter.post(
        f"/api/v1/studies/{STUDY}/participants/S1/erase", json={"confirm": "S1"}
    )
    assert erased.status_code == 200, erased.text

    # No reloads: each view follows the change by itself.
    expect(start).to_have_count(0)
    expect(console.get_by_role("button", name="Seat here")).to_be_visible()
    expect(console.locator("#console")).not_to_contain_text("S1")
    expect(room.locator("#notice")).not_to_contain_text("Session 2")
    expect(room.locator("#notice")).to_contain_text("Välkommen")
    expect(tablet).to_have_url(f"{live_server.url}/tablet/left")
    expect(tablet.locator("html")).to_have_attribute("lang", "sv")
    expect(tablet.get_by_role("heading", level=1)).to_have_text(THANKS)
    for name, page in (("console", console), ("room", room), ("tablet", tablet)):
        page.screenshot(path=str(artifacts / f"erased-{name}.png"))
    tablet.reload()  # and it stays so: the page needs no link
    expect(tablet.get_by_role("heading", level=1)).to_have_text(THANKS)


@pytest.mark.e2e
def test_a_tablet_on_the_consent_page_follows_a_withdrawal(
    live_server: ServerProcess,
    database: Database,
    context_of: Callable[..., BrowserContext],
) -> None:
    _swedish_study(database)
    participant = _swedish_participant(database, "S2")
    token = _tablet_link(database, participant)
    tablet = context_of(viewport=TABLET, has_touch=True).new_page()
    tablet.goto(f"{live_server.url}/t/{token}")
    expect(tablet).to_have_url(f"{live_server.url}/tablet/consent")
    _tablet_listening(tablet)
    lab = drive.seat_participant(database, live_server.url, STUDY, station="rum-2", code="S3")

    withdrawn = lab.experimenter.post(
        f"/api/v1/studies/{STUDY}/participants/S2/withdraw", json={"reason": ""}
    )
    assert withdrawn.status_code == 200, withdrawn.text

    expect(tablet).to_have_url(f"{live_server.url}/tablet/withdrawn")
    expect(tablet.get_by_role("heading", level=1)).to_have_text(THANKS)
