"""The study overview: each participant's progress and last activity, and what needs attention.

Everything comes from a handful of grouped queries (not one query per participant), so the page
stays fast with a thousand participants. Warnings name what an experimenter should do:

- a session that has been running without an answer for a while (is the robot stuck?);
- a session questionnaire still missing a while after its session ended;
- a station with a participant but no usable device key, or whose devices have gone quiet
  during a running session;
- a participant who declined a new version of the consent text (staff decide whether to
  withdraw them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timedelta

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.services.audit import Actor
from app.services.blinding import condition_labels
from app.services.participants.enrolment import condition_label
from app.services.privacy import consent, sites
from app.services.sessions.runtime import session_label
from app.services.studies import protocol_of
from app.tables import (
    Allocation,
    Answer,
    Device,
    Participant,
    ParticipantStatus,
    Response,
    SessionStatus,
    Station,
    Study,
    StudySession,
    Submission,
    utcnow,
)

STALLED_AFTER = timedelta(minutes=10)
QUESTIONNAIRE_LATE_AFTER = timedelta(minutes=15)
DEVICE_QUIET_AFTER = timedelta(minutes=2)


@dataclass
class ParticipantRow:
    """One participant's line on the overview."""

    code: str
    group: str
    status: str
    stratum: str
    site: str | None
    """The participant's site (None in a study without sites)."""
    language: str | None
    """The participant's language (None: not chosen yet on the tablet)."""
    locked: bool
    sessions_done: int
    running_session: int | None
    questionnaires_done: int
    station: str | None
    last_activity: datetime | None
    consent: str = ""
    """What is due about the consent text ('' when nothing): re-consent needed, or declined."""
    pilot: bool = False
    """A pilot participant (app.services.design.study_phases): listed, marked, never counted."""


@dataclass
class Attention:
    """Something an experimenter should look at, and where."""

    message: str
    participant: str | None = None
    station: str | None = None


@dataclass
class StudyOverview:
    """The overview page's content."""

    rows: list[ParticipantRow] = field(default_factory=list)
    warnings: list[Attention] = field(default_factory=list)
    groups: dict[str, dict[str, int]] = field(default_factory=dict)
    sessions_total: int = 0
    questionnaires_total: int = 0
    erased: int = 0
    """Participants whose data was erased: counted in their group as withdrawn, never listed."""
    pilots: int = 0
    """Pilot participants: listed (marked), not counted in the groups."""


def _latest(*values: datetime | None) -> datetime | None:
    present = [v for v in values if v is not None]
    return max(present) if present else None


