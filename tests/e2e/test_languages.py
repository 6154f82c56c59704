"""A Swedish participant in real Chromium on a 768×1024 tablet and in the escape room: the
language is chosen on the tablet's first page, and from then on every page, banner, question and
reply is Swedish, with no English sentence of the interface or the protocol on screen."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Browser, Page, expect
from sqlalchemy import select

from app.db import Database
from app.i18n.catalogues import catalogue
from app.i18n.protocol_texts import text_slots
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.participants import enrolment, tablet_tokens
from app.services.sessions import stations
from app.tables import Answer, Prompt, Role
from tests import participant_words as words
from tests.conftest import EXP3_ONLY, PASSWORD, PRE_STUDY_ANSWERS, make_user
from tests.e2e import room_driver as drive
from tests.e2e.conftest import SECRET
from tests.servers import ServerProcess

SYSTEM = Actor.system("e2e-languages")


def _swedish_study(database: Database) -> str:
    text = resources.files("app.protocols").joinpath("fast_adaptation_trust_sv.toml").read_text()
    # the browser's own recogniser, so that the room hears Swedish (the server's is English only)
    for old, new in {**EXP3_ONLY, "cloud_recognizer = false": "cloud_recognizer = true"}.items():
        text = text.replace(old, new)
    with database.writing() as db:
        studies.create_study(db, name="sv", loaded=parse_protocol(text), actor=SYSTEM)
    return text


def _english_sentences(protocol_text: str) -> set[str]:
    """What a Swedish participant must not see: the interface's English sentences that Swedish
    says otherwise, and the protocol's English texts (both with more than one word)."""
    swedish = catalogue("sv")
    words = {m for m in catalogue("en").messages if swedish.gettext(m) != m and "%" not in m}
    protocol = parse_protocol(protocol_text).protocol
    for slot in text_slots(protocol.model_dump(mode="json")):
        words.update([slot.source] if isinstance(slot.source, str) else slot.source)
    return {w for w in words if " " in w}


def _no_english(page: Page, english: set[str], where: str) -> None:
    shown = " ".join(page.locator("body").inner_text().split())
    leaked = sorted(w for w in english if " ".join(w.split()) in shown)
    assert leaked == [], f"{where}: English on a Swedish page: {leaked}"


def _fill_pre_study(page: Page, english: set[str]) -> None:
    """Each pre-study page, answered as the JSON tests answer it, checked for English."""
    while "/tablet/q/" in page.url:
        instrument = page.url.rsplit("/", 1)[1]
        expect(page.locator("html")).to_have_attribute("lang", "sv")
        _no_english(page, english, instrument)
        for name, value in PRE_STUDY_ANSWERS[instrument].items():
            field = page.locator(f'[name="{name}"]')
            if field.first.get_attribute("type") == "radio":
                page.locator(f'input[name="{name}"][value="{value}"]').check()
            else:
                field.fill(value)
        page.get_by_role("button", name="Fortsätt").click()
        page.wait_for_url(lambda url, before=instrument: not url.endswith(before))


def _only_swedish(page: Page, known: list[str], where: str) -> None:
    """Every word the room shows, in its tab title, labels and key hints, is the Swedish
    catalogue's or the protocol's Swedish (or the station's name)."""
    shown = page.evaluate(
        """() => [document.title, ...document.body.innerText.split("\\n"),
             ...[...document.querySelectorAll("[aria-label], [aria-keyshortcuts]")]
               .filter((el) => el.checkVisibility())
               .flatMap((el) => ["aria-label", "aria-keyshortcuts"].map((a) => el.getAttribute(a)))
               .filter(Boolean)]"""
    )
    left = words.unexplained(shown, known, also=["rum-1"])
    assert left == [], f"{where}: not Swedish: {left}"


