"""Every participant change × every view that shows the participant: each change, applied through
each service that applies it, reaches the topic of every view showing them (issue 48, class A).

The views' topics are taken from the code the views listen with: the study's pages and dashboard
stream the study topic (app.web.live), the console the station topic (app.web.live), the room and
the robots the station topic (app.api.station_ws), a tablet the topics its link resolves to
(app.tablet.Tablet.topics), personal and kiosk alike. A change added to
app.services.participants.participant_changes.Change fails here until an entry point below applies
it and it reaches them all.
"""

from __future__ import annotations

import asyncio
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import timedelta
from importlib import resources

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from app import events
from app.db import Database
from app.events import RESYNC, Event
from app.protocol import parse_protocol
from app.services import studies, topics
from app.services.audit import Actor
from app.services.participants import enrolment, languages, questionnaires, tablet_tokens
from app.services.participants.participant_changes import Change
from app.services.privacy import consent, erasure, retention
from app.services.sessions import stations
from app.settings import REPO_ROOT
from app.tables import AuditEvent, Participant, StudyStatus, utcnow
from app.tablet import resolve
from tests.conftest import EXP3_ONLY, Lab

SYSTEM = Actor.system("lifecycle")
SECRET = b"participant-changes-test-secret"
STUDY = "life"
STATION = "lab-1"
CODE = "P001"


@dataclass
class World:
    """A Swedish participant with a tablet link, seated at a station with a kiosk link."""

    database: Database
    study_id: int = 0
    station_id: int = 0
    personal: str = ""
    kiosk: str = ""


def _protocol(then: str) -> str:
    text = resources.files("app.protocols").joinpath("fast_adaptation_trust_sv.toml").read_text()
    retention_section = f'[retention]\nidentifiable_for = "1 year"\nthen = "{then}"\n\n'
    for old, new in {**EXP3_ONLY, "[allocation]": retention_section + "[allocation]"}.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


def _participant(db: Session) -> Participant:
    return enrolment.get_participant(db, studies.get_study(db, STUDY), CODE, actor=SYSTEM)


def build_world(database: Database, *, then: str = "anonymise") -> World:
    """The study, the participant (consented, in Swedish), their link, the station and its kiosk."""
    world = World(database)
    with database.writing() as db:
        study = studies.create_study(
            db, name=STUDY, loaded=parse_protocol(_protocol(then)), actor=SYSTEM
        )
        world.study_id = study.id
    with database.writing() as db:
        participant = enrolment.enroll_participant(
            db, study_name=STUDY, actor=SYSTEM, code=CODE, language="sv"
        ).participant
    with database.writing() as db:
        world.personal = tablet_tokens.issue_participant_token(
            db, participant=db.merge(participant), secret=SECRET, actor=SYSTEM
        )
    with database.writing() as db:
        participant = _participant(db)
        protocol = languages.protocol_for("sv", studies.protocol_of(studies.get_study(db, STUDY)))
        questionnaires.accept_consent(
            db, participant=participant, protocol=protocol, accepted=True, actor=SYSTEM
        )
    with database.writing() as db:
        station = stations.create_station(db, name=STATION, actor=SYSTEM)
        world.station_id = station.id
    with database.writing() as db:
        world.kiosk = tablet_tokens.issue_kiosk_token(
            db, station=stations.get_station(db, STATION), secret=SECRET, actor=SYSTEM
        )
    with database.writing() as db:
        stations.assign_participant(
            db, station_name=STATION, participant=_participant(db), actor=SYSTEM
        )
    return world


# ------------------------------------------------------------------------------------ views


def _tablet_topics(database: Database, token: str) -> list[str]:
    with database.read_session() as db:
        return resolve(db, token).topics()


VIEWS: dict[str, Callable[[World], list[str]]] = {
    "study pages": lambda w: [topics.study_topic(w.study_id)],
    "dashboard": lambda w: [topics.study_topic(w.study_id)],
    "console": lambda w: [topics.station_topic_of(w.station_id)],
    "room": lambda w: [topics.station_topic_of(w.station_id)],
    "robot": lambda w: [topics.station_topic_of(w.station_id)],
    "tablet": lambda w: _tablet_topics(w.database, w.personal),
    "kiosk tablet": lambda w: _tablet_topics(w.database, w.kiosk),
}
"""Each view showing a seated participant, and the topics it listens to (read before the change:
a kiosk shows whoever sits there until the change moves them)."""
NOT_YET_SHOWN = {"console", "room", "robot", "tablet", "kiosk tablet"}
"""What does not show a participant being enrolled: nobody has seated them or opened their link."""


# ---------------------------------------------------------------------------- entry points


def _unseat(world: World) -> None:
    with world.database.writing() as db:
        stations.unassign(db, station_name=STATION, actor=SYSTEM)


