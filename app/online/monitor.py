"""What an online study's participants are doing now: the dashboard's online panel.

Nothing here is recorded for the monitor's sake. Where a participant is comes from what decides
it for them too — their submitted pages and ended sessions (app.services.participants.
questionnaires.page_for) and their running session — so the panel cannot disagree with the page
the participant is shown, whichever page they reached it from. Who is "online now" comes from
the room's socket (open on any worker: ``device_socket``) or their last request to ``/online``.
A participation past its time limit that nobody has looked at since is counted as expired here,
as its next visit would make it.

Every figure is of the reader's scope (app.services.privacy.sites): participants of sites out of
scope are never counted, and the screened-out (who belong to no site's participants) are counted
only for a reader of every site.
"""

from __future__ import annotations

import statistics
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from sqlalchemy import ColumnElement, func, select
from sqlalchemy.orm import Session

from app.protocol import Protocol
from app.services.participants import questionnaires
from app.services.participants.questionnaires import Page
from app.services.privacy.sites import Scope
from app.services.sessions.runtime import first_session_number, session_label
from app.tables import (
    Device,
    DeviceSocket,
    OnlineParticipation,
    OnlineStatus,
    Participant,
    ParticipantStatus,
    SessionStatus,
    Study,
    StudySession,
    Submission,
)

ONLINE_NOW = timedelta(minutes=2)
"""Seen within this (a page of theirs asked ``/online``), or their room connected: online now."""


def step_of(page: Page, session: int | None = None) -> str:
    """Where a participant is, as a key: ``consent``, ``questionnaire:trust:2``, ``room:2``
    (``session``: the one they are in, or will start next, when the page is the room)."""
    suffix = f":{page.session}" if page.session is not None else ""
    if page.kind == "questionnaire" and page.instrument is not None:
        return f"questionnaire:{page.instrument.key}{suffix}"
    if page.kind == "wait":  # an online participant's wait is the room
        return f"room:{session}" if session is not None else "room"
    return page.kind


def flow(protocol: Protocol) -> list[tuple[str, str]]:
    """Every step a participant passes, in order, as (key, words for staff)."""

    def pages(when: str, session: int | None = None) -> list[tuple[str, str]]:
        after = "" if session is None else f", after session {session}"
        suffix = "" if session is None else f":{session}"
        return [
            (f"questionnaire:{i.key}{suffix}", f"Questionnaire: {i.title}{after}")
            for i in protocol.instruments_at(when)
        ]

    steps = [("language", "Choosing a language"), ("consent", "Consent"), *pages("pre")]
    for number in range(first_session_number(protocol), protocol.schedule.sessions + 1):
        steps.append((f"room:{number}", f"In the room: {session_label(number)}"))
        if number >= 1:
            steps += pages("session", number)
    return [*steps, *pages("post"), ("done", "Finished")]


@dataclass(frozen=True)
class StepCount:
    """How many participants are at (or left at) one step."""

    step: str
    label: str
    count: int


@dataclass
class OnlineMonitor:
    """The online panel's figures, at ``now``."""

    now: datetime
    active: int = 0
    """Enrolled, not finished and within their time limit."""
    online_now: int = 0
    completed: int = 0
    expired: int = 0
    ended: int = 0
    """Withdrawn or erased by staff."""
    screened_out: int | None = 0
    """Not enrolled (their browser, or a full study); None: not the reader's to count."""
    at_step: list[StepCount] = field(default_factory=list)
    """The active participants by the step they are at, in the study's order."""
    dropped_at: list[StepCount] = field(default_factory=list)
    """The expired and ended by the step they had reached, in the study's order."""
    median_minutes_to_complete: float | None = None
    median_session_minutes: float | None = None
    median_page_seconds: list[tuple[str, float]] = field(default_factory=list)
    """Each questionnaire's median time on its page (first submissions the page timed)."""


def _counted(found: Counter[str], steps: list[tuple[str, str]]) -> list[StepCount]:
    labels = dict(steps)
    order = {key: index for index, (key, _) in enumerate(steps)}
    return [
        StepCount(step, labels.get(step, step), count)
        for step, count in sorted(found.items(), key=lambda entry: order.get(entry[0], len(order)))
    ]


def _median(values: list[float]) -> float | None:
    return round(statistics.median(values), 1) if values else None


