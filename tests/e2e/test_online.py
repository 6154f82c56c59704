"""An online participant in real Chromium: from a (fake) recruitment platform's link through the
browser check, consent, the questionnaires and a session in the room to the platform's
completion URL, with a reload mid-session and a return in a new browser after closing the tab."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from playwright.sync_api import Browser, Page, expect
from sqlalchemy import select

from app.db import Database
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.tables import Answer, OnlineParticipation, OnlineStatus, Participant, Submission
from tests.app.test_online_join import online_protocol
from tests.e2e.room_driver import PAPER_ORDER, answer_by_rules, wait_question, wait_ready, walk
from tests.servers import ServerProcess

PID = "5f0c1d2e3a4b5c6d7e8f9a0b"
AS_IT_LEAVES = """() => addEventListener("beforeunload", () => {
  const room = window.trustlabRoom;
  const left = { said: room.said && room.said.kind, saying: room.saying };
  sessionStorage.setItem("test:left", JSON.stringify(left));
})"""
"""Keep what the room was saying as the page is left (the next page of the tab reads it)."""
ONE_SESSION = {
    "sessions = 4": "sessions = 1",
    "runs_per_session = 3": "runs_per_session = 1",
    "familiarisation_run = true": "familiarisation_run = false",
}


class FakePlatform:
    """A recruitment platform on loopback: a study page linking to trustlab, and the
    completion page participants are sent back to."""

    def __init__(self, join_url: str) -> None:
        platform = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                if self.path.startswith("/complete"):
                    platform.completions.append(self.path)
                    body = f"<h1>Submission complete: {self.path}</h1>"
                else:
                    link = f"{join_url}?PROLIFIC_PID={PID}&STUDY_ID=st1&SESSION_ID=se1"
                    body = f'<a id="take-part" href="{link}">Open study in a new window</a>'
                data = body.encode()
                self.send_response(200)
                self.send_header("Content-Type", "text/html; charset=utf-8")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def log_message(self, *_args: object) -> None:
                pass

        self.completions: list[str] = []
        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def platform(live_server: ServerProcess) -> Iterator[FakePlatform]:
    fake = FakePlatform(f"{live_server.url}/join/web")
    yield fake
    fake.close()


@pytest.fixture
def web_study(database: Database, platform: FakePlatform) -> str:
    text = online_protocol(**ONE_SESSION).replace(
        "https://app.prolific.com/submissions/complete?cc={code}",
        f"{platform.url}/complete?cc={{code}}",
    )
    with database.writing() as db:
        studies.create_study(db, name="web", loaded=parse_protocol(text), actor=Actor.system())
    return "web"


def _likert(page: Page, name: str, value: int) -> None:
    page.locator(f'input[name="{name}"][value="{value}"]').check()


def _pre_study(page: Page, url: str) -> None:
    page.get_by_label("I have read the text above and I agree to take part.").check()
    page.get_by_role("button", name="Continue").click()
    expect(page).to_have_url(f"{url}/tablet/q/demographics")
    page.get_by_label("1. How old are you (in years)?").fill("29")
    page.get_by_label("Prefer not to say").check()
    page.get_by_role("button", name="Continue").click()
    for instrument, names in (
        ("background", ["bg_robot_experience", "bg_vr_familiarity", "bg_digital_skills"]),
        ("tipi", [f"tipi_{n}" for n in range(1, 11)]),
        ("nars", [f"nars_{n}" for n in range(1, 15)]),
    ):
        expect(page).to_have_url(f"{url}/tablet/q/{instrument}")
        for name in names:
            _likert(page, name, 3)
        if instrument == "nars":
            _look_away(page)
        page.get_by_role("button", name="Continue").click()


def _look_away(page: Page) -> None:
    """Another tab in front for a moment (at least 50 ms of it), then this one again."""
    hide = """(hidden) => {
        Object.defineProperty(document, "hidden", { configurable: true, get: () => hidden });
        document.dispatchEvent(new Event("visibilitychange"));
    }"""
    page.evaluate(hide, True)
    page.wait_for_timeout(50)  # a lower bound on the time away, not a race
    page.evaluate(hide, False)


def _join(page: Page, platform: FakePlatform, url: str) -> None:
    page.goto(f"{platform.url}/study")
    page.locator("#take-part").click()
    expect(page).to_have_url(f"{url}/join/web?PROLIFIC_PID={PID}&STUDY_ID=st1&SESSION_ID=se1")
    expect(page.get_by_text("Press the space bar to begin.")).to_be_visible()
    page.keyboard.press("Space")


@pytest.mark.e2e
def test_an_online_participant_goes_from_the_platform_and_back(
    browser: Browser,
    live_server: ServerProcess,
    database: Database,
    web_study: str,
    platform: FakePlatform,
    artifacts: Path,
) -> None:
    url = live_server.url
    context = browser.new_context(viewport={"width": 1366, "height": 768})
    page = context.new_page()
    _join(page, platform, url)
    expect(page).to_have_url(f"{url}/tablet/consent")
    page.screenshot(path=str(artifacts / "01-consent.png"))
    _pre_study(page, url)

    # The room, in the same tab: the participant starts the session when ready.
    expect(page).to_have_url(f"{url}/online")
    start = page.get_by_role("button", name="I am ready: start")
    expect(start).to_be_visible()
    page.screenshot(path=str(artifacts / "02-room-ready.png"))
    _look_away(page)  # the room's beacon reports it
    start.click()
    wait_ready(page)
    page.wait_for_function("() => window.trustlabRoom.state.expected.action === 'prompt'")
    (first, way), *rest = PAPER_ORDER
    walk(page, way)
    answer_by_rules(page, first, wait_question(page, first))
    page.reload()  # mid-session: the room comes back where it was, nothing asked twice
    wait_ready(page)
    for category, waypoints in rest[:-1]:
        walk(page, waypoints)
        answer_by_rules(page, category, wait_question(page, category))
    # The session's last answer: the room hands over to the session's questionnaire, once the
    # robot has said its reply (what the room was doing as it left is kept in the tab's
    # session storage, which the next page of the same tab still reads).
    page.evaluate(AS_IT_LEAVES)
    category, waypoints = rest[-1]
    walk(page, waypoints)
    answer_by_rules(page, category, wait_question(page, category), then_leaves=True)
    expect(page).to_have_url(f"{url}/tablet/q/trust/1")
    left = json.loads(page.evaluate("() => sessionStorage.getItem('test:left')"))
    assert left == {"said": "reply", "saying": False}
    page.screenshot(path=str(artifacts / "03-trust.png"))
    context.close()  # the participant closes the tab

    # They come back from the platform in a new browser: the same participation, where they were.
    context = browser.new_context(viewport={"width": 1366, "height": 768})
    page = context.new_page()
    _join(page, platform, url)
    expect(page).to_have_url(f"{url}/tablet/q/trust/1")
    for n in range(1, 6):
        _likert(page, f"trust_{n}", 4)
    page.get_by_role("button", name="Continue").click()
    expect(page).to_have_url(f"{url}/tablet/q/overall")
    _likert(page, "overall_experience", 5)
    _likert(page, "interaction_quality", 4)
    page.get_by_role("button", name="Continue").click()
    expect(page.get_by_text("Your completion code is C1ABC2.")).to_be_visible()
    page.screenshot(path=str(artifacts / "04-complete.png"))
    expect(page).to_have_url(f"{platform.url}/complete?cc=C1ABC2")  # the redirect, by itself
    context.close()

    assert platform.completions == ["/complete?cc=C1ABC2"]
    with database.read_session() as db:
        assert len(db.scalars(select(Participant)).all()) == 1
        participation = db.scalar(select(OnlineParticipation))
        assert participation is not None and participation.status == OnlineStatus.COMPLETED
        assert participation.flags == {}  # one ID, even from a second browser
        assert len(db.scalars(select(Answer)).all()) == 3
        # the pages timed themselves, and the time away of a questionnaire page and the room
        # reached the server
        timed = {row.instrument: row for row in db.scalars(select(Submission))}
        assert all(timed[key].seconds_on_page for key in ("demographics", "nars", "trust"))
        assert (timed["nars"].seconds_away or 0) >= 0.05
        assert (timed["tipi"].seconds_away or 0) == 0
        assert participation.room_seconds_away >= 0.05
