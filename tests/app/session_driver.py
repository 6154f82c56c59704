"""A robot, a tablet and an experimenter driving one participant through a whole study against a
real server process, retrying through crashes and outages with the same idempotency keys; and
the checks that afterwards nothing acknowledged was lost and nothing was applied twice."""

from __future__ import annotations

import random
import time
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import httpx
from sqlalchemy import select

from app.db import Database
from app.services.audit import Actor
from app.services.participants import enrolment, tablet_tokens
from app.services.sessions import stations, verify
from app.tables import Answer, LearnerState, Prompt, Role, Submission
from tests.conftest import (
    PASSWORD,
    POST_ANSWERS,
    PRE_STUDY_ANSWERS,
    TRUST_ANSWERS,
    make_user,
)
from tests.servers import ServerProcess

SERVER_SECRET = b"subprocess-test-secret-0123456789abcdef"
"""The secret tests.servers.ServerProcess gives its servers (tablet tokens are derived from it)."""


RETRYABLE = (httpx.TransportError, httpx.TimeoutException)


@dataclass(frozen=True)
class Acknowledged:
    """An answer the server confirmed with a 200."""

    step_id: int
    answer: bool
    reply: str


class Driver:
    """A robot plus an experimenter that retry through crashes with the same idempotency keys."""

    def __init__(self, server: ServerProcess, key: str, station: str, tablet_token: str) -> None:
        self.server = server
        self.station = station
        self.robot = httpx.Client(headers={"Authorization": f"Bearer {key}"}, timeout=5.0)
        self.tablet = httpx.Client(headers={"Authorization": f"Bearer {tablet_token}"}, timeout=5.0)
        self.experimenter = httpx.Client(timeout=5.0)
        self.acknowledged: list[Acknowledged] = []
        self.questionnaires: list[tuple[str, int | None]] = []
        self.retries = 0
        self.statuses: Counter[int] = Counter()
        self.sent = 0
        self.before_each_request: Callable[[int], None] = lambda sent: None

    def call(
        self, client: httpx.Client, method: str, path: str, body: object = None
    ) -> httpx.Response:
        while True:
            self.sent += 1
            self.before_each_request(self.sent)
            try:
                response = client.request(method, f"{self.server.url}{path}", json=body)
            except RETRYABLE:
                self.retries += 1
                time.sleep(0.05)
                continue
            self.statuses[response.status_code] += 1
            assert response.status_code < 500 or response.status_code == 503, (
                f"{method} {path}: {response.status_code} {response.text[:500]}"
            )
            if response.status_code == 503:
                self.retries += 1
                time.sleep(0.05)
                continue
            return response

    def sign_in(self, username: str) -> None:
        response = self.call(
            self.experimenter,
            "POST",
            "/api/v1/session",
            {"username": username, "password": PASSWORD},
        )
        assert response.status_code == 200, response.text
        self.experimenter.headers["X-CSRF-Token"] = response.json()["csrf_token"]

    def fill_tablet(self) -> None:
        """Do whatever the tablet asks: consent, then the questionnaire it shows."""
        page = self.call(self.tablet, "GET", "/api/v1/tablet").json()
        if page["kind"] == "consent":
            response = self.call(self.tablet, "POST", "/api/v1/tablet/consent", {"accept": True})
        elif page["kind"] == "questionnaire":
            key = page["instrument"]["key"]
            answers = {**PRE_STUDY_ANSWERS, "trust": TRUST_ANSWERS, "overall": POST_ANSWERS}[key]
            response = self.call(
                self.tablet,
                "POST",
                f"/api/v1/tablet/questionnaires/{key}",
                {"session": page["session"], "answers": answers},
            )
            if response.status_code == 200:
                self.questionnaires.append((key, page["session"]))
        else:
            return
        assert response.status_code == 200, response.text

    def run(self, rng: random.Random) -> None:
        while True:
            state = self.call(self.robot, "GET", "/api/v1/station").json()
            expected = state["expected"]
            if expected["action"] == "wait":
                self.fill_tablet()
                continue
            if expected["action"] == "done":
                while self.call(self.tablet, "GET", "/api/v1/tablet").json()["kind"] != "done":
                    self.fill_tablet()
                return
            if expected["action"] == "start_session":
                started = self.call(
                    self.experimenter, "POST", f"/api/v1/stations/{self.station}/sessions"
                )
                assert started.status_code in (201, 409), started.text
                continue
            if expected["action"] == "answer":
                step = state["open_prompts"][0]
            else:
                assert expected["action"] == "prompt", expected
                category = rng.choice(expected["categories"])
                response = self.call(
                    self.robot, "POST", "/api/v1/station/prompts", {"category": category}
                )
                assert response.status_code in (200, 201), response.text
                step = response.json()
            yes = step["action"] == 0
            key = uuid.uuid4().hex
            response = self.call(
                self.robot,
                "POST",
                f"/api/v1/station/steps/{step['step_id']}/answer",
                {"answer": "yes" if yes else "no", "idempotency_key": key},
            )
            assert response.status_code == 200, response.text
            self.acknowledged.append(Acknowledged(step["step_id"], yes, response.json()["reply"]))


@dataclass(frozen=True)
class Seated:
    """A participant seated at a station, with the credentials the driver needs."""

    station: str
    device_key: str
    tablet_token: str


def seat_participant(database: Database, study: str, station: str = "crash") -> Seated:
    """An admin ``operator``, a station with a robot key, and a new participant seated there."""
    make_user(database, "operator", Role.ADMIN)
    with database.writing() as db:
        stations.create_station(db, name=station, actor=Actor.system())
    with database.writing() as db:
        key = stations.issue_device_key(
            db, station_name=station, label="robot", actor=Actor.system()
        ).key
    with database.writing() as db:
        participant = enrolment.enroll_participant(db, study_name=study, actor=Actor.system())
    with database.writing() as db:
        stations.assign_participant(
            db, station_name=station, participant=participant.participant, actor=Actor.system()
        )
    with database.writing() as db:
        tablet_token = tablet_tokens.issue_participant_token(
            db,
            participant=db.merge(participant.participant),
            secret=SERVER_SECRET,
            actor=Actor.system(),
        )
    return Seated(station, key, tablet_token)


def assert_exactly_once(database: Database, study: str, driver: Driver) -> None:
    """Every acknowledged answer stored as acknowledged, each step answered once, learners at
    the right version, ``trustlab verify`` clean, every questionnaire kept."""
    with database.read_session() as db:
        answers = {a.prompt_id: a for a in db.scalars(select(Answer))}
        prompts = list(db.scalars(select(Prompt)))
        versions = {row.category: row.version for row in db.scalars(select(LearnerState))}
        report = verify.verify_study(db, study_name=study)
        submitted = set(db.execute(select(Submission.instrument, Submission.session)).all())
    for ack in driver.acknowledged:
        stored = answers[ack.step_id]
        assert (stored.answer, stored.reply) == (ack.answer, ack.reply)
    assert len(answers) == len(prompts) == 39  # every step answered once: 3 + 4 sessions x 9
    assert len({a.step_id for a in driver.acknowledged}) == 39
    assert versions == {"conation": 12, "affection": 12, "cognition": 12}
    assert report.ok, report.findings
    assert set(driver.questionnaires) <= submitted
    assert len(submitted) == 1 + 4 + 4 + 1  # consent, pre-study, 4 sessions, post-study
