"""The live experiment: sessions, runs, prompts and exactly-once answers at a station.

The participant timeline is: an optional familiarisation session (number 0, one run, logged but
never adapting), then sessions 1..S of R runs each. In a run every category is prompted once, in
whatever order the client asks. A run completes when its last category is answered (the next run
starts on the next prompt, or explicitly); a session completes with its last run. Experimenters
start sessions and may end a run or a session early; the server enforces the order and every
refusal says what is expected instead.

Exactly-once adaptation:

- a prompt request while the category has an open prompt in the run returns that prompt;
- ``UNIQUE(run, category)`` on prompts and ``UNIQUE(prompt)`` on answers make duplicates impossible;
- prompts, answers and the experimenter's session and run commands lock the participant's
  timeline first (PostgreSQL; SQLite's write transactions are exclusive); an answer updates the
  learner, stores its new state as the next version only if the stored version is still the one
  it started from, appends the answer and commits — all or nothing; repeating it (same
  idempotency key, or the same answer again) returns the stored reply without a second update; a
  different answer is refused with 409.

Data access: every read and write goes through :mod:`app.services.sessions.step_store` (hand-written
SQL on the request's transaction), so the robot's hot path costs little more than its statements,
and the rules here work on plain values rather than ORM objects.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict, InvalidInput, NotFound
from app.protocol import Protocol
from app.services import blinding
from app.services.audit import Actor
from app.services.participants import languages, questionnaires
from app.services.privacy import consent
from app.services.sessions import learner_cache, learners, replies, step_store
from app.services.sessions.stations import get_station
from app.services.sessions.step_store import (
    NOT_SAID,
    HowAnswered,
    LearnerRow,
    RunState,
    Seat,
    Seated,
    Step,
    StoredAnswer,
)
from app.services.studies import protocol_by_id
from app.services.topics import participant_topic, station_topic_of, study_topic
from app.sql import Cursor
from app.tables import Answer, ParticipantStatus, Prompt, RunStatus, SessionStatus
from models.learners.base import Learner

FAMILIARISATION = 0


# ---------------------------------------------------------------- the schedule, from the protocol


def first_session_number(protocol: Protocol) -> int:
    """0 when the protocol has a familiarisation run, else 1."""
    return FAMILIARISATION if protocol.schedule.familiarisation_run else 1


def runs_in(protocol: Protocol, session_number: int) -> int:
    """How many runs a session has (the familiarisation session has one)."""
    return 1 if session_number == FAMILIARISATION else protocol.schedule.runs_per_session


def session_label(number: int) -> str:
    """How people call a session."""
    return "the familiarisation run" if number == FAMILIARISATION else f"session {number}"


# ---------------------------------------------------------------------------- the live context


@dataclass
class Context:
    """Who is at a station, their protocol, and the run in question (usually their latest)."""

    cursor: Cursor
    seat: Seat
    participant: Seated
    protocol: Protocol
    run: RunState | None
    own: Protocol | None = None
    """The protocol in its first language, for the staff's words (the console's "Next:" line
    names instruments in it, not in the participant's language); None: ``protocol`` is."""

    @property
    def staff_protocol(self) -> Protocol:
        """The protocol whose texts staff read (its first language)."""
        return self.own or self.protocol

    @property
    def learners_shown(self) -> bool:
        """Whether staff may see this participant's learners (app.services.blinding)."""
        return not blinding.sealed(self.protocol, unblinded=self.participant.unblinded)


