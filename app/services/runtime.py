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
- an answer locks its run and learner rows, updates the learner, stores the new state with a new
  version, appends the answer and commits — all or nothing; repeating it (same idempotency key, or
  the same answer again) returns the stored reply without a second update; a different answer is
  refused with 409.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sqlalchemy import bindparam, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict, InvalidInput, NotFound
from app.protocol import Protocol
from app.services import audit, learners, questionnaires
from app.services.audit import Actor
from app.services.stations import get_station, participant_topic, station_topic, study_topic
from app.services.studies import protocol_of
from app.tables import (
    Answer,
    LearnerState,
    Participant,
    ParticipantStatus,
    Prompt,
    Run,
    RunStatus,
    SessionStatus,
    Station,
    Study,
    StudySession,
    utcnow,
)
from models.replies import confidence_level

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
    """Who is at a station and where their timeline stands."""

    station: Station
    participant: Participant
    study: Study
    protocol: Protocol
    session: StudySession | None
    run: Run | None
    run_locked: bool = False


# The hot path's statements, built once: SQLAlchemy's expression building costs as much as running
# a small query, and every prompt and answer needs these.
_SEATED = (
    select(Station, Participant, Study)
    .outerjoin(Participant, Participant.id == Station.participant_id)
    .outerjoin(Study, Study.id == Participant.study_id)
    .where(Station.name == bindparam("station"))
)
_SEATED_LOCKED = _SEATED.with_for_update(of=Station)
_LATEST = (
    select(StudySession, Run)
    .outerjoin(Run, Run.session_id == StudySession.id)
    .where(StudySession.participant_id == bindparam("participant"))
    .order_by(StudySession.number.desc(), Run.number.desc())
    .limit(1)
)
_LATEST_RUN_LOCKED = (
    select(StudySession, Run)
    .join(Run, Run.session_id == StudySession.id)
    .where(StudySession.participant_id == bindparam("participant"))
    .order_by(StudySession.number.desc(), Run.number.desc())
    .limit(1)
    .with_for_update(of=Run)
    .execution_options(populate_existing=True)
)
""":data:`_LATEST` with the run row-locked (PostgreSQL) in the same statement: prompts and answers
lock the current run before reading its prompts, and this spares them a separate locking query.
An inner join, as every session has a run from the moment it starts; PostgreSQL returns the run
as it is once the lock is granted, as a refresh after locking would."""
_RUN_PROMPTS = (
    select(Prompt, Answer.id)
    .outerjoin(Answer, Answer.prompt_id == Prompt.id)
    .where(Prompt.run_id == bindparam("run"))
    .order_by(Prompt.id)
)
_LEARNER = (
    select(LearnerState)
    .where(
        LearnerState.participant_id == bindparam("participant"),
        LearnerState.category == bindparam("category"),
    )
    .with_for_update()
)
_ANSWER_OF = select(Answer).where(Answer.prompt_id == bindparam("prompt"))


def _seated(
    db: Session, station_name: str, loaded: Station | None, lock_station: bool
) -> tuple[Station, Participant | None, Study | None]:
    """The station, its participant and their study: as ``loaded`` if given, else one query.

    A robot's device brings its station with participant and study already loaded
    (:func:`app.services.stations.authenticate_device`); a station row lock always queries.
    """
    if loaded is not None and not lock_station:
        assert loaded.name == station_name, (loaded.name, station_name)
        participant = loaded.participant
        return loaded, participant, participant.study if participant is not None else None
    query = _SEATED_LOCKED if lock_station else _SEATED
    found = db.execute(query, {"station": station_name}).first()
    if found is None:
        get_station(db, station_name)  # raises NotFound naming the stations that exist
    assert found is not None
    return found[0], found[1], found[2]