def _lock(world: World) -> None:
    with world.database.writing() as db:
        questionnaires.set_locked(db, participant=_participant(db), locked=True, actor=SYSTEM)


def _new_consent_text(world: World) -> None:
    with world.database.writing() as db:
        consent.add_version(
            db,
            study_name=STUDY,
            texts={"en": "The second version of the text.", "sv": "Textens andra version."},
            actor=SYSTEM,
        )


def _answer_consent(accepted: bool) -> Callable[[World], None]:
    def act(world: World) -> None:
        with world.database.writing() as db:
            participant = _participant(db)
            study = studies.get_study(db, STUDY)
            protocol = languages.protocol_for(participant.language, studies.protocol_of(study))
            if accepted:
                questionnaires.accept_consent(
                    db, participant=participant, protocol=protocol, accepted=True, actor=SYSTEM
                )
            else:
                questionnaires.decline_consent(
                    db, participant=participant, protocol=protocol, actor=SYSTEM
                )

    return act


def _retention_run(world: World) -> None:
    with world.database.writing() as db:
        studies.set_study_status(db, name=STUDY, status=StudyStatus.CLOSED, actor=SYSTEM)
    with world.database.writing() as db:
        retention.run(
            db, now=utcnow() + timedelta(days=800), actor=SYSTEM, secret=SECRET, dry_run=False
        )


def _enrol(world: World) -> None:
    with world.database.writing() as db:
        enrolment.enroll_participant(db, study_name=STUDY, actor=SYSTEM, code=CODE + "b")


def _seat(world: World) -> None:
    with world.database.writing() as db:
        stations.assign_participant(
            db, station_name=STATION, participant=_participant(db), actor=SYSTEM
        )


def _language(world: World) -> None:
    with world.database.writing() as db:
        participant = _participant(db)
        languages.set_language(
            db,
            participant=participant,
            protocol=studies.protocol_of(studies.get_study(db, STUDY)),
            study_name=STUDY,
            language="en",
            actor=SYSTEM,
        )


def _unlock(world: World) -> None:
    with world.database.writing() as db:
        questionnaires.set_locked(db, participant=_participant(db), locked=False, actor=SYSTEM)


def _withdraw(world: World) -> None:
    with world.database.writing() as db:
        enrolment.withdraw_participant(db, study_name=STUDY, code=CODE, actor=SYSTEM)


def _erase(world: World) -> None:
    with world.database.writing() as db:
        erasure.erase_participant(db, study_name=STUDY, code=CODE, actor=SYSTEM, secret=SECRET)


@dataclass(frozen=True)
class EntryPoint:
    """A service entry point applying a change: what it needs first, and the call itself."""

    name: str
    act: Callable[[World], None]
    prepare: Callable[[World], None] | None = None
    then: str = "anonymise"  # what the study's retention does
    shown_by: frozenset[str] = field(default_factory=lambda: frozenset(VIEWS))


ENROLMENT_VIEWS = frozenset(VIEWS) - NOT_YET_SHOWN
NOBODY_AT_THE_KIOSK = frozenset(VIEWS) - {"kiosk tablet"}
"""A kiosk with nobody seated shows a page that asks the experimenter to seat someone."""
ENTRY_POINTS: dict[Change, list[EntryPoint]] = {
    Change.ENROLLED: [EntryPoint("enrolment.enroll_participant", _enrol, shown_by=ENROLMENT_VIEWS)],
    Change.SEATED: [
        EntryPoint(
            "stations.assign_participant", _seat, prepare=_unseat, shown_by=NOBODY_AT_THE_KIOSK
        )
    ],
    Change.UNSEATED: [EntryPoint("stations.unassign", _unseat)],
    Change.LANGUAGE: [EntryPoint("languages.set_language", _language)],
    Change.LOCKED: [EntryPoint("questionnaires.set_locked(True)", _lock)],
    Change.UNLOCKED: [EntryPoint("questionnaires.set_locked(False)", _unlock, prepare=_lock)],
    Change.WITHDRAWN: [EntryPoint("enrolment.withdraw_participant", _withdraw)],
    Change.ERASED: [
        EntryPoint("erasure.erase_participant", _erase),
        EntryPoint("retention.run (erase)", _retention_run, then="erase"),
    ],
    Change.ANONYMISED: [EntryPoint("retention.run (anonymise)", _retention_run)],
    Change.RECONSENTED: [
        EntryPoint("questionnaires.accept_consent", _answer_consent(True), _new_consent_text)
    ],
    Change.CONSENT_DECLINED: [
        EntryPoint("questionnaires.decline_consent", _answer_consent(False), _new_consent_text)
    ],
}
"""Every service entry point that applies each change (a new one is listed here)."""
CASES = [(change, entry) for change, entries in ENTRY_POINTS.items() for entry in entries]