def _context(
    db: Session,
    station_name: str,
    *,
    seat: Seat | None = None,
    lock_station: bool = False,
    lock_timeline: bool = False,
    latest_run: bool = True,
) -> Context:
    """The station's seat (as given, e.g. by a robot's device, or read), its protocol, and the
    participant's latest run unless ``latest_run`` is False. ``lock_station`` row-locks the
    station and ``lock_timeline`` the participant's timeline (step_store.lock_timeline) on
    PostgreSQL, before anything else is read; SQLite's write transactions are exclusive."""
    cursor = Cursor.of(db)
    if seat is None or lock_station:
        seat = step_store.station_seat(cursor, name=station_name, lock=lock_station)
        if seat is None:
            get_station(db, station_name)  # raises NotFound naming the stations that exist
            raise AssertionError(station_name)  # pragma: no cover
    participant = seat.participant
    if participant is None:
        raise Conflict(
            f"no participant is assigned to station {seat.station_name!r}: "
            "an experimenter assigns one first"
        )
    if lock_timeline:
        status = step_store.lock_timeline(cursor, participant_id=participant.id)
        if status is not None and status != participant.status:  # changed before the lock
            participant = dataclasses.replace(participant, status=status)
    own = protocol_by_id(
        db, study_id=participant.study_id, protocol_sha256=participant.protocol_sha256
    )
    protocol = languages.protocol_for(participant.language, own)
    run = step_store.latest_run(cursor, participant_id=participant.id) if latest_run else None
    return Context(cursor, seat, participant, protocol, run, own)


@dataclass(frozen=True)
class RunProgress:
    """Which categories of a run are answered, open (prompted, unanswered) or still to come."""

    answered: list[str]
    open: list[Step]
    pending: list[str]


def run_progress(run: RunState, protocol: Protocol) -> RunProgress:
    """The state of each category in a run."""
    answered = [step.category for step in run.steps if step.answer_id is not None]
    open_steps = [step for step in run.steps if step.answer_id is None]
    asked = {step.category for step in run.steps}
    pending = [c.name for c in protocol.categories if c.name not in asked]
    return RunProgress(answered, open_steps, pending)


# ------------------------------------------------------------------------------ expected next


@dataclass(frozen=True)
class Expected:
    """What the station should do next, for people and for programs."""

    action: str
    message: str
    categories: list[str] = field(default_factory=list)
    step_id: int | None = None
    session: int | None = None


def session_gate(ctx: Context, number: int) -> str:
    """Why session ``number`` cannot start yet ('' when it can): consent, questionnaires, and a
    new consent text the protocol wants accepted before the next session."""
    participant = ctx.participant
    done = step_store.submitted(ctx.cursor, participant_id=participant.id)
    # Staff read it: instruments by their titles in the protocol's own language.
    blocker = questionnaires.blocker_given(done, participant.code, ctx.staff_protocol, number)
    if blocker or not ctx.protocol.questionnaires.consent.reconsent_before_next_session:
        return blocker
    current, accepted = step_store.consent_versions(
        ctx.cursor, study_id=participant.study_id, participant_id=participant.id
    )
    return consent.reconsent_blocker(participant.code, current, accepted)


def expected_next(db: Session, ctx: Context, progress: RunProgress | None = None) -> Expected:
    """The next step of the timeline at this station (``ctx.run``: the participant's latest run;
    ``progress``: its progress, if known)."""
    protocol, participant = ctx.protocol, ctx.participant
    code = participant.code
    if participant.status == ParticipantStatus.WITHDRAWN:
        return Expected("none", f"{code} has withdrawn: assign another participant")
    run = ctx.run
    if run is not None and run.session_status == SessionStatus.RUNNING:
        label = session_label(run.session_number)
        if run.run_status == RunStatus.RUNNING:
            progress = progress or run_progress(run, protocol)
            if progress.open:
                step = progress.open[0]
                return Expected(
                    "answer",
                    f"record {code}'s yes/no answer to step {step.id} ({step.category})",
                    [s.category for s in progress.open],
                    step_id=step.id,
                    session=run.session_number,
                )
            return Expected(
                "prompt",
                f"prompt one of {', '.join(progress.pending)} (run {run.run_number} of {label})",
                progress.pending,
                session=run.session_number,
            )
        return Expected(
            "prompt",
            f"run {run.run_number} of {label} is over: prompting any category starts run "
            f"{run.run_number + 1}",
            [c.name for c in protocol.categories],
            session=run.session_number,
        )
    next_number = first_session_number(protocol) if run is None else run.session_number + 1
    if next_number > protocol.schedule.sessions:
        return Expected("done", f"{code} has finished every session")
    blocker = session_gate(ctx, next_number)
    if blocker:
        return Expected("wait", blocker, session=next_number)
    return Expected(
        "start_session",
        f"an experimenter starts {session_label(next_number)} for {code}",
        session=next_number,
    )