def _context(
    db: Session,
    station_name: str,
    *,
    station: Station | None = None,
    lock_station: bool = False,
    lock_run: bool = False,
) -> Context:
    """Station, participant, study and the latest session and run: one query when ``station``
    comes loaded (see :func:`_seated`), two otherwise. ``lock_run``: the run comes row-locked
    (PostgreSQL), as :func:`_lock_run` would lock it."""
    station, participant, study = _seated(db, station_name, station, lock_station)
    if participant is None:
        raise Conflict(
            f"no participant is assigned to station {station.name!r}: "
            "an experimenter assigns one first"
        )
    assert study is not None
    query = _LATEST_RUN_LOCKED if lock_run else _LATEST
    latest = db.execute(query, {"participant": participant.id}).first()
    session, run = (latest[0], latest[1]) if latest is not None else (None, None)
    return Context(
        station, participant, study, protocol_of(study), session, run, lock_run and run is not None
    )


def _lock(db: Session, row: Run | StudySession) -> None:
    """Row-lock on PostgreSQL; SQLite's write transactions are exclusive already."""
    if db.get_bind().dialect.name == "postgresql":
        db.refresh(row, with_for_update=True)


def _lock_run(db: Session, ctx: Context, run: Run) -> None:
    """Row-lock ``run`` unless the context's query already did."""
    if not (ctx.run_locked and run is ctx.run):
        _lock(db, run)


@dataclass(frozen=True)
class RunProgress:
    """Which categories of a run are answered, open (prompted, unanswered) or still to come."""

    answered: list[str]
    open: list[Prompt]
    pending: list[str]


def run_progress(db: Session, run: Run, protocol: Protocol) -> RunProgress:
    """The state of each category in a run (one query)."""
    rows = db.execute(_RUN_PROMPTS, {"run": run.id}).all()
    answered = [prompt.category for prompt, answer_id in rows if answer_id is not None]
    open_prompts = [prompt for prompt, answer_id in rows if answer_id is None]
    asked = {prompt.category for prompt, _ in rows}
    pending = [c.name for c in protocol.categories if c.name not in asked]
    return RunProgress(answered, open_prompts, pending)


# ------------------------------------------------------------------------------ expected next


@dataclass(frozen=True)
class Expected:
    """What the station should do next, for people and for programs."""

    action: str
    message: str
    categories: list[str] = field(default_factory=list)
    step_id: int | None = None
    session: int | None = None


def session_gate(db: Session, participant: Participant, protocol: Protocol, number: int) -> str:
    """Why session ``number`` cannot start yet ('' when it can): consent and questionnaires."""
    return questionnaires.session_blocker(db, participant, protocol, number)


def expected_next(db: Session, ctx: Context, progress: RunProgress | None = None) -> Expected:
    """The next step of the timeline at this station (``progress``: the current run's, if known)."""
    protocol, participant = ctx.protocol, ctx.participant
    code = participant.code
    if participant.status == ParticipantStatus.WITHDRAWN:
        return Expected("none", f"{code} has withdrawn: assign another participant")
    session, run = ctx.session, ctx.run
    if session is not None and session.status == SessionStatus.RUNNING and run is not None:
        label = session_label(session.number)
        if run.status == RunStatus.RUNNING:
            progress = progress or run_progress(db, run, protocol)
            if progress.open:
                prompt = progress.open[0]
                return Expected(
                    "answer",
                    f"record {code}'s yes/no answer to step {prompt.id} ({prompt.category})",
                    [p.category for p in progress.open],
                    step_id=prompt.id,
                    session=session.number,
                )
            return Expected(
                "prompt",
                f"prompt one of {', '.join(progress.pending)} (run {run.number} of {label})",
                progress.pending,
                session=session.number,
            )
        return Expected(
            "prompt",
            f"run {run.number} of {label} is over: prompting any category starts run "
            f"{run.number + 1}",
            [c.name for c in protocol.categories],
            session=session.number,
        )
    next_number = first_session_number(protocol) if session is None else session.number + 1
    if next_number > protocol.schedule.sessions:
        return Expected("done", f"{code} has finished every session")
    blocker = session_gate(db, participant, protocol, next_number)
    if blocker:
        return Expected("wait", blocker, session=next_number)
    return Expected(
        "start_session",
        f"an experimenter starts {session_label(next_number)} for {code}",
        session=next_number,
    )


# ------------------------------------------------------------------------------- sessions, runs


def _topics(ctx: Context) -> list[str]:
    return [station_topic(ctx.station), study_topic(ctx.study.id)]


