"""An online participation from join to completion: what the server does where an experimenter
would in the lab.

:func:`join` is the only way in. It finds the recruitment ID's participation (a return, a reload,
a second tab) or, for a new ID whose browser passed the check, enrols a participant and gives them
a virtual station of their own, seated, with a derived device key (app.online.identity) and a
tablet link, all in the enrolment's own transaction: ``UNIQUE(study_id, recruitment_hash)`` makes
two joins with one ID at once end in one participation, the other finding it. From there the
participant's pages are the tablet's, and the room is the lab's room client on their station;
:func:`start_session` starts a session when they say they are ready, and the participation ends
as completed (the post-study questionnaires done), expired (the time limit passed) or ended (staff
withdrew or erased them). An ended participation's device key is revoked at once.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime, timedelta
from enum import StrEnum
from pathlib import Path

from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput, NotFound
from app.i18n.catalogues import Message
from app.online.identity import (
    browser_hash,
    check_recruitment_id,
    device_key,
    recruitment_hash,
)
from app.online.spec import DeviceKind, OnlineSpec
from app.protocol import SITE_FACTOR, Protocol
from app.randomisation import stratum_key
from app.security import token_digest
from app.services import audit
from app.services.audit import Actor
from app.services.participants import enrolment, participant_changes, tablet_tokens
from app.services.participants.participant_changes import Change
from app.services.sessions import runtime
from app.services.sessions.stations import ONLINE_STATIONS
from app.services.studies import get_study, protocol_of
from app.tables import (
    ActorKind,
    Allocation,
    Device,
    OnlineParticipation,
    OnlineStatus,
    Participant,
    ParticipantStatus,
    SessionStatus,
    Station,
    Study,
    StudyPhase,
    StudySession,
    StudyStatus,
    utcnow,
)

JOIN_ACTOR = Actor(ActorKind.SYSTEM, "online join")
"""Who enrols online participants, as the audit log names it."""
STATION_PREFIX = ONLINE_STATIONS
"""Online participants' stations are named ``online-<participant id>``; staff cannot create
stations with these names (app.services.sessions.stations)."""
PARAMETER_MAX = 200
"""A platform parameter's value is kept up to this many characters."""
ENROL_ATTEMPTS = 3


class Outcome(StrEnum):
    """What a join came to."""

    ENROLLED = "enrolled"
    RESUMED = "resumed"
    SCREENED_OUT = "screened_out"
    FULL = "full"
    CLOSED = "closed"
    EXPIRED = "expired"
    COMPLETED = "completed"
    ENDED = "ended"


@dataclass(frozen=True)
class BrowserCheck:
    """What the join page's script found out about the browser (static/js/online_check.js)."""

    webgl: bool
    audio: bool
    width: int
    height: int
    keyboard: bool
    touch: bool

    @property
    def device(self) -> DeviceKind:
        """The kind of device, from its input: touch without a key pressed is a tablet or a
        phone (by the shorter side of its window), anything else a desktop."""
        if self.touch and not self.keyboard:
            return DeviceKind.PHONE if min(self.width, self.height) < 600 else DeviceKind.TABLET
        return DeviceKind.DESKTOP

    def problem(self, online: OnlineSpec) -> str:
        """Why this browser cannot run the study ('' when it can), in the participant's terms
        (the join page words it in their language from this key)."""
        if not self.webgl:
            return "webgl"
        if not self.audio:
            return "audio"
        if self.device not in online.devices:
            return f"device:{self.device.value}"
        if self.width < online.min_width or self.height < online.min_height:
            return "window"
        return ""


@dataclass(frozen=True)
class Joined:
    """A join's outcome; ``participation`` unless the study was full or closed, ``token`` the
    tablet link's token of an active one."""

    outcome: Outcome
    participation: OnlineParticipation | None = None
    token: str | None = None


def is_online(db: Session, participant_id: int) -> bool:
    """Whether the participant joined online (their tablet's waiting pages are the room)."""
    found = db.scalar(
        select(OnlineParticipation.id).where(OnlineParticipation.participant_id == participant_id)
    )
    return found is not None


def online_spec(study: Study) -> OnlineSpec:
    """The study's ``[online]``; NotFound when it is not run online."""
    online = protocol_of(study).online
    if online is None:
        raise NotFound(f"study {study.name!r} is not run online")
    return online