# ------------------------------------------------------------------------------- sessions, runs


def _topics(ctx: Context) -> list[str]:
    return [station_topic_of(ctx.seat.station_id), study_topic(ctx.participant.study_id)]


def _site(ctx: Context) -> str | None:
    """The ``site`` every event of the session carries (app.services.privacy.sites.reaches)."""
    return ctx.participant.site


def _audit(ctx: Context, actor: Actor, action: str, details: dict[str, Any]) -> None:
    step_store.insert_audit(
        ctx.cursor,
        actor_kind=str(actor.kind),
        actor=actor.name,
        action=action,
        study_id=ctx.participant.study_id,
        subject=ctx.participant.code,
        details=details,
    )


def _running(db: Session, ctx: Context) -> RunState:
    """The latest run of the running session; Conflict (saying what is expected) without one."""
    run = ctx.run
    if run is None or run.session_status != SessionStatus.RUNNING:
        raise Conflict(
            f"no session is running for {ctx.participant.code}; expected: "
            + expected_next(db, ctx).message
        )
    return run


def start_session(db: Session, *, station_name: str, actor: Actor) -> StationView:
    """Start the participant's next session (and its first run); commits. The station then."""
    ctx = _context(db, station_name, lock_station=True, lock_timeline=True)
    participant = ctx.participant
    code = participant.code
    if participant.status != ParticipantStatus.ACTIVE:
        raise Conflict(f"{code} is {participant.status}: no further sessions")
    if ctx.run is not None and ctx.run.session_status == SessionStatus.RUNNING:
        raise Conflict(
            f"{session_label(ctx.run.session_number)} is already running for {code}; "
            "expected: " + expected_next(db, ctx).message
        )
    expected = expected_next(db, ctx)
    if expected.action != "start_session":
        raise Conflict(f"cannot start a session for {code}: {expected.message}")
    number = expected.session
    assert number is not None
    try:
        session_id = step_store.open_session(
            ctx.cursor,
            participant_id=participant.id,
            station_id=ctx.seat.station_id,
            number=number,
            actor=actor.name,
        )
    except IntegrityError as exc:
        db.rollback()
        raise Conflict(f"{session_label(number)} was started concurrently; reload") from exc
    run_id = step_store.open_run(
        ctx.cursor, session_id=session_id, participant_id=participant.id, number=1
    )
    ctx.run = RunState(session_id, number, SessionStatus.RUNNING, run_id, 1, RunStatus.RUNNING, [])
    _audit(ctx, actor, "session.started", {"session": number, "station": ctx.seat.station_name})
    events.publish(
        db,
        topics=_topics(ctx),
        type="session_started",
        participant=code,
        session=number,
        site=_site(ctx),
    )
    view = _view(db, ctx)
    db.commit()
    return view


def _close_session(ctx: Context, run: RunState, status: SessionStatus, actor: Actor) -> None:
    """Close the run's session (its participant completes with the last session)."""
    step_store.close_session(ctx.cursor, session_id=run.session_id, status=status, actor=actor.name)
    run.session_status = status
    participant = ctx.participant
    last = run.session_number == ctx.protocol.schedule.sessions
    if last and participant.status == ParticipantStatus.ACTIVE:
        step_store.complete_participant(ctx.cursor, participant_id=participant.id)
        ctx.participant = dataclasses.replace(participant, status=ParticipantStatus.COMPLETED)
    _audit(ctx, actor, "session.ended", {"session": run.session_number, "status": status})
    events.publish(
        ctx.cursor.db,
        topics=[*_topics(ctx), participant_topic(participant.id)],
        type="session_ended",
        participant=participant.code,
        session=run.session_number,
        status=str(status),
        site=_site(ctx),
    )


