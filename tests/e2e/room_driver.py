"""Driving the browser escape room as a participant would: by the keyboard, in real Chromium.

Shared by tests/e2e/test_room.py and bench/room.py. The walker steers in a closed loop (read the
pose the page shows, turn towards the next waypoint, walk, look again), so it arrives however
fast or slow the machine draws frames; it never relies on a key held for an exact time.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Iterable
from dataclasses import dataclass

import httpx
from playwright.sync_api import Page

from app.db import Database
from app.protocol import default_protocol
from app.services.audit import Actor
from app.services.participants import enrolment
from app.services.sessions import stations
from app.tables import Role
from tests.conftest import PASSWORD, give_pre_study, make_user

SYSTEM = Actor.system("room-e2e")
WALK_SPEED = 1.4
TURN_SPEED = 110.0
"""Metres and degrees a second, as static/js/room/walk.js moves (the walker stops a little short
of each target and looks again, so a slow or fast frame never carries it past)."""
START = (1.35, 0.9)
"""The shipped layout's start circle, where the exit sends the participant back to."""
ARRIVED = 0.15
"""Metres from a waypoint that count as there."""
TURN_TOLERANCE = 4.0
"""Degrees off the waypoint's bearing that still walk straight on."""

# The shipped layout's corridors (app/room.py, DEFAULT_PATH): waypoints along their middles.
TO_CONATION = [(1.35, 3.0), (1.5, 5.0)]
TO_AFFECTION_FROM_CONATION = [(3.4, 5.0), (4.0, 3.0)]
TO_COGNITION_FROM_AFFECTION = [(4.0, 1.0), (6.08, 1.0)]
TO_EXIT_FROM_COGNITION = [(6.65, 1.0), (6.65, 5.1)]
PAPER_ORDER = [
    ("conation", TO_CONATION),
    ("affection", TO_AFFECTION_FROM_CONATION),
    ("cognition", TO_COGNITION_FROM_AFFECTION),
]
"""Walking the S-shaped maze from the start: each category's zone in turn along the path."""
AFFECTION_FIRST = [
    ("affection", [(1.0, 3.0), (2.5, 4.3), (3.2, 4.4), (4.0, 3.0)]),  # round the conation zone
    ("conation", [(3.4, 5.0), (1.8, 5.0)]),
    ("cognition", [(3.4, 5.0), (4.0, 1.0), (6.08, 1.0)]),
]
"""Another order a participant may choose: past the conation zone's edge to affection first."""


def preferred_questions() -> dict[str, str]:
    """The question the paper's rules make right in each category of the shipped protocol."""
    protocol = default_protocol().protocol
    return {
        c.name: c.questions[c.preferred] for c in protocol.categories if c.preferred is not None
    }


@dataclass
class RoomLab:
    """A station with a device key and a participant past the pre-study questionnaires, seated
    there; an experimenter's HTTP client starts the sessions."""

    url: str
    admin: str
    station: str
    key: str
    code: str
    experimenter: httpx.Client

    def start_session(self) -> None:
        started = self.experimenter.post(f"/api/v1/stations/{self.station}/sessions")
        assert started.status_code == 201, started.text

    def end_session(self) -> None:
        ended = self.experimenter.post(f"/api/v1/stations/{self.station}/sessions/current/end")
        assert ended.status_code == 200, ended.text

    def wizard_prompt(self, category: str) -> int:
        """Trigger ``category`` from the console (Wizard-of-Oz); the step's id."""
        prompted = self.experimenter.post(
            f"/api/v1/stations/{self.station}/prompts", json={"category": category}
        )
        assert prompted.status_code == 201, prompted.text
        step_id: int = prompted.json()["step_id"]
        return step_id

    def wizard_answer(self, step_id: int, answer: str = "yes") -> str:
        """Record the participant's answer from the console (Wizard-of-Oz); the robot's reply."""
        answered = self.experimenter.post(
            f"/api/v1/stations/{self.station}/steps/{step_id}/answer",
            json={"answer": answer, "idempotency_key": uuid.uuid4().hex},
        )
        assert answered.status_code == 200, answered.text
        reply: str = answered.json()["reply"]
        return reply

    def seat(self, database: Database, study: str, code: str) -> None:
        """Enrol ``code`` in ``study`` and seat them here in the previous participant's place."""
        with database.writing() as db:
            enrolment.enroll_participant(db, study_name=study, actor=SYSTEM, code=code)
        seated = self.experimenter.put(
            f"/api/v1/stations/{self.station}/participant", json={"study": study, "code": code}
        )
        assert seated.status_code == 200, seated.text
        self.code = code

    def revoke_keys(self) -> None:
        listed = self.experimenter.get("/api/v1/stations").json()
        station = next(s for s in listed if s["name"] == self.station)
        for device in station["devices"]:
            revoked = self.experimenter.post(f"/api/v1/devices/{device['id']}/revoke")
            assert revoked.status_code == 200, revoked.text