def join(
    db: Session,
    *,
    study_name: str,
    query: Mapping[str, str],
    browser_id: str,
    check: BrowserCheck,
    secret: bytes,
    checkpoint_dir: Path | None = None,
    now: Callable[[], datetime] = utcnow,
) -> Joined:
    """Join ``study_name`` with the platform's URL parameters ``query``; commits."""
    study = get_study(db, study_name)
    online = online_spec(study)
    if study.phase == StudyPhase.DRAFT:
        raise Conflict(f"study {study.name!r} is not open yet: try the link again later")
    recruitment_id = check_recruitment_id(
        query.get(online.id_parameter, ""), parameter=online.id_parameter
    )
    hashed = recruitment_hash(secret, study.id, recruitment_id)
    for _attempt in range(ENROL_ATTEMPTS):
        found = _participation(db, study.id, hashed)
        if found is not None:
            return _returning(db, found, secret=secret, at=now())
        if study.status != StudyStatus.OPEN:
            return Joined(Outcome.CLOSED)
        parameters = {
            name: query[name][:PARAMETER_MAX] for name in online.parameters if name in query
        }
        browser = browser_hash(secret, browser_id)
        problem = check.problem(online)
        protocol = protocol_of(study)
        strata = _strata(protocol, parameters) if not problem else {}
        if not problem and _full(db, study, protocol, online, strata):
            return Joined(Outcome.FULL)
        try:
            if problem:
                return _screen_out(db, study, hashed, parameters, browser, check, problem, now())
            return _enrol(
                db,
                study,
                online,
                hashed,
                parameters,
                browser,
                check.device,
                strata,
                secret=secret,
                checkpoint_dir=checkpoint_dir,
                at=now(),
            )
        except Conflict:
            db.rollback()  # the same ID joined at the same moment, or an allocation slot was
            continue  # taken: look again
    raise Conflict("too many people joined at this moment: reload the page")


def _participation(db: Session, study_id: int, hashed: str) -> OnlineParticipation | None:
    return db.scalar(
        select(OnlineParticipation).where(
            OnlineParticipation.study_id == study_id,
            OnlineParticipation.recruitment_hash == hashed,
        )
    )


def _strata(protocol: Protocol, parameters: Mapping[str, str]) -> dict[str, str]:
    strata = {}
    for factor in protocol.allocation.stratify_by:
        value = parameters.get(factor, "").strip()
        if not value:
            raise InvalidInput(
                Message(
                    "the link has no %(parameter)s, which this study needs: please tell the "
                    "researcher through the recruitment platform",
                    parameter=factor,
                )
            )
        strata[factor] = value
    return strata


def _stratum(protocol: Protocol, online: OnlineSpec, strata: Mapping[str, str]) -> str:
    values = dict(strata)
    if protocol.sites is not None and protocol.sites.stratify and online.site is not None:
        values[SITE_FACTOR] = online.site
    return stratum_key(values)


def complete_counts(db: Session, study: Study, *, pilot: bool) -> dict[tuple[str, str], int]:
    """Complete online participants by (stratum, condition)."""
    rows = db.execute(
        select(Allocation.stratum, Allocation.condition, func.count())
        .join(OnlineParticipation, OnlineParticipation.participant_id == Allocation.participant_id)
        .where(
            OnlineParticipation.study_id == study.id,
            OnlineParticipation.status == OnlineStatus.COMPLETED,
            OnlineParticipation.pilot == pilot,
        )
        .group_by(Allocation.stratum, Allocation.condition)
    )
    return {(stratum, condition): count for stratum, condition, count in rows}


def _full(
    db: Session, study: Study, protocol: Protocol, online: OnlineSpec, strata: Mapping[str, str]
) -> bool:
    """Whether every condition of the joiner's stratum has its complete participants. Only
    the stratum as a whole closes, never one condition: closing one would tell the next
    joiner which condition they are about to get, and break the concealed sequence."""
    target = online.target_per_condition
    if target is None:
        return False
    counts = complete_counts(db, study, pilot=study.phase == StudyPhase.PILOT)
    stratum = _stratum(protocol, online, strata)
    return all(counts.get((stratum, c.id), 0) >= target for c in protocol.conditions)


def _screen_out(
    db: Session,
    study: Study,
    hashed: str,
    parameters: dict[str, str],
    browser: str,
    check: BrowserCheck,
    problem: str,
    at: datetime,
) -> Joined:
    """Record that this ID was screened out (a return is told so again), nobody enrolled."""
    participation = OnlineParticipation(
        study_id=study.id,
        recruitment_hash=hashed,
        status=OnlineStatus.SCREENED_OUT,
        reason=problem,
        parameters=parameters,
        browser=browser,
        device=check.device.value,
        step="check",
        step_at=at,
        joined_at=at,
        expires_at=at,
        finished_at=at,
        last_seen_at=at,
        pilot=study.phase == StudyPhase.PILOT,
    )
    db.add(participation)
    try:
        db.commit()
    except IntegrityError:
        raise Conflict("the same ID was screened at this moment") from None
    return Joined(Outcome.SCREENED_OUT, participation)