def _close_run(ctx: Context, run: RunState, status: RunStatus, actor: Actor) -> bool:
    """Close a run; closes its session too when it was the last. Returns whether it did."""
    step_store.close_run(ctx.cursor, run_id=run.run_id, status=status)
    run.run_status = status
    events.publish(
        ctx.cursor.db,
        topics=_topics(ctx),
        type="run_ended",
        participant=ctx.participant.code,
        session=run.session_number,
        run=run.run_number,
        status=str(status),
        site=_site(ctx),
    )
    if run.run_number < runs_in(ctx.protocol, run.session_number):
        return False
    early = status == RunStatus.ENDED_EARLY or step_store.session_had_early_runs(
        ctx.cursor, session_id=run.session_id
    )
    _close_session(ctx, run, SessionStatus.ENDED_EARLY if early else SessionStatus.COMPLETED, actor)
    return True


def end_session(db: Session, *, station_name: str, actor: Actor) -> StationView:
    """End the running session early (its open run too); commits. The station then."""
    ctx = _context(db, station_name, lock_station=True, lock_timeline=True)
    run = _running(db, ctx)
    if run.run_status == RunStatus.RUNNING:
        step_store.close_run(ctx.cursor, run_id=run.run_id, status=RunStatus.ENDED_EARLY)
        run.run_status = RunStatus.ENDED_EARLY
    _close_session(ctx, run, SessionStatus.ENDED_EARLY, actor)
    view = _view(db, ctx)
    db.commit()
    return view


def _open_next_run(ctx: Context) -> RunState:
    """Open the run after ``ctx.run`` in its session; it becomes ``ctx.run``."""
    run = ctx.run
    assert run is not None
    total = runs_in(ctx.protocol, run.session_number)
    if (
        run.run_number >= total
    ):  # pragma: no cover - the session would have closed with its last run
        raise Conflict(f"all {total} runs of {session_label(run.session_number)} are over")
    number = run.run_number + 1
    try:
        run_id = step_store.open_run(
            ctx.cursor, session_id=run.session_id, participant_id=ctx.participant.id, number=number
        )
    except IntegrityError as exc:  # another request opened it first (PostgreSQL)
        ctx.cursor.db.rollback()
        raise Conflict(f"run {number} was started concurrently; ask again") from exc
    events.publish(
        ctx.cursor.db,
        topics=_topics(ctx),
        type="run_started",
        participant=ctx.participant.code,
        session=run.session_number,
        run=number,
        site=_site(ctx),
    )
    ctx.run = RunState(
        run.session_id,
        run.session_number,
        run.session_status,
        run_id,
        number,
        RunStatus.RUNNING,
        [],
    )
    return ctx.run


def start_run(db: Session, *, station_name: str, actor: Actor) -> StationView:
    """Start the next run of the running session; commits. The station then."""
    ctx = _context(db, station_name, lock_station=True, lock_timeline=True)
    run = _running(db, ctx)
    if run.run_status == RunStatus.RUNNING:
        progress = run_progress(run, ctx.protocol)
        waiting = [s.category for s in progress.open] + progress.pending
        raise Conflict(
            f"run {run.run_number} is still running (waiting for {', '.join(waiting)}); "
            "end it first or finish its categories"
        )
    _open_next_run(ctx)
    view = _view(db, ctx)
    db.commit()
    return view


def end_run(db: Session, *, station_name: str, actor: Actor) -> StationView:
    """End the running run early (unanswered categories stay unanswered); commits. The station
    then."""
    ctx = _context(db, station_name, lock_station=True, lock_timeline=True)
    run = _running(db, ctx)
    if run.run_status != RunStatus.RUNNING:
        raise Conflict(
            f"run {run.run_number} is already over; expected: {expected_next(db, ctx).message}"
        )
    _close_run(ctx, run, RunStatus.ENDED_EARLY, actor)
    view = _view(db, ctx)
    db.commit()
    return view


# ------------------------------------------------------------------------------ prompts, answers


def _category_index(ctx: Context, category: str) -> int:
    for index, spec in enumerate(ctx.protocol.categories):
        if spec.name == category:
            return index
    names = ", ".join(c.name for c in ctx.protocol.categories)
    raise InvalidInput(f"unknown category {category!r}: expected one of {names}")