def start_session(db: Session, *, station_name: str, actor: Actor) -> StudySession:
    """Start the participant's next session (and its first run); commits."""
    ctx = _context(db, station_name, lock_station=True)
    code = ctx.participant.code
    if ctx.participant.status != ParticipantStatus.ACTIVE:
        raise Conflict(f"{code} is {ctx.participant.status}: no further sessions")
    if ctx.session is not None and ctx.session.status == SessionStatus.RUNNING:
        raise Conflict(
            f"{session_label(ctx.session.number)} is already running for {code}; "
            "expected: " + expected_next(db, ctx).message
        )
    expected = expected_next(db, ctx)
    if expected.action != "start_session":
        raise Conflict(f"cannot start a session for {code}: {expected.message}")
    number = expected.session
    assert number is not None
    session = StudySession(
        participant_id=ctx.participant.id,
        station_id=ctx.station.id,
        number=number,
        started_by=actor.name,
    )
    db.add(session)
    db.flush()
    db.add(Run(session_id=session.id, participant_id=ctx.participant.id, number=1))
    audit.record(
        db,
        actor=actor,
        action="session.started",
        study_id=ctx.study.id,
        subject=code,
        details={"session": number, "station": ctx.station.name},
    )
    events.publish(
        db, topics=_topics(ctx), type="session_started", participant=code, session=number
    )
    try:
        db.commit()
    except IntegrityError as exc:
        db.rollback()
        raise Conflict(f"{session_label(number)} was started concurrently; reload") from exc
    return session


def _close_session(
    db: Session, ctx: Context, session: StudySession, status: SessionStatus, actor: Actor
) -> None:
    session.status = status
    session.ended_at = utcnow()
    session.ended_by = actor.name
    last = ctx.protocol.schedule.sessions
    if session.number == last and ctx.participant.status == ParticipantStatus.ACTIVE:
        ctx.participant.status = ParticipantStatus.COMPLETED
    audit.record(
        db,
        actor=actor,
        action="session.ended",
        study_id=ctx.study.id,
        subject=ctx.participant.code,
        details={"session": session.number, "status": status},
    )
    events.publish(
        db,
        topics=[*_topics(ctx), participant_topic(ctx.participant.id)],
        type="session_ended",
        participant=ctx.participant.code,
        session=session.number,
        status=str(status),
    )


def _close_run(db: Session, ctx: Context, run: Run, status: RunStatus, actor: Actor) -> bool:
    """Close a run; closes its session too when it was the last. Returns whether it did."""
    run.status = status
    run.ended_at = utcnow()
    session = ctx.session
    assert session is not None
    events.publish(
        db,
        topics=_topics(ctx),
        type="run_ended",
        participant=ctx.participant.code,
        session=session.number,
        run=run.number,
        status=str(status),
    )
    if run.number < runs_in(ctx.protocol, session.number):
        return False
    early = status == RunStatus.ENDED_EARLY or db.scalar(
        select(func.count()).where(
            Run.session_id == session.id, Run.status == RunStatus.ENDED_EARLY
        )
    )
    _close_session(
        db, ctx, session, SessionStatus.ENDED_EARLY if early else SessionStatus.COMPLETED, actor
    )
    return True


def end_session(db: Session, *, station_name: str, actor: Actor) -> StudySession:
    """End the running session early (its open run too); commits."""
    ctx = _context(db, station_name, lock_station=True)
    session = ctx.session
    if session is None or session.status != SessionStatus.RUNNING:
        raise Conflict(
            f"no session is running for {ctx.participant.code}; expected: "
            + expected_next(db, ctx).message
        )
    _lock(db, session)
    if ctx.run is not None and ctx.run.status == RunStatus.RUNNING:
        ctx.run.status = RunStatus.ENDED_EARLY
        ctx.run.ended_at = utcnow()
    _close_session(db, ctx, session, SessionStatus.ENDED_EARLY, actor)
    db.commit()
    return session