def _enrol(
    db: Session,
    study: Study,
    online: OnlineSpec,
    hashed: str,
    parameters: dict[str, str],
    browser: str,
    device: DeviceKind,
    strata: dict[str, str],
    *,
    secret: bytes,
    checkpoint_dir: Path | None,
    at: datetime,
) -> Joined:
    made: dict[str, object] = {}
    flags = {}
    if browser and _browser_seen(db, study.id, browser):
        flags["second_id_same_browser"] = True

    def along(participant: Participant) -> None:
        station = Station(
            name=f"{STATION_PREFIX}{participant.id}",
            online=True,
            site=participant.site,
            study_id=study.id,
            participant_id=participant.id,
            assigned_at=at,
        )
        db.add(station)
        db.flush()
        participation = OnlineParticipation(
            study_id=study.id,
            recruitment_hash=hashed,
            participant_id=participant.id,
            station_id=station.id,
            parameters=parameters,
            browser=browser,
            device=device.value,
            step="joined",
            step_at=at,
            joined_at=at,
            expires_at=at + timedelta(minutes=online.time_limit_minutes),
            last_seen_at=at,
            flags=flags,
            pilot=participant.pilot,
        )
        db.add(participation)
        db.flush()
        key = device_key(secret, participation.id, participation.key_generation)
        db.add(
            Device(
                station_id=station.id,
                label="browser",
                key_hash=token_digest(key),
                key_prefix=key[:10],
                created_by=JOIN_ACTOR.name,
            )
        )
        made["token"] = tablet_tokens.grant_participant_token(
            db, participant=participant, secret=secret, actor=JOIN_ACTOR
        )
        participant_changes.participant_changed(db, participant, Change.SEATED)
        made["participation"] = participation

    enrolment.enroll_participant(
        db,
        study_name=study.name,
        actor=JOIN_ACTOR,
        strata=strata,
        site=online.site,
        checkpoint_dir=checkpoint_dir,
        along=along,
    )
    participation = made["participation"]
    assert isinstance(participation, OnlineParticipation)
    return Joined(Outcome.ENROLLED, participation, str(made["token"]))


def _browser_seen(db: Session, study_id: int, browser: str) -> bool:
    return (
        db.scalar(
            select(OnlineParticipation.id)
            .where(OnlineParticipation.study_id == study_id, OnlineParticipation.browser == browser)
            .limit(1)
        )
        is not None
    )


def _returning(
    db: Session, participation: OnlineParticipation, *, secret: bytes, at: datetime
) -> Joined:
    """The same recruitment ID again: where they stand now."""
    status = refresh(db, participation, at=at)
    if status == OnlineStatus.ACTIVE:
        participant = db.get(Participant, participation.participant_id)
        assert participant is not None
        token = tablet_tokens.participant_token(secret, participant)
        if token is None:  # the server's key changed, or staff reissued the link
            token = tablet_tokens.issue_participant_token(
                db, participant=participant, secret=secret, actor=JOIN_ACTOR
            )
        return Joined(Outcome.RESUMED, participation, token)
    outcome = {
        OnlineStatus.SCREENED_OUT: Outcome.SCREENED_OUT,
        OnlineStatus.EXPIRED: Outcome.EXPIRED,
        OnlineStatus.COMPLETED: Outcome.COMPLETED,
        OnlineStatus.ENDED: Outcome.ENDED,
    }[OnlineStatus(status)]
    return Joined(outcome, participation)


def status_due(
    participation: OnlineParticipation, participant: Participant | None, *, at: datetime
) -> str:
    """The status the participation should have at ``at`` (what :func:`refresh` makes it): an
    active one past its time limit expires, and one whose participant staff withdrew or erased
    ends. Changes nothing: a visit that would change nothing needs no write."""
    if participation.status != OnlineStatus.ACTIVE:
        return participation.status
    if participant is None or participant.status == ParticipantStatus.WITHDRAWN:
        return OnlineStatus.ENDED
    if at >= participation.expires_at:
        return OnlineStatus.EXPIRED
    return OnlineStatus.ACTIVE


def refresh(db: Session, participation: OnlineParticipation, *, at: datetime) -> str:
    """The participation's status now (:func:`status_due`), made so: an expiry ends a running
    session, and either end revokes their key; commits a change."""
    participant = (
        db.get(Participant, participation.participant_id)
        if participation.participant_id is not None
        else None
    )
    status = status_due(participation, participant, at=at)
    if status == participation.status:
        return status
    if status == OnlineStatus.EXPIRED:
        _end_running_session(db, participation)
    finish(db, participation, OnlineStatus(status), at=at)
    return participation.status