def seat_participant(
    database: Database, url: str, study: str, *, station: str = "room-1", code: str = "R001"
) -> RoomLab:
    """Enrol ``code`` in ``study``, fill their pre-study questionnaires, seat them at ``station``
    (made, with a device key) and sign in an admin of its own (``admin-STATION``)."""
    with database.writing() as db:
        participant = enrolment.enroll_participant(
            db, study_name=study, actor=SYSTEM, code=code
        ).participant
    participant = give_pre_study(database, study=study, participant=participant, actor=SYSTEM)
    with database.writing() as db:
        stations.create_station(db, name=station, actor=SYSTEM)
    with database.writing() as db:
        key = stations.issue_device_key(db, station_name=station, label="room", actor=SYSTEM).key
    with database.writing() as db:
        stations.assign_participant(
            db, station_name=station, participant=db.merge(participant), actor=SYSTEM
        )
    admin = f"admin-{station}"
    make_user(database, admin, Role.ADMIN)
    experimenter = httpx.Client(base_url=url, timeout=30)
    signed_in = experimenter.post("/api/v1/session", json={"username": admin, "password": PASSWORD})
    experimenter.headers["X-CSRF-Token"] = signed_in.json()["csrf_token"]
    return RoomLab(
        url=url, admin=admin, station=station, key=key, code=code, experimenter=experimenter
    )


def open_room(page: Page, lab: RoomLab, *, query: str = "") -> None:
    """Open the station's room (``query``: its options, e.g. ``?scale=1``), enter the key and
    wait until it is connected and drawn."""
    page.goto(f"{lab.url}/stations/{lab.station}/room{query}")
    page.get_by_label(f"Device key of station {lab.station}").fill(lab.key)
    page.get_by_role("button", name="Open the room").click()
    wait_ready(page)


def wait_ready(page: Page) -> None:
    """Until the room is drawn and its WebSocket has said hello."""
    page.wait_for_function("() => window.trustlabRoom && window.trustlabRoom.ready")


def pose(page: Page) -> dict[str, float]:
    """The participant's pose as the page holds it."""
    value: dict[str, float] = page.evaluate("() => window.trustlabRoom.pose")
    return value


def _hold(page: Page, key: str, seconds: float) -> None:
    page.keyboard.down(key)
    page.wait_for_timeout(max(30, int(seconds * 1000)))
    page.keyboard.up(key)


def walk_to(
    page: Page, x: float, z: float, *, max_moves: int = 600, until_start: bool = False
) -> None:
    """Steer to (x, z) with the arrow keys: turn until facing it, walk a little, look again.
    ``until_start``: walking to the exit, which sends the participant back to the start circle
    once they step into it, so arriving there is arriving."""
    for _ in range(max_moves):
        here = pose(page)
        distance = math.hypot(x - here["x"], z - here["z"])
        if distance < ARRIVED or (until_start and _at_start(here)):
            return
        bearing = math.degrees(math.atan2(x - here["x"], z - here["z"])) % 360
        off = (bearing - here["heading"] + 540) % 360 - 180
        if abs(off) > TURN_TOLERANCE:
            _hold(page, "ArrowRight" if off > 0 else "ArrowLeft", 0.85 * abs(off) / TURN_SPEED)
        else:
            _hold(page, "ArrowUp", min(0.85 * distance / WALK_SPEED, 1.5))
    raise AssertionError(f"did not reach ({x}, {z}); stopped at {pose(page)}")


def face(page: Page, heading: float) -> None:
    """Turn on the spot until facing ``heading`` (degrees, 0 = the far wall)."""
    for _ in range(100):
        off = (heading - pose(page)["heading"] + 540) % 360 - 180
        if abs(off) <= TURN_TOLERANCE:
            return
        _hold(page, "ArrowRight" if off > 0 else "ArrowLeft", 0.85 * abs(off) / TURN_SPEED)
    raise AssertionError(f"did not turn to {heading}: {pose(page)}")