@functools.lru_cache(maxsize=256)
def _prompt_salt(allocation_seed: str) -> int:
    digest = hashlib.sha256(f"prompt:{allocation_seed}".encode()).digest()
    return int.from_bytes(digest[:8], "big")


def _rng(ctx: Context, run: RunState, category_index: int) -> np.random.Generator:
    """A generator per (study secret, participant, run, category): unpredictable yet replayable."""
    salt = _prompt_salt(ctx.participant.allocation_seed)
    return np.random.default_rng([salt, ctx.participant.id, run.run_id, category_index])


def _learner_row(ctx: Context, category: str) -> LearnerRow:
    row = step_store.learner(ctx.cursor, participant_id=ctx.participant.id, category=category)
    if row is None:  # pragma: no cover - learners are created with the participant
        raise NotFound(f"{ctx.participant.code} has no learner for {category!r}")
    return row


def _spec(row: LearnerRow) -> learners.LearnerSpec:
    return learners.LearnerSpec(row.kind, row.n_arms, dict(row.config), row.checkpoint_sha256)


def _live_learner(ctx: Context, row: LearnerRow) -> Learner:
    """The learner at the row's version: the process's live copy, or rebuilt from its state."""

    def rebuild() -> Learner:
        learner = learners.build(_spec(row))
        learner.load_state_dict(step_store.learner_state(ctx.cursor, learner_id=row.id))
        return learner

    return learner_cache.of(ctx.cursor.db).take(row.id, row.version, rebuild)


@dataclass(frozen=True)
class PromptResult:
    """A prompt and whether this request created it (False: the open prompt, handed out again)."""

    prompt: Step
    created: bool
    session_number: int
    run_number: int
    learners_shown: bool = True
    """Whether staff may see the learner's figures (False while the study is blinded)."""
    language: str = "en"
    """The language the question is in: the participant's."""


def _refuse_withdrawn(ctx: Context) -> None:
    """A withdrawn participant's learners never change again (an acknowledged answer still
    replays: that happened before the withdrawal)."""
    if ctx.participant.status == ParticipantStatus.WITHDRAWN:
        raise Conflict(
            f"{ctx.participant.code} has withdrawn: no more prompts or answers; "
            "seat another participant at this station"
        )


def _preferred(ctx: Context, category: str, probabilities: list[float]) -> float | None:
    """The probability of the category's preferred question, if the protocol names one."""
    preferred = ctx.protocol.category(category).preferred
    return None if preferred is None else probabilities[preferred]


def request_prompt(
    db: Session,
    *,
    station_name: str,
    category: str,
    actor: Actor,
    device_id: int | None = None,
    seat: Seat | None = None,
    zone: str | None = None,
) -> PromptResult:
    """Choose the question for ``category`` with the participant's learner; commits.

    ``seat``: the station's seat as a robot's device brings it (read in this transaction).
    ``zone``: the trigger zone the client says the participant walked into; stored with a new
    step (an open prompt handed out again keeps the zone it was first asked in)."""
    ctx = _context(db, station_name, seat=seat, lock_timeline=True)
    _refuse_withdrawn(ctx)
    index = _category_index(ctx, category)
    run = _running(db, ctx)
    if run.run_status != RunStatus.RUNNING:
        run = _open_next_run(ctx)
    progress = run_progress(run, ctx.protocol)
    for step in progress.open:
        if step.category == category:
            db.commit()
            return PromptResult(
                step,
                False,
                run.session_number,
                run.run_number,
                ctx.learners_shown,
                ctx.protocol.default_language,
            )
    if category in progress.answered:
        waiting = [s.category for s in progress.open] + progress.pending
        raise Conflict(
            f"{category} was already answered in run {run.run_number} of "
            f"{session_label(run.session_number)}; expected one of: {', '.join(waiting)}"
        )
    row = _learner_row(ctx, category)
    learner = _live_learner(ctx, row)
    probabilities = learners.probabilities_list(learner)
    action = int(learner.select(_rng(ctx, run, index)))
    learner_cache.of(ctx.cursor.db).put(row.id, row.version, learner)  # choosing changes no state
    step = step_store.insert_prompt(
        ctx.cursor,
        participant_id=ctx.participant.id,
        run_id=run.run_id,
        category=category,
        action=action,
        question=ctx.protocol.categories[index].questions[action],
        probabilities=probabilities,
        learner_version=row.version,
        adapts=run.session_number != FAMILIARISATION,
        p_preferred=_preferred(ctx, category, probabilities),
        device_id=device_id,
        actor=actor.name,
        zone=zone,
    )
    events.publish(
        db,
        topics=_topics(ctx),
        type="prompt_opened",
        participant=ctx.participant.code,
        step_id=step.id,
        category=category,
        action=action,
        site=_site(ctx),
    )
    db.commit()
    return PromptResult(
        step,
        True,
        run.session_number,
        run.run_number,
        ctx.learners_shown,
        ctx.protocol.default_language,
    )