def _end_running_session(db: Session, participation: OnlineParticipation) -> None:
    running = db.scalar(
        select(StudySession.id).where(
            StudySession.participant_id == participation.participant_id,
            StudySession.status == SessionStatus.RUNNING,
        )
    )
    station = db.get(Station, participation.station_id) if participation.station_id else None
    if running is not None and station is not None:
        runtime.end_session(db, station_name=station.name, actor=_expiry_actor())


def _expiry_actor() -> Actor:
    return Actor(ActorKind.SYSTEM, "online time limit")


def finish(
    db: Session, participation: OnlineParticipation, status: OnlineStatus, *, at: datetime
) -> None:
    """End the participation as ``status``; its station's device key stops working; commits."""
    participation.status = status
    participation.finished_at = at
    participation.step = "done" if status == OnlineStatus.COMPLETED else participation.step
    participation.step_at = at
    if participation.station_id is not None:
        db.execute(
            update(Device)
            .where(Device.station_id == participation.station_id, Device.revoked_at.is_(None))
            .values(revoked_at=at)
        )
    db.commit()


def participant_actor(participant: Participant) -> Actor:
    """An online participant acting in their own browser, as the audit log names them."""
    return Actor(ActorKind.PARTICIPANT, f"{participant.code} (online)"[:64])


def start_session(db: Session, participation: OnlineParticipation) -> None:
    """Start the participant's next session at their virtual station (they said they are
    ready); commits. Conflict when it is not theirs to start now."""
    if participation.status != OnlineStatus.ACTIVE or participation.station_id is None:
        raise Conflict("this participation has ended")
    station = db.get(Station, participation.station_id)
    participant = db.get(Participant, participation.participant_id)
    assert station is not None and participant is not None
    runtime.start_session(db, station_name=station.name, actor=participant_actor(participant))


def station_key(secret: bytes, participation: OnlineParticipation) -> str:
    """The device key of the participation's virtual station (derived, never stored)."""
    return device_key(secret, participation.id, participation.key_generation)


SEEN_EVERY = timedelta(seconds=30)
"""How stale ``last_seen_at`` may grow before a visit writes it again: the monitor's "online now"
looks two minutes back, and a write on every visit to ``/online`` made each one a write
transaction (a single SQLite writer's queue, at hundreds of participants: bench/online.py)."""


def step_due(participation: OnlineParticipation, step: str, *, at: datetime) -> bool:
    """Whether :func:`record_step` would write: a new step, or a sighting :data:`SEEN_EVERY`
    after the last one written."""
    return step[:80] != participation.step or at - participation.last_seen_at >= SEEN_EVERY


def record_step(
    db: Session, participation: OnlineParticipation, step: str, *, at: datetime
) -> None:
    """Note the page they are on and that they were seen; commits only a change
    (:func:`step_due`)."""
    step = step[:80]
    if not step_due(participation, step, at=at):
        return
    participation.last_seen_at = at
    if step != participation.step:
        participation.step = step
        participation.step_at = at
    db.commit()


LONGEST_AWAY_SECONDS = 24 * 3600.0
"""One report of time away from the room is at most a day (a study's time limit is shorter)."""


def record_away(db: Session, participation: OnlineParticipation, seconds: float) -> None:
    """Add one spell of the room's tab being hidden to their time away (data quality:
    app/services/participants/data_quality.py); commits. Nothing once the participation is
    over: a closing tab's last report may arrive after the completion."""
    if participation.status != OnlineStatus.ACTIVE:
        return
    # One UPDATE adding to the column: two reports arriving at once (a hidden tab closed) both
    # count, whichever commits first.
    db.execute(
        update(OnlineParticipation)
        .where(OnlineParticipation.id == participation.id)
        .values(
            room_seconds_away=OnlineParticipation.room_seconds_away
            + min(max(seconds, 0.0), LONGEST_AWAY_SECONDS)
        )
    )
    db.commit()


def find_by_recruitment_id(
    db: Session, *, study_name: str, recruitment_id: str, secret: bytes, actor: Actor
) -> OnlineParticipation:
    """The participation of a recruitment ID (an admin's request: a participant who writes
    through the platform knows only their ID); audited, with the ID's hash only; commits.
    NotFound when the ID never joined this study (or its data was erased)."""
    study = get_study(db, study_name)
    online_spec(study)
    given = check_recruitment_id(recruitment_id, parameter="recruitment ID")
    found = _participation(db, study.id, recruitment_hash(secret, study.id, given))
    if found is None:
        raise NotFound(f"no participation of that recruitment ID in study {study.name!r}")
    participant = (
        db.get(Participant, found.participant_id) if found.participant_id is not None else None
    )
    audit.record(
        db,
        actor=actor,
        action="online.recruitment_id_looked_up",
        study_id=study.id,
        subject=participant.code if participant is not None else "",
        details={"participation": found.id},
    )
    db.commit()
    return found