def _open_next_run(db: Session, ctx: Context) -> Run:
    session, run = ctx.session, ctx.run
    assert session is not None and run is not None
    total = runs_in(ctx.protocol, session.number)
    if run.number >= total:  # pragma: no cover - the session would have closed with its last run
        raise Conflict(f"all {total} runs of {session_label(session.number)} are over")
    new_run = Run(session_id=session.id, participant_id=ctx.participant.id, number=run.number + 1)
    db.add(new_run)
    db.flush()
    events.publish(
        db,
        topics=_topics(ctx),
        type="run_started",
        participant=ctx.participant.code,
        session=session.number,
        run=new_run.number,
    )
    ctx.run = new_run
    return new_run


def _running_session(db: Session, ctx: Context) -> StudySession:
    session = ctx.session
    if session is None or session.status != SessionStatus.RUNNING:
        raise Conflict(
            f"no session is running for {ctx.participant.code}; expected: "
            + expected_next(db, ctx).message
        )
    return session


def start_run(db: Session, *, station_name: str, actor: Actor) -> Run:
    """Start the next run of the running session; commits."""
    ctx = _context(db, station_name, lock_station=True)
    _running_session(db, ctx)
    assert ctx.run is not None
    if ctx.run.status == RunStatus.RUNNING:
        pending = run_progress(db, ctx.run, ctx.protocol)
        waiting = [p.category for p in pending.open] + pending.pending
        raise Conflict(
            f"run {ctx.run.number} is still running (waiting for {', '.join(waiting)}); "
            "end it first or finish its categories"
        )
    run = _open_next_run(db, ctx)
    db.commit()
    return run


def end_run(db: Session, *, station_name: str, actor: Actor) -> Run:
    """End the running run early (unanswered categories stay unanswered); commits."""
    ctx = _context(db, station_name, lock_station=True)
    _running_session(db, ctx)
    run = ctx.run
    assert run is not None
    if run.status != RunStatus.RUNNING:
        raise Conflict(
            f"run {run.number} is already over; expected: {expected_next(db, ctx).message}"
        )
    _lock(db, run)
    _close_run(db, ctx, run, RunStatus.ENDED_EARLY, actor)
    db.commit()
    return run


# ------------------------------------------------------------------------------ prompts, answers


def _category_index(ctx: Context, category: str) -> int:
    for index, spec in enumerate(ctx.protocol.categories):
        if spec.name == category:
            return index
    names = ", ".join(c.name for c in ctx.protocol.categories)
    raise InvalidInput(f"unknown category {category!r}: expected one of {names}")


def _rng(ctx: Context, run: Run, category_index: int) -> np.random.Generator:
    """A generator per (study secret, participant, run, category): unpredictable yet replayable."""
    digest = hashlib.sha256(f"prompt:{ctx.study.allocation_seed}".encode()).digest()
    salt = int.from_bytes(digest[:8], "big")
    return np.random.default_rng([salt, ctx.participant.id, run.id, category_index])


def _learner_row(db: Session, participant_id: int, category: str) -> LearnerState:
    row = db.scalar(_LEARNER, {"participant": participant_id, "category": category})
    if row is None:  # pragma: no cover - learners are created with the participant
        raise NotFound(f"participant {participant_id} has no learner for {category!r}")
    return row


@dataclass(frozen=True)
class PromptResult:
    """A prompt and whether this request created it (False: the open prompt, handed out again)."""

    prompt: Prompt
    created: bool
    session_number: int
    run_number: int


def _refuse_withdrawn(ctx: Context) -> None:
    """A withdrawn participant's learners never change again (an acknowledged answer still
    replays: that happened before the withdrawal)."""
    if ctx.participant.status == ParticipantStatus.WITHDRAWN:
        raise Conflict(
            f"{ctx.participant.code} has withdrawn: no more prompts or answers; "
            "seat another participant at this station"
        )