@dataclass(frozen=True)
class AnswerResult:
    """An answer and its reply; ``replayed`` when it was recorded by an earlier request."""

    answer: StoredAnswer
    prompt: Step
    replayed: bool
    run_completed: bool
    session_completed: bool
    expected: Expected
    learners_shown: bool = True
    """Whether staff may see the reply's level and the learner's figures."""


def _completed_by(ctx: Context, run: RunState, existing: StoredAnswer) -> tuple[bool, bool]:
    """Whether ``existing`` completed its run and its session, from what is stored.

    A run completes in the transaction of its last answer, and a run's answers are serialised by
    the timeline lock, so the answer that completed a completed run is the run's newest one; it
    completed the session too when that run is the session's last (however the session ended).
    """
    if run.run_status != RunStatus.COMPLETED:
        return False, False
    newest = max((s.answer_id for s in run.steps if s.answer_id is not None), default=None)
    if newest != existing.id:
        return False, False
    return True, run.run_number >= runs_in(ctx.protocol, run.session_number)


def _replay(
    db: Session, ctx: Context, step: Step, *, answer: bool, idempotency_key: str
) -> AnswerResult:
    """The stored answer's reply again, exactly as first sent (``replayed`` aside); ``expected``
    is what the station should do now, which is the original unless the station moved on.
    ``ctx.run``: the step's run. Rolls back (nothing changes)."""
    assert step.answer_id is not None and ctx.run is not None
    existing = step_store.stored_answer(ctx.cursor, answer_id=step.answer_id)
    said = "yes" if existing.answer else "no"
    if existing.idempotency_key == idempotency_key and existing.answer != answer:
        raise Conflict(
            f"idempotency key {idempotency_key!r} was used for the answer {said!r} to step "
            f"{step.id}; use a new key for a new answer"
        )
    if existing.answer != answer:
        raise Conflict(
            f"step {step.id} was already answered {said!r}; a different answer is refused"
        )
    run_done, session_done = _completed_by(ctx, ctx.run, existing)
    if ctx.run.run_status != RunStatus.RUNNING:  # a later run may exist: expect from the latest
        ctx.run = step_store.latest_run(ctx.cursor, participant_id=ctx.participant.id)
    expected = expected_next(db, ctx)
    db.rollback()
    return AnswerResult(existing, step, True, run_done, session_done, expected, ctx.learners_shown)


def _step_context(db: Session, station_name: str, step_id: int, seat: Seat | None) -> Context:
    """The context of an answer: ``ctx.run`` is the step's run, read with the participant's
    timeline locked (PostgreSQL)."""
    ctx = _context(db, station_name, seat=seat, lock_timeline=True, latest_run=False)
    ctx.run = step_store.run_of_step(ctx.cursor, step_id=step_id, participant_id=ctx.participant.id)
    if ctx.run is None:
        raise NotFound(
            f"step {step_id} is not a step of {ctx.participant.code} at station "
            f"{ctx.seat.station_name!r}"
        )
    return ctx


