"""The browser escape room end to end: a participant walks the maze by keyboard in real Chromium,
the zones ask the robot's questions, and every answer reaches the database exactly once."""

from __future__ import annotations

import itertools
import json
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from playwright.sync_api import (
    Browser,
    BrowserContext,
    Page,
    Playwright,
    Route,
    WebSocketRoute,
    expect,
)
from sqlalchemy import func, select

from app.db import Database
from app.protocol import default_protocol, parse_protocol
from app.services import studies
from app.services.sessions import verify
from app.services.sessions.answer_audio import as_wav
from app.speech.synthesis import with_true_sizes
from app.speech.wav import decode_wav
from app.tables import Answer, Participant, Prompt
from tests.conftest import protocol_text
from tests.e2e import room_driver as drive
from tests.e2e.conftest import SSE_OPEN, launch_chromium, sign_in_page
from tests.servers import ServerProcess

STUDY = "default"
SHORT_STUDY = "short"
"""Sessions of two runs and no practice run: the walk through a session needs one run to walk
out of and one to follow it, not the shipped protocol's practice run and three runs (the practice
run is walked in the reload test)."""
SHORT_PROTOCOL = {"runs_per_session = 3": "runs_per_session = 2"}
SHORT_PROTOCOL |= {"familiarisation_run = true": "familiarisation_run = false"}
CLOUD_STUDY = "cloud"
"""A study whose protocol allows the browser's own (cloud) recogniser."""
CLOUD_PROTOCOL = {"cloud_recognizer = false": "cloud_recognizer = true"}
SEATS = itertools.count(1)
DESKTOP = {"width": 1366, "height": 768}


@dataclass
class RoomServer:
    """One server and database for this module's tests: each test seats its own participant at
    a station of its own, so they do not meet (a server start is the dearest part of a setup)."""

    server: ServerProcess
    database: Database

    @property
    def url(self) -> str:
        return self.server.url