def request_prompt(
    db: Session,
    *,
    station_name: str,
    category: str,
    actor: Actor,
    device_id: int | None = None,
    station: Station | None = None,
) -> PromptResult:
    """Choose the question for ``category`` with the participant's learner; commits.

    ``station``: the station as a robot's device brings it (see :func:`_seated`)."""
    ctx = _context(db, station_name, station=station, lock_run=True)
    _refuse_withdrawn(ctx)
    index = _category_index(ctx, category)
    session = _running_session(db, ctx)
    run = ctx.run
    assert run is not None
    _lock_run(db, ctx, run)
    if run.status != RunStatus.RUNNING:
        run = _open_next_run(db, ctx)
    progress = run_progress(db, run, ctx.protocol)
    for prompt in progress.open:
        if prompt.category == category:
            db.commit()
            return PromptResult(prompt, False, session.number, run.number)
    if category in progress.answered:
        waiting = [p.category for p in progress.open] + progress.pending
        raise Conflict(
            f"{category} was already answered in run {run.number} of "
            f"{session_label(session.number)}; expected one of: {', '.join(waiting)}"
        )
    row = _learner_row(db, ctx.participant.id, category)
    learner = learners.cache.take(row)
    probabilities = learners.probabilities_list(learner)
    action = int(learner.select(_rng(ctx, run, index)))
    learners.cache.put(row.id, row.version, learner)
    prompt = Prompt(
        participant_id=ctx.participant.id,
        run_id=run.id,
        category=category,
        action=action,
        question=ctx.protocol.categories[index].questions[action],
        probabilities=probabilities,
        p_preferred=_preferred(ctx, category, probabilities),
        learner_version=row.version,
        adapts=session.number != FAMILIARISATION,
        device_id=device_id,
        actor=actor.name,
    )
    db.add(prompt)
    db.flush()
    events.publish(
        db,
        topics=_topics(ctx),
        type="prompt_opened",
        participant=ctx.participant.code,
        step_id=prompt.id,
        category=category,
        action=action,
    )
    db.commit()
    return PromptResult(prompt, True, session.number, run.number)


@dataclass(frozen=True)
class AnswerResult:
    """An answer and its reply; ``replayed`` when it was recorded by an earlier request."""

    answer: Answer
    prompt: Prompt
    replayed: bool
    run_completed: bool
    session_completed: bool
    expected: Expected


def _completed_by(db: Session, ctx: Context, run: Run, existing: Answer) -> tuple[bool, bool]:
    """Whether ``existing`` completed its run and its session, from what is stored.

    A run completes in the transaction of its last answer, and a run's answers are serialised by
    the run lock, so the answer that completed a completed run is the run's newest one; it
    completed the session too when that run is the session's last (however the session ended).
    """
    if run.status != RunStatus.COMPLETED:
        return False, False
    rows = db.execute(_RUN_PROMPTS, {"run": run.id}).all()
    newest = max((answer_id for _, answer_id in rows if answer_id is not None), default=None)
    if newest != existing.id:
        return False, False
    session = ctx.session if ctx.session and ctx.session.id == run.session_id else None
    session = session or db.get(StudySession, run.session_id)
    assert session is not None
    return True, run.number >= runs_in(ctx.protocol, session.number)


def _replay(
    db: Session,
    ctx: Context,
    run: Run,
    existing: Answer,
    prompt: Prompt,
    *,
    answer: bool,
    idempotency_key: str,
) -> AnswerResult:
    """The stored answer's reply again, exactly as first sent (``replayed`` aside); ``expected``
    is what the station should do now, which is the original unless the station moved on."""
    said = "yes" if existing.answer else "no"
    if existing.idempotency_key == idempotency_key and existing.answer != answer:
        raise Conflict(
            f"idempotency key {idempotency_key!r} was used for the answer {said!r} to step "
            f"{prompt.id}; use a new key for a new answer"
        )
    if existing.answer != answer:
        raise Conflict(
            f"step {prompt.id} was already answered {said!r}; a different answer is refused"
        )
    run_done, session_done = _completed_by(db, ctx, run, existing)
    return AnswerResult(existing, prompt, True, run_done, session_done, expected_next(db, ctx))


def _prompt_at_station(db: Session, ctx: Context, step_id: int) -> Prompt:
    prompt = db.get(Prompt, step_id)
    if prompt is None or prompt.participant_id != ctx.participant.id:
        raise NotFound(
            f"step {step_id} is not a step of {ctx.participant.code} at station "
            f"{ctx.station.name!r}"
        )
    return prompt