def record_answer(
    db: Session,
    *,
    station_name: str,
    step_id: int,
    answer: bool,
    idempotency_key: str,
    actor: Actor,
    device_id: int | None = None,
    seat: Seat | None = None,
    heard: HowAnswered | None = None,
) -> AnswerResult:
    """Learn from a yes/no answer and choose the reply, exactly once; commits.

    ``seat``: the station's seat as a robot's device brings it (read in this transaction).
    ``heard``: how the participant answered, stored with the answer (a replay keeps the first)."""
    started = time.perf_counter()
    key = idempotency_key.strip()
    if not key or len(key) > 100 or not key.isprintable():
        raise InvalidInput("idempotency_key: give 1-100 printable characters, unique per answer")
    ctx = _step_context(db, station_name, step_id, seat)
    run = ctx.run
    assert run is not None
    step = run.step(step_id)
    assert step is not None
    if step.answer_id is not None:
        return _replay(db, ctx, step, answer=answer, idempotency_key=key)
    _refuse_withdrawn(ctx)
    if run.run_status != RunStatus.RUNNING:
        ctx.run = step_store.latest_run(ctx.cursor, participant_id=ctx.participant.id)
        raise Conflict(
            f"step {step_id} belongs to run {run.run_number}, which has ended; "
            f"expected: {expected_next(db, ctx).message}"
        )
    reward = ctx.protocol.reward.yes if answer else ctx.protocol.reward.no
    row = _learner_row(ctx, step.category)
    asked = {s.category for s in run.steps}
    answered = [s.category for s in run.steps if s.answer_id is not None]
    remaining = [s for s in run.steps if s.answer_id is None and s.id != step.id]
    pending = [c.name for c in ctx.protocol.categories if c.name not in asked]
    learner = None
    version = row.version
    if step.adapts:
        if row.version != step.learner_version:  # pragma: no cover - guarded by the timeline lock
            raise Conflict(f"the {step.category} learner moved on since step {step_id}")
        learner = _live_learner(ctx, row)
        learner.update(step.action, reward)
        after = learners.probabilities_list(learner)
        version = row.version + 1
    else:
        after = list(step.probabilities)
    reply = replies.choose_reply(
        ctx.protocol,
        _spec(row),
        before=step.probabilities,
        action=step.action,
        after=after,
        said_yes=answer,
    )
    stored = step_store.NewAnswer(
        prompt_id=step.id,
        participant_id=ctx.participant.id,
        answer=answer,
        reward=reward,
        probabilities_after=after,
        p_preferred=_preferred(ctx, step.category, after),
        probability=reply.probability,
        confidence_level=reply.level,
        confidence=reply.name,
        reply=reply.text,
        learner_version=version,
        idempotency_key=key,
        processing_ms=round((time.perf_counter() - started) * 1000.0, 3),
        device_id=device_id,
        actor=actor.name,
        heard=heard or NOT_SAID,
    )
    run_done = session_done = False
    try:
        # The writes, their events and the answer go to the database together (one round trip
        # on PostgreSQL); only the learner's save is checked afterwards.
        with ctx.cursor.batch():
            saved = (
                step_store.save_learner(ctx.cursor, row=row, state=learner.state_dict())
                if learner is not None
                else None
            )
            if not remaining and not pending:
                run_done = True
                session_done = _close_run(ctx, run, RunStatus.COMPLETED, actor)
            events.publish(
                db,
                topics=_topics(ctx),
                type="answer_recorded",
                participant=ctx.participant.code,
                step_id=step.id,
                category=step.category,
                answer=answer,
                confidence=reply.name,
                reply=reply.text,  # a room client says it when Wizard-of-Oz answered
                site=_site(ctx),
            )
            _audit(
                ctx,
                actor,
                "answer.recorded",
                {"step_id": step.id, "answer": answer, "learner_version": version},
            )
            events.send_pending(db)
            answer_id = step_store.insert_answer(ctx.cursor, stored)
    except IntegrityError:  # pragma: no cover - the timeline lock serialises a step's answers
        db.rollback()
        ctx = _step_context(db, station_name, step_id, None)
        assert ctx.run is not None
        recorded = ctx.run.step(step_id)
        assert recorded is not None and recorded.answer_id is not None
        return _replay(db, ctx, recorded, answer=answer, idempotency_key=key)
    if saved is not None and saved.count != 1:  # pragma: no cover - guarded by the timeline lock
        raise Conflict(f"the {step.category} learner moved on since step {step_id}")
    progress = RunProgress([*answered, step.category], remaining, pending)
    expected = expected_next(db, ctx, None if run_done else progress)
    db.commit()
    if learner is not None:
        learner_cache.of(db).put(row.id, version, learner)
    result = StoredAnswer(
        answer_id,
        answer,
        key,
        reply.text,
        reply.level,
        reply.name,
        reply.probability,
        after,
    )
    return AnswerResult(result, step, False, run_done, session_done, expected, ctx.learners_shown)