def test_every_change_has_its_entry_points_and_a_publisher() -> None:
    """A new kind of change is listed above, and some service publishes it."""
    assert set(ENTRY_POINTS) == set(Change)
    services = [
        path.read_text()
        for path in (REPO_ROOT / "app" / "services").rglob("*.py")
        if path.name != "participant_changes.py"
    ]
    for change in Change:
        assert any(re.search(rf"\bChange\.{change.name}\b", source) for source in services), (
            f"no service publishes Change.{change.name}"
        )


def test_the_tablet_script_knows_the_changes_that_end_its_link() -> None:
    """The tablet acts on an erasure and an anonymisation by their event types."""
    script = (REPO_ROOT / "static" / "js" / "tablet.js").read_text()
    for change in (Change.ERASED, Change.ANONYMISED):
        assert f'"{change.event_type}"' in script, change


def _heard(
    database: Database,
    topics: set[str],
    act: Callable[[], None],
    enough: Callable[[list[Event]], bool],
) -> list[Event]:
    """The events on ``topics`` while ``act`` runs in a thread (as a request would), until
    ``enough`` of them came (through a LISTEN connection on PostgreSQL); after the suite's 30 s
    ceiling, what came by then (the test then says what is missing). No quiet period decides
    it: a slow machine delays events, it does not lose them."""

    async def scenario() -> list[Event]:
        listener = None
        if not database.is_sqlite:
            listener = events.PostgresListener(database.url, database.hub)
            listener.start()
        received: list[Event] = []
        try:
            async with database.hub.subscribe(topics) as subscription:
                await asyncio.to_thread(act)
                deadline = time.monotonic() + 30
                while not enough(received):
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    try:
                        event = await asyncio.wait_for(subscription.next(), left)
                    except TimeoutError:
                        break
                    if event is not RESYNC:
                        received.append(event)
        finally:
            if listener is not None:
                listener.stop()
        return received

    return asyncio.run(scenario())


@pytest.mark.parametrize(("change", "entry"), CASES, ids=[e.name for _, e in CASES])
def test_a_change_reaches_every_view_of_the_participant(
    database: Database, change: Change, entry: EntryPoint
) -> None:
    world = build_world(database, then=entry.then)
    if entry.prepare is not None:
        entry.prepare(world)
    views = {name: VIEWS[name](world) for name in sorted(entry.shown_by)}

    def missed(heard: list[Event]) -> list[str]:
        return [
            name
            for name, topics in views.items()
            if not any(e.topic in topics and e.type == change.event_type for e in heard)
        ]

    heard = _heard(
        database,
        {t for topics in views.values() for t in topics},
        lambda: entry.act(world),
        enough=lambda got: not missed(got),
    )
    missed_views = missed(heard)
    assert missed_views == [], (
        f"{entry.name}: {change.event_type} never reached {missed_views}: {heard}"
    )
    announcing = [e for e in heard if e.type == change.event_type]
    assert all("site" in e.data for e in announcing)  # app.services.privacy.sites.reaches
    if change in (Change.ERASED, Change.ANONYMISED):  # the code is what they removed
        assert all(CODE not in str(e.data) for e in announcing), announcing


def test_a_withdrawal_mid_session_ends_it_and_the_station_shows_it(lab: Lab) -> None:
    """The room and the robots stop offering the session of someone who withdrew: it ends early
    with the withdrawal (audited with it); they stay seated, so an answer acknowledged before
    still replays, and the console offers to free the station."""
    code = lab.enrol_and_assign()
    lab.start_session()
    step = lab.prompt("conation")
    answered = {"answer": "yes", "idempotency_key": "before-withdrawal"}
    first = lab.robot.post(f"/api/v1/station/steps/{step['step_id']}/answer", json=answered)
    assert first.status_code == 200, first.text

    withdrawn = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants/{code}/withdraw", json={}
    )
    assert withdrawn.status_code == 200, withdrawn.text

    state = lab.robot.get("/api/v1/station").json()
    assert state["participant"] == code and state["expected"]["action"] == "none"
    assert state["session"]["status"] == "ended_early"
    assert state["run"]["status"] == "ended_early"
    replay = lab.robot.post(f"/api/v1/station/steps/{step['step_id']}/answer", json=answered)
    assert replay.status_code == 200 and replay.json()["reply"] == first.json()["reply"]
    with lab.database.read_session() as db:
        audited = db.scalars(
            select(AuditEvent).where(AuditEvent.action == "participant.withdrawn")
        ).one()
    assert audited.details["session_ended_early"] == state["session"]["number"]
    console = lab.experimenter.get(f"/stations/{lab.station}")
    assert "Free the station" in console.text and "End session early" not in console.text