@dataclass(frozen=True)
class _Step:
    """The prompt being answered, its run, the run's prompts, and the prompt's answer if any."""

    prompt: Prompt
    run: Run
    rows: list[tuple[Prompt, int | None]]
    answer_id: int | None


def _step_in_run(
    db: Session, ctx: Context, step_id: int, run: Run
) -> tuple[Prompt, int | None, list[tuple[Prompt, int | None]]] | None:
    """``step_id`` among the prompts of ``run`` (one query, locked first on PostgreSQL)."""
    _lock_run(db, ctx, run)
    rows: list[tuple[Prompt, int | None]] = [
        (prompt, answer_id) for prompt, answer_id in db.execute(_RUN_PROMPTS, {"run": run.id})
    ]
    for prompt, answer_id in rows:
        if prompt.id == step_id:
            return prompt, answer_id, rows
    return None


def _find_step(db: Session, ctx: Context, step_id: int) -> _Step:
    """The step and what the answer needs to know about its run.

    Nearly always the step belongs to the current run: its prompts (with their answers' ids) are
    read in one query that serves the duplicate check, the run-completion check and the reply.
    Otherwise (an old step, or not this participant's) the step is looked up on its own.
    """
    if ctx.run is not None:
        found = _step_in_run(db, ctx, step_id, ctx.run)
        if found is not None:
            return _Step(found[0], ctx.run, found[2], found[1])
    prompt = _prompt_at_station(db, ctx, step_id)
    run = db.get(Run, prompt.run_id)
    assert run is not None
    found = _step_in_run(db, ctx, step_id, run)
    assert found is not None
    return _Step(prompt, run, found[2], found[1])


def _preferred(ctx: Context, category: str, probabilities: list[float]) -> float | None:
    """The probability of the category's preferred question, if the protocol names one."""
    preferred = ctx.protocol.category(category).preferred
    return None if preferred is None else probabilities[preferred]


def _reply_probability(ctx: Context, prompt: Prompt, after: list[float]) -> float:
    basis = ctx.protocol.replies.basis
    return float(prompt.probabilities[prompt.action] if basis == "chosen" else after[prompt.action])