# ---------------------------------------------------------------------------- the station view


@dataclass(frozen=True)
class StationView:
    """A snapshot of a station for robots, operator consoles and WebSocket resumption."""

    station: str
    participant: str | None
    study: str | None
    session: dict[str, Any] | None
    run: dict[str, Any] | None
    open_prompts: list[Step]
    expected: Expected
    learners_shown: bool = True
    """Whether staff may see the seated participant's learners (app.services.blinding)."""
    language: str | None = None
    """The seated participant's language: what the room and the robot speak (None: nobody)."""
    last_reply: dict[str, Any] | None = None
    """The robot's reply to the newest answer of the current run: a client that was away when
    it was given (a room offline during a Wizard-of-Oz answer) can still say it on return."""


def station_view(db: Session, *, station_name: str, seat: Seat | None = None) -> StationView:
    """Where the station stands and what it should do next (``seat``: as a device brings it)."""
    if seat is None:
        seat = step_store.station_seat(Cursor.of(db), name=station_name)
        if seat is None:
            get_station(db, station_name)  # raises NotFound naming the stations that exist
            raise AssertionError(station_name)  # pragma: no cover
    if seat.participant is None:
        return StationView(
            seat.station_name,
            None,
            None,
            None,
            None,
            [],
            Expected(
                "assign", f"an experimenter assigns a participant to station {seat.station_name!r}"
            ),
        )
    return _view(db, _context(db, station_name, seat=seat))


def _view(db: Session, ctx: Context) -> StationView:
    """The station as ``ctx`` has it: read in this transaction, or just changed by it (the
    experimenter's session and run commands answer with this, built before they commit)."""
    session_info = run_info = None
    open_prompts: list[Step] = []
    run = ctx.run
    if run is not None:
        session_info = {
            "number": run.session_number,
            "status": run.session_status,
            "runs": runs_in(ctx.protocol, run.session_number),
            "familiarisation": run.session_number == FAMILIARISATION,
        }
        progress = run_progress(run, ctx.protocol)
        run_info = {
            "number": run.run_number,
            "status": run.run_status,
            "answered": progress.answered,
            "pending": progress.pending,
        }
        if run.run_status == RunStatus.RUNNING:
            open_prompts = progress.open
    return StationView(
        ctx.seat.station_name,
        ctx.participant.code,
        ctx.participant.study_name,
        session_info,
        run_info,
        open_prompts,
        expected_next(db, ctx),
        ctx.learners_shown,
        ctx.protocol.default_language,
        _last_reply(run),
    )


def _last_reply(run: RunState | None) -> dict[str, Any] | None:
    """The newest answered step of ``run`` and the robot's reply to it (None: none answered)."""
    answered = [s for s in run.steps if s.answer_id is not None] if run is not None else []
    if not answered:
        return None
    newest = max(answered, key=lambda s: s.answer_id or 0)
    return {
        "step_id": newest.id,
        "category": newest.category,
        "reply": newest.reply,
        "confidence": newest.confidence,
    }


def last_step(db: Session, *, participant_id: int) -> tuple[Prompt, Answer | None] | None:
    """The participant's most recent prompt and its answer, if any (for the operator console)."""
    found = db.execute(
        select(Prompt, Answer)
        .outerjoin(Answer, Answer.prompt_id == Prompt.id)
        .where(Prompt.participant_id == participant_id)
        .order_by(Prompt.id.desc())
        .limit(1)
    ).first()
    return (found[0], found[1]) if found else None