def _at_start(here: dict[str, float]) -> bool:
    return math.hypot(here["x"] - START[0], here["z"] - START[1]) < 0.01 and here["heading"] == 0


def walk_out(page: Page) -> None:
    """From the cognition zone's corridor out through the exit, back to the start (the room
    sends the participant back once its state says the run is complete: after the last reply,
    that state may still be on its way when the walker reaches the exit, so wait for it)."""
    walk_to(page, *TO_EXIT_FROM_COGNITION[0])
    walk_to(page, *TO_EXIT_FROM_COGNITION[1], until_start=True)
    page.wait_for_function(
        """([x, z]) => {
             const p = window.trustlabRoom.pose;
             return Math.hypot(p.x - x, p.z - z) < 0.01 && p.heading === 0;
           }""",
        arg=list(START),
    )


def walk(page: Page, waypoints: Iterable[tuple[float, float]]) -> None:
    """Walk through each waypoint in turn."""
    for x, z in waypoints:
        walk_to(page, x, z)


def wait_question(page: Page, category: str) -> str:
    """The text of the question the robot asks for ``category`` (once its caption shows)."""
    page.wait_for_function(
        "(c) => { const q = window.trustlabRoom.question; return q && q.category === c; }",
        arg=category,
    )
    text: str = page.evaluate("() => window.trustlabRoom.question.question")
    return text


def answer_by_rules(
    page: Page, category: str, question: str, *, how: str = "key", then_leaves: bool = False
) -> str:
    """Answer as the paper's rules say (yes to the preferred question, no to the others), by the
    Y/N keys or the on-screen buttons; waits until the robot's reply is shown, unless
    ``then_leaves``: an online room leaves for the next page after a session's last reply, and
    the caller waits for that page instead."""
    said = "yes" if preferred_questions()[category] == question else "no"
    if how == "key":
        page.keyboard.press("KeyY" if said == "yes" else "KeyN")
    else:
        page.get_by_role("button", name="Yes" if said == "yes" else "No").click()
    if not then_leaves:
        wait_reply(page)
    return said


def wait_reply(page: Page, *, timeout: float | None = None) -> None:
    """Until the question is closed and the robot's reply to its answer is said (the answer is
    stored by then: the server replies after it commits). Its caption may be gone already: the
    card that follows a session's last answer clears it."""
    page.wait_for_function(
        "() => !window.trustlabRoom.question && (window.trustlabRoom.said || {}).kind === 'reply'",
        timeout=timeout,
    )


def session_running(page: Page) -> bool:
    """Whether the room's state has a running session, once it knows the run is over."""
    page.wait_for_function("() => window.trustlabRoom.state.run.status === 'completed'")
    running: bool = page.evaluate("() => window.trustlabRoom.state.session.status === 'running'")
    return running


def run_through(
    page: Page, order: list[tuple[str, list[tuple[float, float]]]], *, how: str = "key"
) -> list[str]:
    """One run: each category's zone in ``order``, answered by the rules, then out at the exit
    (which takes the participant back to the start) when another run of the session follows.
    Returns the categories in the order asked."""
    asked = []
    for category, waypoints in order:
        walk(page, waypoints)
        question = wait_question(page, category)
        answer_by_rules(page, category, question, how=how)
        asked.append(category)
    if session_running(page):
        walk_out(page)
    return asked


FAKE_SPEECH = """
window.__heard = [];
class FakeRecognition {
  start() {
    const next = window.__heard.shift();
    setTimeout(() => {
      if (!next) { this.onend && this.onend(); return; }
      const result = [{ transcript: next[0], confidence: next[1] }];
      this.onresult && this.onresult({ results: [result] });
    }, 20);
  }
  abort() {}
}
window.SpeechRecognition = FakeRecognition;
window.webkitSpeechRecognition = FakeRecognition;
window.speechSynthesis = { speak(u) { setTimeout(() => u.onend && u.onend(), 5); }, cancel() {} };
"""
"""A browser recogniser and voice for a page's init script: the recogniser hears the next of
window.__heard ([transcript, confidence] pairs), or silence when it is empty."""