def record_answer(
    db: Session,
    *,
    station_name: str,
    step_id: int,
    answer: bool,
    idempotency_key: str,
    actor: Actor,
    device_id: int | None = None,
    station: Station | None = None,
) -> AnswerResult:
    """Learn from a yes/no answer and choose the reply, exactly once; commits.

    Every read comes before the first change, so the changes (learner, answer, audit row, run)
    are flushed once, at commit. ``station``: as a robot's device brings it (:func:`_seated`).
    """
    started = time.perf_counter()
    key = idempotency_key.strip()
    if not key or len(key) > 100:
        raise InvalidInput("idempotency_key: give 1-100 characters, unique per answer")
    ctx = _context(db, station_name, station=station, lock_run=True)
    step = _find_step(db, ctx, step_id)
    prompt, run = step.prompt, step.run
    if step.answer_id is not None:
        existing = db.get(Answer, step.answer_id)
        assert existing is not None
        result = _replay(db, ctx, run, existing, prompt, answer=answer, idempotency_key=key)
        db.rollback()
        return result
    _refuse_withdrawn(ctx)
    if run.status != RunStatus.RUNNING:
        raise Conflict(
            f"step {step_id} belongs to run {run.number}, which has ended; "
            f"expected: {expected_next(db, ctx).message}"
        )
    reward = ctx.protocol.reward.yes if answer else ctx.protocol.reward.no
    row = _learner_row(db, ctx.participant.id, prompt.category)
    asked = {p.category for p, _ in step.rows}
    answered = [p.category for p, answer_id in step.rows if answer_id is not None]
    remaining = [p for p, answer_id in step.rows if answer_id is None and p.id != prompt.id]
    pending = [c.name for c in ctx.protocol.categories if c.name not in asked]
    # Reads end here: from now on the session only collects changes.
    learner = None
    if prompt.adapts:
        if row.version != prompt.learner_version:  # pragma: no cover - guarded by the run lock
            raise Conflict(f"the {prompt.category} learner moved on since step {step_id}")
        learner = learners.cache.take(row)
        learner.update(prompt.action, reward)
        after = learners.probabilities_list(learner)
        row.state = learner.state_dict()
        row.version += 1
        row.updated_at = utcnow()
    else:
        after = list(prompt.probabilities)
    probability = _reply_probability(ctx, prompt, after)
    level = confidence_level(probability, ctx.protocol.replies.thresholds)
    reply = ctx.protocol.replies.levels[level]
    run_done = session_done = False
    if not remaining and not pending:
        ctx.run = run
        run_done = True
        session_done = _close_run(db, ctx, run, RunStatus.COMPLETED, actor)
    events.publish(
        db,
        topics=_topics(ctx),
        type="answer_recorded",
        participant=ctx.participant.code,
        step_id=prompt.id,
        category=prompt.category,
        answer=answer,
        confidence=reply.name,
    )
    audit.record(
        db,
        actor=actor,
        action="answer.recorded",
        study_id=ctx.study.id,
        subject=ctx.participant.code,
        details={"step_id": prompt.id, "answer": answer, "learner_version": row.version},
    )
    record = Answer(
        prompt_id=prompt.id,
        participant_id=ctx.participant.id,
        answer=answer,
        reward=reward,
        probabilities_after=after,
        p_preferred=_preferred(ctx, prompt.category, after),
        probability=probability,
        confidence_level=level,
        confidence=reply.name,
        reply=reply.text,
        learner_version=row.version,
        idempotency_key=key,
        device_id=device_id,
        actor=actor.name,
        processing_ms=round((time.perf_counter() - started) * 1000.0, 3),
    )
    db.add(record)
    progress = RunProgress([*answered, prompt.category], remaining, pending)
    expected = expected_next(db, ctx, None if run_done else progress)
    try:
        db.commit()
    except IntegrityError:
        db.rollback()
        existing = db.scalar(_ANSWER_OF, {"prompt": prompt.id})
        if existing is None:
            raise
        ctx = _context(db, station_name)
        stored_run = db.get(Run, prompt.run_id)
        assert stored_run is not None
        return _replay(db, ctx, stored_run, existing, prompt, answer=answer, idempotency_key=key)
    if learner is not None:
        learners.cache.put(row.id, row.version, learner)
    return AnswerResult(record, prompt, False, run_done, session_done, expected)


# ---------------------------------------------------------------------------- the station view


@dataclass(frozen=True)
class StationView:
    """A snapshot of a station for robots, operator consoles and WebSocket resumption."""

    station: str
    participant: str | None
    study: str | None
    session: dict[str, Any] | None
    run: dict[str, Any] | None
    open_prompts: list[Prompt]
    expected: Expected


def station_view(db: Session, *, station_name: str, station: Station | None = None) -> StationView:
    """Where the station stands and what it should do next (``station``: see :func:`_seated`)."""
    station, participant, _ = _seated(db, station_name, station, lock_station=False)
    if participant is None:
        return StationView(
            station.name,
            None,
            None,
            None,
            None,
            [],
            Expected(
                "assign", f"an experimenter assigns a participant to station {station.name!r}"
            ),
        )
    ctx = _context(db, station_name, station=station)
    session_info = run_info = None
    open_prompts: list[Prompt] = []
    if ctx.session is not None:
        session_info = {
            "number": ctx.session.number,
            "status": ctx.session.status,
            "runs": runs_in(ctx.protocol, ctx.session.number),
            "familiarisation": ctx.session.number == FAMILIARISATION,
        }
    if ctx.run is not None:
        progress = run_progress(db, ctx.run, ctx.protocol)
        run_info = {
            "number": ctx.run.number,
            "status": ctx.run.status,
            "answered": progress.answered,
            "pending": progress.pending,
        }
        if ctx.run.status == RunStatus.RUNNING:
            open_prompts = progress.open
    return StationView(
        station.name,
        ctx.participant.code,
        ctx.study.name,
        session_info,
        run_info,
        open_prompts,
        expected_next(db, ctx),
    )


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