def online_monitor(
    db: Session, *, study: Study, protocol: Protocol, scope: Scope, now: datetime
) -> OnlineMonitor:
    """The figures of ``study``'s online participants that ``scope`` may see."""
    whom: ColumnElement[bool] = (Participant.study_id == study.id) & scope.where()
    rows = db.execute(
        select(OnlineParticipation, Participant)
        .join(Participant, Participant.id == OnlineParticipation.participant_id)
        .where(OnlineParticipation.study_id == study.id, OnlineParticipation.pilot.is_(False))
        .where(whom)
    ).all()
    monitor = OnlineMonitor(now=now)
    if scope.sites is None:
        monitor.screened_out = db.scalar(
            select(func.count()).where(
                OnlineParticipation.study_id == study.id,
                OnlineParticipation.status == OnlineStatus.SCREENED_OUT,
                OnlineParticipation.pilot.is_(False),
            )
        )
    else:
        monitor.screened_out = None
    participants = {participant.id: participant for _, participant in rows}
    where = questionnaires.progress_of_many(db, study, list(participants))
    in_session = select(StudySession.participant_id, StudySession.number).where(
        StudySession.participant_id.in_(list(participants)),
        StudySession.status == SessionStatus.RUNNING,
    )
    running = {row.participant_id: row.number for row in db.execute(in_session)}
    connected = set(
        db.scalars(
            select(Device.station_id)
            .join(DeviceSocket, DeviceSocket.device_id == Device.id)
            .where(DeviceSocket.expires_at > now, Device.revoked_at.is_(None))
        )
    )
    steps = flow(protocol)
    at: Counter[str] = Counter()
    dropped: Counter[str] = Counter()
    durations: list[float] = []
    for participation, participant in rows:
        status = participation.status
        if status == OnlineStatus.ACTIVE:  # as its next visit will make it
            if participant.status == ParticipantStatus.WITHDRAWN:
                status = OnlineStatus.ENDED
            elif participation.expires_at <= now:
                status = OnlineStatus.EXPIRED
        if status == OnlineStatus.COMPLETED:
            monitor.completed += 1
            if participation.finished_at is not None:
                spent = participation.finished_at - participation.joined_at
                durations.append(spent.total_seconds() / 60)
            continue
        progress = where[participant.id]
        page = questionnaires.page_reached(participant, protocol, progress)
        step = step_of(page, running.get(participant.id, _next_session(protocol, progress)))
        if status == OnlineStatus.ACTIVE:
            monitor.active += 1
            at[step] += 1
            recent = participation.last_seen_at >= now - ONLINE_NOW
            if recent or participation.station_id in connected:
                monitor.online_now += 1
        else:
            if status == OnlineStatus.EXPIRED:
                monitor.expired += 1
            else:
                monitor.ended += 1
            dropped[step] += 1
    monitor.at_step = _counted(at, steps)
    monitor.dropped_at = _counted(dropped, steps)
    monitor.median_minutes_to_complete = _median(durations)
    _durations(db, protocol, monitor, list(participants))
    return monitor


def _next_session(protocol: Protocol, progress: questionnaires.Progress) -> int:
    """The session a participant who waits starts next."""
    return max(progress.closed) + 1 if progress.closed else first_session_number(protocol)


def _durations(
    db: Session, protocol: Protocol, monitor: OnlineMonitor, participant_ids: list[int]
) -> None:
    """Median minutes of an ended session, and median seconds on each questionnaire's page."""
    sessions = db.execute(
        select(StudySession.started_at, StudySession.ended_at).where(
            StudySession.participant_id.in_(participant_ids),
            StudySession.ended_at.is_not(None),
            StudySession.number >= 1,
        )
    ).all()
    monitor.median_session_minutes = _median(
        [(ended - started).total_seconds() / 60 for started, ended in sessions if ended]
    )
    pages: dict[str, list[float]] = defaultdict(list)
    timed = db.execute(
        select(Submission.instrument, Submission.seconds_on_page).where(
            Submission.participant_id.in_(participant_ids),
            Submission.seconds_on_page.is_not(None),
        )
    )
    for instrument, seconds in timed:
        if seconds is not None:
            pages[instrument].append(seconds)
    titles = {i.key: i.title for i in protocol.questionnaires.instruments}
    monitor.median_page_seconds = [
        (titles[key], median)
        for key in titles
        if (median := _median(pages.get(key, []))) is not None
    ]