@pytest.mark.e2e
def test_a_swedish_participant_on_the_tablet_and_in_the_room(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    artifacts: Path,
) -> None:
    protocol_text = _swedish_study(database)
    english = _english_sentences(protocol_text)
    with database.writing() as db:
        participant = enrolment.enroll_participant(
            db, study_name="sv", actor=SYSTEM, code="S1"
        ).participant
    with database.writing() as db:
        token = tablet_tokens.issue_participant_token(
            db, participant=db.merge(participant), secret=SECRET, actor=SYSTEM
        )
    context = browser.new_context(viewport={"width": 768, "height": 1024}, has_touch=True)
    tablet = context.new_page()
    tablet.goto(f"{live_server.url}/t/{token}")
    expect(tablet).to_have_url(f"{live_server.url}/tablet/language")
    tablet.screenshot(path=str(artifacts / "01-language.png"), full_page=True)
    tablet.get_by_role("button", name="Svenska").click()

    expect(tablet).to_have_url(f"{live_server.url}/tablet/consent")
    expect(tablet.locator("html")).to_have_attribute("lang", "sv")
    expect(tablet.get_by_role("heading", level=1)).to_have_text("Innan vi börjar")
    _no_english(tablet, english, "consent")
    tablet.get_by_role("button", name="Fortsätt").click()
    expect(tablet.get_by_role("alert").first).to_contain_text("Kryssa i rutan för att delta.")
    tablet.get_by_label("Jag har läst texten ovan och samtycker till att delta.").check()
    tablet.screenshot(path=str(artifacts / "02-consent.png"), full_page=True)
    tablet.get_by_role("button", name="Fortsätt").click()
    tablet.wait_for_url("**/tablet/q/**")  # _fill_pre_study reads the URL to know where it is
    _fill_pre_study(tablet, english)
    expect(tablet).to_have_url(f"{live_server.url}/tablet/wait")
    expect(tablet.locator("body")).to_contain_text("Vänta på försöksledaren.")
    _no_english(tablet, english, "wait")

    # The room, with the participant seated: its banners, the question and the reply in Swedish.
    with database.writing() as db:
        stations.create_station(db, name="rum-1", actor=SYSTEM)
    with database.writing() as db:
        key = stations.issue_device_key(db, station_name="rum-1", label="rum", actor=SYSTEM).key
    with database.writing() as db:
        seated = enrolment.get_participant(
            db, studies.get_study(db, "sv"), "S1", actor=Actor.system()
        )
        stations.assign_participant(db, station_name="rum-1", participant=seated, actor=SYSTEM)
    room = context.new_page()
    room.add_init_script(drive.FAKE_SPEECH)
    room.goto(f"{live_server.url}/stations/rum-1/room?voice=off&listen=on")
    room.get_by_label("Device key of station rum-1").fill(key)
    room.get_by_role("button", name="Open the room").click()
    room.wait_for_function("() => window.trustlabRoom && window.trustlabRoom.ready")
    expect(room.locator("html")).to_have_attribute("lang", "sv")
    expect(room.locator("#notice")).to_contain_text("Först kommer en övningsrunda")
    expect(room.locator("#rules")).to_contain_text("Ditt mål är att ta dig ut ur rummet.")
    # Drawn before the Swedish words arrived, and said again once they did (issue 48, item 12).
    expect(room.locator("#connection")).to_have_text("Ansluten")
    swedish_words = words.known_texts("sv", parse_protocol(protocol_text).protocol)
    _only_swedish(room, swedish_words, "the room before the session")

    make_user(database, "e2e-admin", Role.ADMIN)
    staff = httpx.Client(base_url=live_server.url, timeout=30)
    signed_in = staff.post("/api/v1/session", json={"username": "e2e-admin", "password": PASSWORD})
    staff.headers["X-CSRF-Token"] = signed_in.json()["csrf_token"]
    assert staff.post("/api/v1/stations/rum-1/sessions").status_code == 201
    expect(room.locator("#run-label")).to_have_text("Övningsrunda (räknas inte)")
    prompted = staff.post("/api/v1/stations/rum-1/prompts", json={"category": "cognition"})
    assert prompted.status_code == 201, prompted.text
    question = prompted.json()["question"]
    assert question.startswith("Här är nycklarna.")
    expect(room.locator("#caption-text")).to_have_text(question)
    expect(room.locator("#caption-speaker")).to_have_text("Robot:")
    # The answer keys are the catalogue's: J and N in Swedish, on the buttons and the keyboard.
    expect(room.locator("#answer-yes kbd")).to_have_text("J")
    expect(room.get_by_role("button", name="Ja")).to_have_attribute("aria-keyshortcuts", "J")
    room.reload()  # the question again, with every word drawn after a reload in Swedish too
    room.wait_for_function("() => window.trustlabRoom && window.trustlabRoom.ready")
    expect(room.locator("#caption-text")).to_have_text(question)
    expect(room.locator("#caption-speaker")).to_have_attribute("data-t", "Robot:")
    expect(room.locator("#connection")).to_have_text("Ansluten")
    _only_swedish(room, swedish_words, "the room asking")
    room.keyboard.press("KeyJ")
    expect(room.locator("#captions")).to_have_attribute("data-kind", "reply")
    swedish = parse_protocol(protocol_text).protocol.in_language("sv")
    replies = {level.line(True) for level in swedish.replies.levels}
    assert room.locator("#caption-text").inner_text() in replies
    room.screenshot(path=str(artifacts / "03-room.png"))
    _no_english(room, english, "room")
    _only_swedish(room, swedish_words, "the room replying")
    with database.read_session() as db:
        keyed = db.scalars(
            select(Answer).join(Prompt).where(Prompt.id == prompted.json()["step_id"])
        )
        assert [(a.answer, a.modality) for a in keyed] == [(True, "key")]

    # Answered aloud in Swedish: the protocol's Swedish phrases are what the recogniser listens for.
    room.evaluate("() => { window.__heard.push(['Ja, absolut.', 0.9]); }")
    spoken = staff.post("/api/v1/stations/rum-1/prompts", json={"category": "conation"})
    assert spoken.status_code == 201, spoken.text
    expect(room.locator("#caption-text")).to_have_text(spoken.json()["question"])
    drive.wait_reply(room)
    with database.read_session() as db:
        heard = db.scalars(
            select(Answer).join(Prompt).where(Prompt.id == spoken.json()["step_id"])
        ).one()
    assert (heard.answer, heard.modality, heard.transcript) == (True, "speech", "Ja, absolut.")