@pytest.fixture(scope="module")
def room_server(
    sqlite_template: Path, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[RoomServer]:
    folder = tmp_path_factory.mktemp("room")
    shutil.copyfile(sqlite_template, folder / "room.sqlite3")
    url = f"sqlite:///{folder / 'room.sqlite3'}"
    database = Database(url, sqlite_synchronous="NORMAL")
    with database.writing() as db:
        studies.create_study(db, name=STUDY, loaded=default_protocol(), actor=drive.SYSTEM)
        short = parse_protocol(protocol_text(**SHORT_PROTOCOL))
        studies.create_study(db, name=SHORT_STUDY, loaded=short, actor=drive.SYSTEM)
        cloud = parse_protocol(protocol_text(**CLOUD_PROTOCOL))
        studies.create_study(db, name=CLOUD_STUDY, loaded=cloud, actor=drive.SYSTEM)
    server = ServerProcess(url, folder / "var")
    server.start()
    yield RoomServer(server, database)
    server.stop()
    database.dispose()


def _seat(room_server: RoomServer, study: str) -> drive.RoomLab:
    seat = next(SEATS)
    return drive.seat_participant(
        room_server.database, room_server.url, study, station=f"room-{seat}", code=f"R{seat:03d}"
    )


@pytest.fixture
def lab(room_server: RoomServer) -> drive.RoomLab:
    """This test's participant in the shipped study, seated at a station of its own."""
    return _seat(room_server, STUDY)


@pytest.fixture
def short_lab(room_server: RoomServer) -> drive.RoomLab:
    """This test's participant in the study of two-run sessions, seated at a station of its own."""
    return _seat(room_server, SHORT_STUDY)


@pytest.fixture
def context_of(browser: Browser) -> Iterator[Callable[..., BrowserContext]]:
    """New browser contexts, closed when the test ends (an open page's streams would hold the
    server's graceful shutdown)."""
    made: list[BrowserContext] = []

    def make(**options: object) -> BrowserContext:
        made.append(browser.new_context(**options))  # type: ignore[arg-type]
        return made[-1]

    yield make
    for context in made:
        context.close()


TABLET = {"width": 768, "height": 1024}


def _steps(database: Database, code: str) -> list[tuple[int, str, str | None, str | None, int]]:
    """(prompt id, category, zone, answer modality, answers stored for it) of every step of the
    participant ``code``."""
    with database.read_session() as db:
        rows = db.execute(
            select(Prompt.id, Prompt.category, Prompt.zone, Answer.modality)
            .join(Participant, Participant.id == Prompt.participant_id)
            .outerjoin(Answer, Answer.prompt_id == Prompt.id)
            .where(Participant.code == code)
            .order_by(Prompt.id)
        ).all()
        counts = dict(
            db.execute(select(Answer.prompt_id, func.count()).group_by(Answer.prompt_id)).all()
        )
    return [(pid, category, zone, how, counts.get(pid, 0)) for pid, category, zone, how in rows]


def _wait_until(condition: Callable[[], bool], limit: float = 30.0) -> None:
    """Poll the database until ``condition`` holds (a generous limit: only a hang fails)."""
    deadline = time.monotonic() + limit
    while not condition():
        assert time.monotonic() < deadline, "the condition never held"
        time.sleep(0.05)


def _verified(database: Database, study: str) -> None:
    with database.read_session() as db:
        report = verify.verify_study(db, study_name=study)
    assert report.ok, report.findings


@pytest.mark.e2e
def test_a_participant_walks_through_a_session(
    room_server: RoomServer,
    short_lab: drive.RoomLab,
    context_of: Callable[..., BrowserContext],
    artifacts: Path,
) -> None:
    database = room_server.database
    lab = short_lab
    page = context_of(viewport=DESKTOP).new_page()
    drive.open_room(page, lab)
    expect(page.locator("#notice")).to_contain_text("Session 1 comes next")
    page.screenshot(path=str(artifacts / "01-waiting.png"))

    lab.start_session()  # session 1: two runs, zones in orders the test chooses
    expect(page.locator("#run-label")).to_have_text("Session 1 · run 1 of 2")
    expect(page.locator("#notice")).to_be_hidden()
    drive.walk(page, drive.TO_CONATION)
    drive.wait_question(page, "conation")
    drive.face(page, 90)  # towards the robot, past the first wall's end
    page.screenshot(path=str(artifacts / "02-question-desktop.png"))
    page.set_viewport_size(TABLET)
    page.screenshot(path=str(artifacts / "03-question-tablet.png"))
    page.set_viewport_size(DESKTOP)
    question = page.evaluate("() => window.trustlabRoom.question.question")
    drive.answer_by_rules(page, "conation", question, how="button")
    for category, waypoints in drive.PAPER_ORDER[1:]:
        drive.walk(page, waypoints)
        drive.answer_by_rules(page, category, drive.wait_question(page, category))
    drive.walk_out(page)
    expect(page.locator("#run-label")).to_have_text("Session 1 · run 1 of 2")
    assert drive.run_through(page, drive.AFFECTION_FIRST) == ["affection", "conation", "cognition"]
    expect(page.locator("#notice")).to_contain_text("Please use the tablet")  # the gate holds
    expect(page.locator("#captions")).to_be_hidden()  # no reply lingers under the card
    page.screenshot(path=str(artifacts / "04-session-done.png"))

    steps = _steps(database, lab.code)
    assert len(steps) == 6  # 3 categories × 2 runs
    assert all(count == 1 for *_, count in steps), steps  # every answer stored once
    assert all(zone == category for _, category, zone, _, _ in steps)  # with the zone walked into
    assert {how for *_, how, _ in steps} == {"key", "button"}
    _verified(database, SHORT_STUDY)


def _answers_for(database: Database, code: str, category: str) -> list[Answer]:
    with database.read_session() as db:
        return list(
            db.scalars(
                select(Answer)
                .join(Prompt, Prompt.id == Answer.prompt_id)
                .join(Participant, Participant.id == Answer.participant_id)
                .where(Prompt.category == category, Participant.code == code)
            )
        )


class _Relay:
    """Every room WebSocket through Playwright, so a test can lose the server's reply to an
    answer (the answer reached the server; its acknowledgement did not reach the page)."""

    def __init__(self, page: Page) -> None:
        self.lose_answer_replies = False
        page.route_web_socket("**/api/v1/station/ws", self._route)

    def _route(self, socket: WebSocketRoute) -> None:
        server = socket.connect_to_server()
        socket.on_message(server.send)
        server.on_message(lambda message: self._to_page(socket, message))

    def _to_page(self, socket: WebSocketRoute, message: str | bytes) -> None:
        reply = json.loads(message)
        if self.lose_answer_replies and reply.get("op") == "answer":
            return
        socket.send(message)


@pytest.mark.e2e
def test_a_reload_mid_run_finishes_it_without_duplicates(
    room_server: RoomServer,
    lab: drive.RoomLab,
    context_of: Callable[..., BrowserContext],
    artifacts: Path,
) -> None:
    database = room_server.database
    context = context_of(viewport=TABLET, has_touch=True)
    page = context.new_page()
    relay = _Relay(page)
    drive.open_room(page, lab)
    lab.start_session()
    expect(page.locator("#pads")).to_be_visible()  # a touch screen gets walking pads

    drive.walk(page, drive.TO_CONATION)
    drive.wait_question(page, "conation")  # the question arrives after the walk ends
    step = page.evaluate("() => window.trustlabRoom.question.step_id")
    before = drive.pose(page)
    page.screenshot(path=str(artifacts / "01-tablet-question.png"))
    page.reload()  # a question open: it is asked again, where the participant stood
    drive.wait_ready(page)
    question = drive.wait_question(page, "conation")
    assert page.evaluate("() => window.trustlabRoom.question.step_id") == step
    after = drive.pose(page)
    assert abs(after["x"] - before["x"]) < 0.1 and abs(after["z"] - before["z"]) < 0.1
    drive.answer_by_rules(page, "conation", question, how="button")

    # The answer reaches the server but its reply is lost; the reload sends it again.
    drive.walk(page, drive.TO_AFFECTION_FROM_CONATION)
    question = drive.wait_question(page, "affection")
    relay.lose_answer_replies = True
    page.keyboard.press("KeyY")
    page.wait_for_function(f"() => localStorage.getItem('trustlab.room.answer.{lab.station}')")
    _wait_until(
        lambda: len(_answers_for(database, lab.code, "affection")) == 1
    )  # the server has it
    relay.lose_answer_replies = False
    page.reload()
    drive.wait_ready(page)
    page.wait_for_function(
        f"() => !localStorage.getItem('trustlab.room.answer.{lab.station}') && "
        "!window.trustlabRoom.question"
    )
    drive.walk(page, drive.TO_COGNITION_FROM_AFFECTION)
    drive.answer_by_rules(page, "cognition", drive.wait_question(page, "cognition"))
    expect(page.locator("#notice")).to_contain_text("Session 1 comes next")

    steps = _steps(database, lab.code)
    assert [category for _, category, *_ in steps] == ["conation", "affection", "cognition"]
    assert all(count == 1 for *_, count in steps), steps
    assert all(zone == category for _, category, zone, _, _ in steps)  # practice runs too
    _verified(database, STUDY)


@pytest.mark.e2e
def test_a_dropped_network_shows_a_banner_and_resumes(
    room_server: RoomServer,
    lab: drive.RoomLab,
    context_of: Callable[..., BrowserContext],
    artifacts: Path,
) -> None:
    database = room_server.database
    context = context_of(viewport=DESKTOP)
    page = context.new_page()
    drive.open_room(page, lab)
    lab.start_session()
    drive.walk(page, drive.TO_CONATION)
    question = drive.wait_question(page, "conation")

    context.set_offline(True)
    expect(page.locator("#offline")).to_be_visible()
    expect(page.locator("#connection")).to_have_text("Offline")
    said = drive.preferred_questions()["conation"] == question
    page.keyboard.press("KeyY" if said else "KeyN")  # answered while offline: kept, not lost
    page.screenshot(path=str(artifacts / "01-offline.png"))
    assert _answers_for(database, lab.code, "conation") == []
    context.set_offline(False)
    expect(page.locator("#offline")).to_be_hidden()
    expect(page.locator("#captions")).to_have_attribute("data-kind", "reply")
    stored = _answers_for(database, lab.code, "conation")
    assert len(stored) == 1 and stored[0].answer is said and stored[0].modality == "key"

    drive.walk(page, drive.TO_AFFECTION_FROM_CONATION)  # and the room goes on
    drive.answer_by_rules(page, "affection", drive.wait_question(page, "affection"))
    assert len(_answers_for(database, lab.code, "affection")) == 1


def _console(
    room_server: RoomServer, lab: drive.RoomLab, context_of: Callable[..., BrowserContext]
) -> Page:
    """The station's operator console, signed in as the lab's admin."""
    console = context_of(viewport=DESKTOP).new_page()
    console.add_init_script(SSE_OPEN)
    sign_in_page(console, room_server.server, f"/stations/{lab.station}", username=lab.admin)
    expect(console.locator("#room-panel")).to_be_visible()
    console.wait_for_function("() => window.__sseOpen")  # it hears the changes the test makes
    return console


def _walkable(page: Page) -> bool:
    """Whether holding the forward key for a few drawn frames moves the participant."""
    before = drive.pose(page)
    frames = page.evaluate("() => window.trustlabRoom.frames")
    page.keyboard.down("ArrowUp")
    page.wait_for_function("(n) => window.trustlabRoom.frames > n + 10", arg=frames)
    page.keyboard.up("ArrowUp")
    return drive.pose(page) != before


def _wizard_run(page: Page, lab: drive.RoomLab, categories: list[str]) -> list[str]:
    """Each category prompted and answered yes from the console while the room shows it; the
    replies, in order."""
    replies = []
    for category in categories:
        step = lab.wizard_prompt(category)
        drive.wait_question(page, category)
        replies.append(lab.wizard_answer(step))
    return replies


CATEGORIES = [category for category, _ in drive.PAPER_ORDER]


@pytest.mark.e2e
def test_a_session_finished_from_the_console_shows_what_comes_next_also_after_a_reload(
    room_server: RoomServer,
    lab: drive.RoomLab,
    context_of: Callable[..., BrowserContext],
    artifacts: Path,
) -> None:
    page = context_of(viewport=DESKTOP).new_page()
    drive.open_room(page, lab)
    expect(page.locator("#notice")).to_contain_text("A practice run comes first")
    lab.start_session()  # the practice run, every answer given by Wizard-of-Oz
    expect(page.locator("#run-label")).to_have_text("Practice run (not counted)")
    _wizard_run(page, lab, CATEGORIES)
    expect(page.locator("#notice")).to_contain_text("Session 1 comes next")
    expect(page.locator("#run-label")).to_have_text("Escape room")
    # The last reply was said, and its caption does not linger under the card (issue 48, item 2).
    page.wait_for_function("() => (window.trustlabRoom.said || {}).kind === 'reply'")
    expect(page.locator("#captions")).to_be_hidden()
    assert not _walkable(page)
    page.screenshot(path=str(artifacts / "01-finished-by-wizard.png"))

    page.reload()  # between sessions: the same, from the server's state alone
    drive.wait_ready(page)
    expect(page.locator("#notice")).to_contain_text("Session 1 comes next")
    assert not _walkable(page)


@pytest.mark.e2e
def test_a_wizard_of_oz_answer_shows_the_reply_and_the_way_out_in_the_room(
    room_server: RoomServer,
    lab: drive.RoomLab,
    context_of: Callable[..., BrowserContext],
    artifacts: Path,
) -> None:
    context = context_of(viewport=DESKTOP)
    page = context.new_page()
    drive.open_room(page, lab)
    lab.start_session()
    step = lab.wizard_prompt("conation")
    drive.wait_question(page, "conation")
    reply = lab.wizard_answer(step)  # answered on the console while the room shows the question
    expect(page.locator("#captions")).to_have_attribute("data-kind", "reply")
    expect(page.locator("#caption-text")).to_have_text(reply)
    expect(page.locator("#answer")).to_be_hidden()

    step = lab.wizard_prompt("affection")
    drive.wait_question(page, "affection")
    context.set_offline(True)  # the room is cut off while the console answers: no push reaches it
    expect(page.locator("#offline")).to_be_visible()
    reply = lab.wizard_answer(step, "no")
    context.set_offline(False)  # back: the state it resumes from carries the reply
    expect(page.locator("#offline")).to_be_hidden()
    expect(page.locator("#captions")).to_have_attribute("data-kind", "reply")
    expect(page.locator("#caption-text")).to_have_text(reply)
    expect(page.locator("#answer")).to_be_hidden()
    _wizard_run(page, lab, CATEGORIES[2:])
    expect(page.locator("#notice")).to_contain_text("Session 1 comes next")

    lab.start_session()  # run 1 of 3: its last answer sends the participant to the exit
    expect(page.locator("#run-label")).to_have_text("Session 1 · run 1 of 3")
    *_, last = _wizard_run(page, lab, CATEGORIES)
    walk_out = "Now walk to the exit: the solid circle."
    expect(page.locator("#caption-text")).to_have_text(f"{last} {walk_out}")
    page.screenshot(path=str(artifacts / "01-reply-from-the-console.png"))
    page.reload()  # between runs: the way out is still shown
    drive.wait_ready(page)
    expect(page.locator("#caption-text")).to_have_text(walk_out)
    expect(page.locator("#notice")).to_be_hidden()


def _answer_during_the_prompts_refresh(console: Page, lab: drive.RoomLab) -> list[str]:
    """Start a session and prompt conation; the console's refresh that read the open prompt is
    held back until the prompt is answered and the console has heard of it (htmx's throttle
    drops that event, and a refresh queued behind the held one is dropped when its swap replaces
    the console). The robot's reply is put in the list returned once the console's page has let
    the route handler run (any Playwright call on it)."""
    console.evaluate(
        """() => {
            window.__changes = 0;
            document.addEventListener('htmx:sseMessage', (event) => {
                if (event.detail.type === 'changed') window.__changes += 1;
            });
        }"""
    )
    lab.start_session()
    expect(console.locator("section.woz form button").first).to_be_visible()  # refreshed
    answered: list[str] = []
    step = 0

    def answer_while_refreshing(route: Route) -> None:
        if not (step and not answered and route.request.headers.get("hx-request")):
            route.continue_()
            return
        fetched = route.fetch()
        if f'name="step_id" value="{step}"' not in fetched.text():
            # A refresh for an earlier change (the session's start, late under load): not the
            # one this test is about.
            route.fulfill(response=fetched)
            return
        # The console's refresh has read the open prompt...
        heard = console.evaluate("() => window.__changes")
        answered.append(lab.wizard_answer(step))  # ...and now the answer is committed,
        console.wait_for_function("(n) => window.__changes > n", arg=heard)  # and heard of
        route.fulfill(response=fetched)

    console.route(f"**/stations/{lab.station}", answer_while_refreshing)
    step = lab.wizard_prompt("conation")
    return answered


@pytest.mark.e2e
def test_the_console_shows_the_last_of_two_quick_changes(
    room_server: RoomServer,
    lab: drive.RoomLab,
    context_of: Callable[..., BrowserContext],
) -> None:
    """A change whose event reaches the console while its refresh for the change before is on
    its way is shown all the same."""
    console = _console(room_server, lab, context_of)
    answered = _answer_during_the_prompts_refresh(console, lab)
    expect(console.locator("#console")).to_contain_text("participant: yes")
    assert answered, "the answer was not given during the prompt's refresh"
    expect(console.locator("#console")).to_contain_text(f"robot: “{answered[0]}”")


@pytest.mark.e2e
def test_the_console_catches_up_once_its_swapped_in_copy_is_settled(
    room_server: RoomServer,
    lab: drive.RoomLab,
    context_of: Callable[..., BrowserContext],
) -> None:
    """The console's catch-up refresh waits until the console a refresh swapped in listens.

    htmx processes swapped-in content only when it settles, 20 ms after the swap; a refresh
    held past the console's throttle gap ends with the catch-up due at once, and on a busy
    machine (Chromium's CPU throttled 4x) that came before the settle: htmx heard no trigger and
    the console kept showing the open prompt. Here every swap settles a second late, so the
    catch-up always comes first."""
    console = _console(room_server, lab, context_of)
    console.evaluate("() => { htmx.config.defaultSettleDelay = 1000; }")
    answered = _answer_during_the_prompts_refresh(console, lab)
    expect(console.locator("#console")).to_contain_text("participant: yes")
    assert answered, "the answer was not given during the prompt's refresh"
    expect(console.locator("#console")).to_contain_text(f"robot: “{answered[0]}”")


@pytest.mark.e2e
def test_the_console_shows_no_line_of_the_previous_participant(
    room_server: RoomServer,
    lab: drive.RoomLab,
    context_of: Callable[..., BrowserContext],
    artifacts: Path,
) -> None:
    console = _console(room_server, lab, context_of)
    page = context_of(viewport=DESKTOP).new_page()
    drive.open_room(page, lab)
    lab.start_session()
    lab.wizard_prompt("conation")
    question = drive.wait_question(page, "conation")
    expect(console.locator("#room-panel .utterance")).to_contain_text(question)
    lab.end_session()

    lab.seat(room_server.database, STUDY, lab.code.replace("R", "S"))  # the next participant
    expect(console.locator("#room-panel .room-facts")).to_be_visible()  # where they stand
    expect(console.locator("#room-panel .utterance")).to_have_text("nothing said yet")
    console.screenshot(path=str(artifacts / "01-console-next-participant.png"), full_page=True)


@pytest.mark.e2e
def test_spoken_answers_count_only_when_clear_and_the_console_follows_the_room(
    room_server: RoomServer,
    context_of: Callable[..., BrowserContext],
    artifacts: Path,
) -> None:
    """The browser's own recogniser, in a study that allows a cloud recogniser."""
    lab = _seat(room_server, CLOUD_STUDY)
    database = room_server.database
    console = _console(room_server, lab, context_of)
    expect(console.locator("#room-panel")).to_contain_text("No room client has reported yet")

    context = context_of(viewport=DESKTOP)
    context.add_init_script(drive.FAKE_SPEECH)
    page = context.new_page()
    drive.open_room(page, lab)
    page.wait_for_function("() => window.trustlabRoom.listener === 'browser'")
    heard = page.evaluate(
        """async ([heard, swedish, phrases, hindi, hindiPhrases]) => {
            const speech = await import('/static/js/room/speech.js');
            return [
                heard.map((words) => speech.classifyAnswer(words)),
                swedish.map((words) => speech.classifyAnswer(words, phrases)),
                hindi.map((words) => speech.classifyAnswer(words, hindiPhrases)),
            ];
        }""",
        [
            list(CLASSIFIED),
            list(CLASSIFIED_SV),
            SWEDISH_PHRASES,
            list(CLASSIFIED_HI),
            HINDI_PHRASES,
        ],
    )
    assert dict(zip(CLASSIFIED, heard[0], strict=True)) == CLASSIFIED
    assert dict(zip(CLASSIFIED_SV, heard[1], strict=True)) == CLASSIFIED_SV
    assert dict(zip(CLASSIFIED_HI, heard[2], strict=True)) == CLASSIFIED_HI

    lab.start_session()
    page.evaluate("() => { window.__heard.push(['maybe', 0.95], ['yeah sure', 0.3]); }")
    page.evaluate("() => { window.__heard.push(['Yeah, sure.', 0.92]); }")
    drive.walk(page, drive.TO_CONATION)
    # Not just "no question": the walk may end before the zone's question has even arrived.
    drive.wait_reply(page)
    stored = _answers_for(database, lab.code, "conation")
    assert len(stored) == 1
    assert (stored[0].answer, stored[0].modality, stored[0].transcript) == (
        True,
        "speech",
        "Yeah, sure.",
    )
    assert stored[0].transcript_confidence == pytest.approx(0.92)
    assert stored[0].transcript_engine == "browser"

    # The console's room panel follows without a reload: zone, position and the last line.
    expect(console.locator("#room-panel .room-facts")).to_contain_text("Zoneconation")
    expect(console.locator("#room-panel .utterance")).to_contain_text("Robot replies")
    console.screenshot(path=str(artifacts / "01-console-room-panel.png"), full_page=True)

    lab.revoke_keys()  # the room closes with a clear message, and forgets the key
    expect(page.locator("#notice")).to_contain_text("revoked")
    expect(page.get_by_label(f"Device key of station {lab.station}")).to_be_visible()
    assert page.evaluate(f"() => localStorage.getItem('trustlab.room.key.{lab.station}')") is None
    page.screenshot(path=str(artifacts / "02-revoked.png"))


CLASSIFIED = {
    "yes": "yes",
    "Yeah, sure.": "yes",
    "of course": "yes",
    "no": "no",
    "nope": "no",
    "no, not really": "no",
    "I don't think so": "no",
    "yes no": None,
    "I don't know": None,
    "maybe": None,
    "the second key": None,
    "": None,
}
"""What a recogniser may hear, and what the room takes it for (None: it asks again)."""

SWEDISH_PHRASES = {
    "yes": ["ja", "javisst", "absolut"],
    "no": ["nej", "nä", "nej tack"],
    "english": False,
}
"""A protocol's phrases for a Swedish participant, as the room passes them to the recogniser."""
CLASSIFIED_SV = {
    "Ja": "yes",
    "Ja, absolut!": "yes",
    "javisst": "yes",
    "Nej tack.": "no",
    "nä": "no",
    "ja nej": None,
    "jaså": None,  # a word that begins like "ja" is not "ja"
    "yes": None,  # the built-in English words are for English speakers
    "jag vet inte": None,
}
"""What a Swedish participant's recogniser may hear, and what the room takes it for."""

HINDI_PHRASES = {"yes": ["हाँ", "जी हाँ"], "no": ["नहीं", "जी नहीं"], "english": False}
"""A script whose vowel signs are combining marks: dropping them made "हूँ" ("am") read as "हाँ"."""
CLASSIFIED_HI = {
    "हाँ": "yes",
    "जी हाँ": "yes",
    "नहीं": "no",
    "मैं ठीक हूँ": None,  # "I am fine": "हूँ" is not "हाँ"
    "नहीं, मैं तैयार नहीं हूँ": "no",
}


WALKING_RULES = """async () => {
  const walk = await import('/static/js/room/walk.js');
  const layout = {
    width: 8, depth: 6,
    start: { x: 1.35, z: 0.9, radius: 0.6 }, exit: { x: 6.65, z: 5.1, radius: 0.6 },
    walls: [{ x1: 2.7, z1: 0, x2: 2.7, z2: 4 }],
    zones: [{ category: 'conation', x: 1.92, z: 5.0, radius: 0.7 }],
  };
  const walls = walk.wallSegments(layout);
  let east = { x: 1.35, z: 2.0, heading: 90 };  // towards the inner wall at x = 2.7
  for (let i = 0; i < 100; i += 1) east = walk.step(layout, walls, east, { forward: 1 }, 0.05);
  let slide = { x: 1.35, z: 2.0, heading: 60 };  // at an angle: slides along it to its end
  for (let i = 0; i < 100; i += 1) slide = walk.step(layout, walls, slide, { forward: 1 }, 0.05);
  let burst = { x: 1.35, z: 2.0, heading: 90 };  // one stalled 10-second frame: no tunnelling
  burst = walk.step(layout, walls, burst, { forward: 1 }, 10);
  const turned = walk.step(layout, walls, { x: 1, z: 1, heading: 350 }, { turn: 1 }, 0.1);
  const headset = walk.poseFromHeadset(layout, { x: 0.5, y: 1.6, z: -2 }, { x: 1, y: 0, z: 0 });
  return {
    east_x: east.x, slide_x: slide.x, slide_z: slide.z, burst_x: burst.x, turned: turned.heading,
    in_zone: walk.zoneAt(layout, 1.5, 5.2)?.category ?? null,
    outside: walk.zoneAt(layout, 1.0, 3.0),
    headset,
  };
}"""


@pytest.mark.e2e
def test_walking_rules(room_server: RoomServer, context_of: Callable[..., BrowserContext]) -> None:
    page = context_of().new_page()
    page.goto(f"{room_server.url}/stations/room-rules/room")
    expect(page.get_by_label("Device key of station room-rules")).to_be_visible()
    found = page.evaluate(WALKING_RULES)
    clearance = 0.25 + 0.12 / 2  # body radius + half the wall's thickness
    assert found["east_x"] == pytest.approx(2.7 - clearance, abs=1e-6)  # stopped by the wall
    assert found["slide_x"] > 2.7 and found["slide_z"] > 4.0  # slid along it and round its end
    assert found["burst_x"] < 2.7  # a long frame still does not pass through
    assert found["turned"] == pytest.approx(1.0)  # 350° + 11° wraps to 1°
    assert found["in_zone"] == "conation" and found["outside"] is None
    assert found["headset"] == {"x": 1.85, "z": 2.9, "heading": 90}  # 2 m ahead, 0.5 m right


@pytest.mark.e2e
def test_a_key_of_another_station_is_refused_and_forgotten(
    room_server: RoomServer, lab: drive.RoomLab, context_of: Callable[..., BrowserContext]
) -> None:
    page = context_of(viewport=DESKTOP).new_page()
    # The room's description is held back until the station's hello has refused the key: it
    # arrives last, as it may on a busy server, and must not draw the other station's room.
    held: list[Route] = []
    page.route("**/api/v1/station/room", lambda route: held.append(route))
    page.goto(f"{room_server.url}/stations/elsewhere/room")
    page.get_by_label("Device key of station elsewhere").fill(lab.key)
    page.get_by_role("button", name="Open the room").click()
    expect(page.locator("#notice")).to_contain_text(f"It belongs to station {lab.station}")
    expect(page.get_by_label("Device key of station elsewhere")).to_be_visible()
    assert page.evaluate("() => localStorage.getItem('trustlab.room.key.elsewhere')") is None
    while not held:  # the route's callback runs when Playwright next hears from the browser
        page.wait_for_timeout(20)
    held[0].fulfill(response=held[0].fetch())
    page.wait_for_function("() => !window.trustlabRoom.loading")
    assert page.locator("#view canvas").count() == 0  # its room is not drawn here
    expect(page.locator("#notice")).to_contain_text(f"It belongs to station {lab.station}")


@pytest.fixture(scope="module")
def spoken_yes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A WAV of "yes" (espeak-ng) between pauses, for Chromium's fake microphone to loop."""
    if shutil.which("espeak-ng") is None:
        pytest.fail("espeak-ng is missing: install Debian's espeak-ng (.ci/run does)")
    said = subprocess.run(
        ["espeak-ng", "-v", "en-us", "-s", "150", "--stdout"],
        input=b"yes",
        capture_output=True,
        timeout=30,
        check=True,
    ).stdout
    pause = bytes(16000 * 2)  # 1 s
    path = tmp_path_factory.mktemp("microphone") / "yes.wav"
    path.write_bytes(as_wav(pause + decode_wav(with_true_sizes(said)) + pause))
    return path


@pytest.fixture(scope="module")
def browser_with_microphone(playwright: Playwright, spoken_yes: Path) -> Iterator[Browser]:
    """Chromium whose microphone says "yes" over and over, granted without a prompt."""
    chromium = launch_chromium(
        playwright,
        "--use-fake-ui-for-media-stream",
        "--use-fake-device-for-media-stream",
        f"--use-file-for-fake-audio-capture={spoken_yes}",
        "--autoplay-policy=no-user-gesture-required",
    )
    yield chromium
    chromium.close()


@pytest.mark.e2e
@pytest.mark.timeout(240)
def test_a_spoken_yes_is_recognised_offline_on_the_server(
    room_server: RoomServer, lab: drive.RoomLab, browser_with_microphone: Browser, artifacts: Path
) -> None:
    """No cloud recogniser allowed (the shipped protocol): the room streams its microphone to
    the server, whose offline recogniser hears the yes; it is stored once, with modality speech,
    and the room says the reply. Headless Chromium has no voices: the room plays the server's
    synthesised question (the audio endpoint is asked for it)."""
    context = browser_with_microphone.new_context(viewport=DESKTOP)
    try:
        page = context.new_page()
        spoken_lines: list[str] = []
        page.on(
            "request",
            lambda request: (
                "/api/v1/station/speech/audio" in request.url and spoken_lines.append(request.url)
            ),
        )
        drive.open_room(page, lab)
        page.wait_for_function("() => window.trustlabRoom.listener === 'server'")
        lab.start_session()
        drive.walk(page, drive.TO_CONATION)
        drive.wait_question(page, "conation")
        # Checked on every frame: the indicator shows only until the server has heard the yes,
        # which may be shorter than expect()'s polling interval (a second, by then).
        page.wait_for_function(
            "() => document.getElementById('listening')"
            ".checkVisibility({ visibilityProperty: true })",
            timeout=60_000,
        )
        page.screenshot(path=str(artifacts / "01-listening.png"))
        drive.wait_reply(page, timeout=120_000)
        page.screenshot(path=str(artifacts / "02-replied.png"))
        stored = _answers_for(room_server.database, lab.code, "conation")
        assert len(stored) == 1
        assert (stored[0].answer, stored[0].modality, stored[0].transcript) == (
            True,
            "speech",
            "yes",
        )
        assert (stored[0].transcript_engine or "").startswith("whisper tiny.en")
        assert spoken_lines  # the question came from the server's voice
    finally:
        context.close()