def study_overview(db: Session, *, study: Study, actor: Actor) -> StudyOverview:
    """Progress of every participant, group sizes and warnings."""
    protocol = protocol_of(study)
    now = utcnow()
    # Only the participants of the sites the actor may see (app.services.privacy.sites), everywhere.
    mine = (Participant.study_id == study.id) & sites.visible(actor)
    in_study = select(Participant.id).where(mine)
    participants = db.execute(
        select(Participant, Allocation.condition)
        .join(Allocation, Allocation.participant_id == Participant.id)
        .where(mine)
        .order_by(Participant.enrolled_at, Participant.id)
    ).all()
    sessions: dict[int, list[StudySession]] = {}
    for session in db.scalars(
        select(StudySession)
        .where(StudySession.participant_id.in_(in_study))
        .order_by(StudySession.number)
    ):
        sessions.setdefault(session.participant_id, []).append(session)
    last_answer = dict(
        db.execute(
            select(Answer.participant_id, func.max(Answer.answered_at))
            .where(Answer.participant_id.in_(in_study))
            .group_by(Answer.participant_id)
        ).all()
    )
    last_response = dict(
        db.execute(
            select(Response.participant_id, func.max(Response.answered_at))
            .where(Response.participant_id.in_(in_study))
            .group_by(Response.participant_id)
        ).all()
    )
    submitted: dict[int, set[tuple[str, int | None]]] = {}
    for participant_id, instrument, number in db.execute(
        select(Submission.participant_id, Submission.instrument, Submission.session).where(
            Submission.participant_id.in_(in_study)
        )
    ):
        submitted.setdefault(participant_id, set()).add((instrument, number))
    station_of = dict(
        db.execute(
            select(Station.participant_id, Station.name).where(Station.participant_id.in_(in_study))
        ).all()
    )
    consents = consent.standings(db, study)
    overview = StudyOverview(sessions_total=protocol.schedule.sessions)
    # The groups in the order to list them (C1 before C2, or neutral labels alphabetically), not
    # in the order their first participant happened to enrol.
    for group in condition_labels(study, actor).values():
        overview.groups.setdefault(group, dict.fromkeys(ParticipantStatus, 0))
    session_instruments = [i.key for i in protocol.instruments_at("session")]
    for participant, condition in participants:
        own = sessions.get(participant.id, [])
        closed = [s for s in own if s.status != SessionStatus.RUNNING and s.number >= 1]
        running = next((s for s in own if s.status == SessionStatus.RUNNING), None)
        done = submitted.get(participant.id, set())
        started = _latest(*(s.started_at for s in own))
        last = _latest(
            last_answer.get(participant.id),
            last_response.get(participant.id),
            started,
            participant.enrolled_at,
        )
        group = condition_label(study, condition, actor=actor)
        if participant.pilot:
            overview.pilots += 1
        else:
            counts = overview.groups.setdefault(group, dict.fromkeys(ParticipantStatus, 0))
            counts[participant.status] += 1
        if participant.erased_at is not None:
            overview.erased += 1
            continue
        overview.rows.append(
            ParticipantRow(
                code=participant.code,
                group=group,
                status=participant.status,
                stratum=participant.stratum,
                site=participant.site,
                language=participant.language,
                locked=participant.locked_at is not None,
                sessions_done=len(closed),
                running_session=running.number if running else None,
                questionnaires_done=len(done),
                station=station_of.get(participant.id),
                last_activity=last,
                consent=consents[participant.id].note
                if participant.id in consents and participant.status != ParticipantStatus.WITHDRAWN
                else "",
                pilot=participant.pilot,
            )
        )
        if participant.status == ParticipantStatus.WITHDRAWN:
            continue
        standing = consents.get(participant.id)
        if standing is not None and standing.outdated and standing.declined == standing.current:
            overview.warnings.append(
                Attention(
                    f"{participant.code} declined version {standing.declined} of the consent "
                    "text: talk to them, and withdraw them if they do not agree",
                    participant=participant.code,
                )
            )
        if running is not None and last is not None and now - last > STALLED_AFTER:
            overview.warnings.append(
                Attention(
                    f"{participant.code}: {session_label(running.number)} has had no answer for "
                    f"{int((now - last).total_seconds() // 60)} minutes",
                    participant=participant.code,
                    station=station_of.get(participant.id),
                )
            )
        for session in closed:
            missing = [key for key in session_instruments if (key, session.number) not in done]
            ended = session.ended_at
            if missing and ended is not None and now - ended > QUESTIONNAIRE_LATE_AFTER:
                overview.warnings.append(
                    Attention(
                        f"{participant.code}: the questionnaire after session {session.number} "
                        "is still missing",
                        participant=participant.code,
                    )
                )
    overview.warnings += _station_warnings(db, study, now, actor)
    return overview


def _station_warnings(db: Session, study: Study, now: datetime, actor: Actor) -> list[Attention]:
    warnings = []
    rows = db.execute(
        select(Station, Participant)
        .join(Participant, Participant.id == Station.participant_id)
        .where(Participant.study_id == study.id, sites.visible(actor))
    ).all()
    for station, participant in rows:
        devices = list(
            db.scalars(
                select(Device).where(Device.station_id == station.id, Device.revoked_at.is_(None))
            )
        )
        if not devices:
            warnings.append(
                Attention(
                    f"station {station.name} has {participant.code} but no device key: "
                    "an admin issues one on the stations page (or use Wizard-of-Oz)",
                    station=station.name,
                )
            )
            continue
        running = db.scalar(
            select(StudySession.number).where(
                StudySession.participant_id == participant.id,
                StudySession.status == SessionStatus.RUNNING,
            )
        )
        heard = _latest(*(d.last_seen_at for d in devices))
        if (
            running is not None
            and not any(d.connected for d in devices)
            and (heard is None or now - heard > DEVICE_QUIET_AFTER)
        ):
            warnings.append(
                Attention(
                    f"station {station.name}: no device has been heard from during "
                    f"{session_label(running)}",
                    station=station.name,
                )
            )
    return warnings
