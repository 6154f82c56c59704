"""The robot's hot path as a few hand-written statements on the driver's own cursor.

A prompt or an answer needs who holds the device key, the run the step belongs to with that run's
prompts, the learner's version (its state only when the process has no live copy), and then a few
rows appended or updated. Through SQLAlchemy's ORM each of those small statements cost 100–400 µs
of Python (compiled-statement lookup, row processing, identity map, the unit of work's flush),
several times what SQLite or PostgreSQL spend executing it, and an answer cost 5–6 × a no-op
request (docs/performance.md, "Robot API round trip"). Here they run on the DBAPI cursor of the
request's own session (:class:`app.sql.Cursor`), so they share its transaction: SQLite's ``BEGIN
IMMEDIATE`` and writer queue (app.db), live events published on commit (app.events), and rollback
on any error behave exactly as for ORM work.

Values are written in the form the ORM's column types store them (app.tables: UTC timestamps,
JSON/JSONB documents, booleans), so every other part of trustlab reads these rows through the ORM
unchanged; ``tests/app/test_step_store.py`` checks that round trip on both engines.

The timeline's rules live in app.services.sessions.runtime, which does all its reading and writing
here; the rest of trustlab (enrolment, questionnaires, dashboards, exports) uses the ORM.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from app.sql import Cursor, Statement, Written
from app.tables import ParticipantStatus, RunStatus, SessionStatus

# ------------------------------------------------------------------------------------ the seat


@dataclass(frozen=True, slots=True)
class Seated:
    """The participant seated at a station and their study."""

    id: int
    code: str
    status: str
    study_id: int
    study_name: str
    allocation_seed: str
    protocol_sha256: str
    unblinded: bool
    """Whether an admin has unblinded the study (app.services.blinding)."""
    language: str | None = None
    """The participant's language (None: not chosen, the study's first applies)."""
    site: str | None = None
    """The participant's site (None in a study without sites): the session's live events name it,
    so that accounts limited to other sites do not hear them
    (app.services.privacy.sites.reaches)."""


@dataclass(frozen=True, slots=True)
class Seat:
    """A station and whoever sits there (``participant`` None when nobody does)."""

    station_id: int
    station_name: str
    participant: Seated | None


@dataclass(frozen=True, slots=True)
class DeviceSeat:
    """A live device key's device, and its station's seat."""

    device_id: int
    label: str
    seat: Seat

    @property
    def actor_name(self) -> str:
        """How the device appears in the audit log and the step log."""
        return f"{self.seat.station_name}/{self.label}"[:64]


_SEAT_COLUMNS = """s.id, s.name, p.id, p.code, p.status, p.study_id, st.name, st.allocation_seed,
    st.protocol_sha256, st.unblinded_at IS NOT NULL, p.language, p.site"""
_SEATED_JOINS = """LEFT JOIN participant p ON p.id = s.participant_id
    LEFT JOIN study st ON st.id = p.study_id"""

_DEVICE_SEAT = Statement(
    f"""SELECT d.id, d.label, {_SEAT_COLUMNS} FROM device d JOIN station s ON s.id = d.station_id
    {_SEATED_JOINS} WHERE d.key_hash = :digest AND d.revoked_at IS NULL"""
)
_STATION_SEAT = Statement(
    f"SELECT {_SEAT_COLUMNS} FROM station s {_SEATED_JOINS} WHERE s.name = :name {{lock}}",
    lock_of="s",
)


def _seat(columns: tuple[Any, ...]) -> Seat:
    station_id, station_name, pid, code, status, study_id, study, seed, sha, unblinded = columns[
        :10
    ]
    lang, site = columns[10:]
    seated = (
        None
        if pid is None
        else Seated(pid, code, status, study_id, study, seed, sha, bool(unblinded), lang, site)
    )
    return Seat(station_id, station_name, seated)


def device_seat(cursor: Cursor, *, digest: str) -> DeviceSeat | None:
    """The unrevoked device whose key hashes to ``digest``, with its station's seat."""
    found = cursor.row(_DEVICE_SEAT, {"digest": digest})
    return None if found is None else DeviceSeat(found[0], found[1], _seat(tuple(found[2:])))


def station_seat(cursor: Cursor, *, name: str, lock: bool = False) -> Seat | None:
    """The station called ``name`` and its seat (None when there is no such station);
    ``lock``: the station row is locked (PostgreSQL), serialising people's changes there."""
    found = cursor.row(_STATION_SEAT, {"name": name}, lock=lock)
    return None if found is None else _seat(tuple(found))


# ------------------------------------------------------------------------------- runs and steps


@dataclass(frozen=True, slots=True)
class Step:
    """A prompt (the first half of a step) and whether it has been answered."""

    id: int
    participant_id: int
    category: str
    action: int
    question: str
    probabilities: list[float]
    learner_version: int
    adapts: bool
    answer_id: int | None
    reply: str | None = None
    """The robot's reply to the answer (None while unanswered)."""
    confidence: str | None = None
    """The name of the reply's confidence level (None while unanswered)."""


@dataclass(slots=True)
class RunState:
    """A run, its session and its prompts so far (in the order asked)."""

    session_id: int
    session_number: int
    session_status: str
    run_id: int
    run_number: int
    run_status: str
    steps: list[Step]

    @property
    def running(self) -> bool:
        """Whether both the session and the run are running."""
        return self.session_status == SessionStatus.RUNNING and self.run_status == RunStatus.RUNNING

    def step(self, step_id: int) -> Step | None:
        """The step with this id, if it belongs to this run."""
        return next((s for s in self.steps if s.id == step_id), None)


_RUN_COLUMNS = "ss.id, ss.number, ss.status, r.id, r.number, r.status"
_LOCK_PARTICIPANT = Statement("SELECT status FROM participant WHERE id = :participant FOR UPDATE")
_LATEST_RUN = Statement(
    f"""SELECT {_RUN_COLUMNS} FROM study_session ss JOIN run r ON r.session_id = ss.id
    WHERE ss.participant_id = :participant ORDER BY ss.number DESC, r.number DESC LIMIT 1"""
)
_RUN_OF_STEP = Statement(
    f"""SELECT {_RUN_COLUMNS} FROM prompt pr JOIN run r ON r.id = pr.run_id
    JOIN study_session ss ON ss.id = r.session_id
    WHERE pr.id = :step AND pr.participant_id = :participant"""
)
_STEPS_OF_RUN = Statement(
    """SELECT pr.id, pr.participant_id, pr.category, pr.action, pr.question, pr.probabilities,
    pr.learner_version, pr.adapts, a.id, a.reply, a.confidence FROM prompt pr
    LEFT JOIN answer a ON a.prompt_id = pr.id
    WHERE pr.run_id = :run ORDER BY pr.id"""
)


def lock_timeline(cursor: Cursor, *, participant_id: int) -> str | None:
    """Serialise every change to this participant's sessions, runs, prompts and answers; on
    PostgreSQL also return their status as it is once the lock is held.

    On PostgreSQL the participant's row is locked, and what the caller reads afterwards, in new
    statements, sees whatever the previous holder committed. Locking a *run* row instead was not
    enough: after a lock wait READ COMMITTED re-reads only the locked row, so a query that locked
    "the latest run" could return a run that was no longer the latest (another one opened
    meanwhile), joined to its session's status from before the wait. On SQLite write transactions
    are exclusive and everything this one read is current: no statement, None."""
    if not cursor.postgres:
        return None
    found = cursor.row(_LOCK_PARTICIPANT, {"participant": participant_id})
    return None if found is None else str(found[0])


def _run_with_steps(cursor: Cursor, head: Any) -> RunState | None:
    """The run of ``head`` with its steps."""
    if head is None:
        return None
    steps = [
        Step(
            row[0],
            row[1],
            row[2],
            row[3],
            row[4],
            cursor.parsed(row[5]),
            row[6],
            bool(row[7]),
            row[8],
            row[9],
            row[10],
        )
        for row in cursor.rows(_STEPS_OF_RUN, {"run": head[3]})
    ]
    return RunState(head[0], head[1], head[2], head[3], head[4], head[5], steps)


def latest_run(cursor: Cursor, *, participant_id: int) -> RunState | None:
    """The participant's latest run and its steps; None before the first session. Read after
    :func:`lock_timeline` when the caller will change the timeline."""
    head = cursor.row(_LATEST_RUN, {"participant": participant_id})
    return _run_with_steps(cursor, head)


def run_of_step(cursor: Cursor, *, step_id: int, participant_id: int) -> RunState | None:
    """The run that step ``step_id`` of this participant belongs to, with its steps; None when
    the participant has no such step. Read after :func:`lock_timeline` when answering."""
    head = cursor.row(_RUN_OF_STEP, {"step": step_id, "participant": participant_id})
    return _run_with_steps(cursor, head)


_OPEN_SESSION = Statement(
    """INSERT INTO study_session (participant_id, station_id, number, status, started_at,
    started_by, ended_by, protocol_version) VALUES (:participant, :station, :number, :status,
    :now, :actor, '', (SELECT max(v.number) FROM protocol_version v JOIN participant p
    ON p.study_id = v.study_id WHERE p.id = :participant)) RETURNING id"""
)


def open_session(
    cursor: Cursor, *, participant_id: int, station_id: int, number: int, actor: str
) -> int:
    """Append session ``number`` (``UNIQUE(participant, number)`` refuses a second); its id."""
    return cursor.insert(
        _OPEN_SESSION,
        {
            "participant": participant_id,
            "station": station_id,
            "number": number,
            "status": str(SessionStatus.RUNNING),
            "now": cursor.timestamp(),
            "actor": actor,
        },
    )


_OPEN_RUN = Statement(
    """INSERT INTO run (session_id, participant_id, number, status, started_at)
    VALUES (:session, :participant, :number, :status, :now) RETURNING id"""
)


def open_run(cursor: Cursor, *, session_id: int, participant_id: int, number: int) -> int:
    """Append run ``number`` to a session; its id."""
    return cursor.insert(
        _OPEN_RUN,
        {
            "session": session_id,
            "participant": participant_id,
            "number": number,
            "status": str(RunStatus.RUNNING),
            "now": cursor.timestamp(),
        },
    )


_CLOSE_RUN = Statement("UPDATE run SET status = :status, ended_at = :now WHERE id = :run")
_EARLY_RUNS = Statement(
    "SELECT count(*) FROM run WHERE session_id = :session AND status = :ended_early"
)
_CLOSE_SESSION = Statement(
    """UPDATE study_session SET status = :status, ended_at = :now, ended_by = :actor
    WHERE id = :session"""
)
_COMPLETE_PARTICIPANT = Statement(
    "UPDATE participant SET status = :completed WHERE id = :participant AND status = :active"
)


def close_run(cursor: Cursor, *, run_id: int, status: RunStatus) -> None:
    """Mark a run completed or ended early."""
    cursor.write(_CLOSE_RUN, {"status": str(status), "now": cursor.timestamp(), "run": run_id})


def session_had_early_runs(cursor: Cursor, *, session_id: int) -> bool:
    """Whether any run of the session was ended early."""
    found = cursor.row(
        _EARLY_RUNS, {"session": session_id, "ended_early": str(RunStatus.ENDED_EARLY)}
    )
    return bool(found[0])


def close_session(cursor: Cursor, *, session_id: int, status: SessionStatus, actor: str) -> None:
    """Mark a session completed or ended early, by whom."""
    cursor.write(
        _CLOSE_SESSION,
        {
            "status": str(status),
            "now": cursor.timestamp(),
            "actor": actor,
            "session": session_id,
        },
    )


def complete_participant(cursor: Cursor, *, participant_id: int) -> Written:
    """An active participant has completed the study (a withdrawn one stays withdrawn)."""
    return cursor.write(
        _COMPLETE_PARTICIPANT,
        {
            "completed": str(ParticipantStatus.COMPLETED),
            "active": str(ParticipantStatus.ACTIVE),
            "participant": participant_id,
        },
    )


_SUBMITTED = Statement("SELECT instrument, session FROM submission WHERE participant_id = :p")


def submitted(cursor: Cursor, *, participant_id: int) -> set[tuple[str, int | None]]:
    """The (instrument, session) pairs the participant has submitted (the questionnaire gates
    before each session: app.services.participants.questionnaires.blocker_given)."""
    return {
        (instrument, session)
        for instrument, session in cursor.rows(_SUBMITTED, {"p": participant_id})
    }


_CONSENT_VERSIONS = Statement(
    """SELECT (SELECT max(version) FROM consent_version WHERE study_id = :s),
    (SELECT max(version) FROM consent_record WHERE participant_id = :p AND accepted = :yes)"""
)


def consent_versions(
    cursor: Cursor, *, study_id: int, participant_id: int
) -> tuple[int, int | None]:
    """The study's current consent version (1 while only the protocol's exists) and the latest
    the participant accepted (None: not yet; app.services.privacy.consent.reconsent_blocker)."""
    current, accepted = cursor.row(
        _CONSENT_VERSIONS, {"s": study_id, "p": participant_id, "yes": True}
    )
    return int(current or 1), None if accepted is None else int(accepted)


# ------------------------------------------------------------------------------------ learners


@dataclass(frozen=True, slots=True)
class LearnerRow:
    """A learner's identity, structure and version; its state is read only when needed."""

    id: int
    kind: str
    n_arms: int
    config: dict[str, Any]
    checkpoint_sha256: str | None
    version: int


_LEARNER = Statement(
    """SELECT id, kind, n_arms, config, checkpoint_sha256, version FROM learner
    WHERE participant_id = :participant AND category = :category"""
)
_LEARNER_STATE = Statement("SELECT state FROM learner WHERE id = :learner")
_SAVE_LEARNER = Statement(
    """UPDATE learner SET state = :state, version = :version, updated_at = :now
    WHERE id = :learner AND version = :was"""
)


def learner(cursor: Cursor, *, participant_id: int, category: str) -> LearnerRow | None:
    """The participant's learner for ``category`` (without its state)."""
    found = cursor.row(_LEARNER, {"participant": participant_id, "category": category})
    if found is None:
        return None
    row_id, kind, n_arms, config, sha256, version = found
    return LearnerRow(row_id, kind, n_arms, cursor.parsed(config), sha256, version)


def learner_state(cursor: Cursor, *, learner_id: int) -> dict[str, Any]:
    """A learner's stored state (a cache miss: the process has no live copy at its version)."""
    return dict(cursor.parsed(cursor.row(_LEARNER_STATE, {"learner": learner_id})[0]))


def save_learner(cursor: Cursor, *, row: LearnerRow, state: dict[str, Any]) -> Written:
    """Store the learner's new state as version ``row.version + 1``, only if the stored version
    is still ``row.version``: it was if the count is 1."""
    return cursor.write(
        _SAVE_LEARNER,
        {
            "state": cursor.json(state),
            "version": row.version + 1,
            "now": cursor.timestamp(),
            "learner": row.id,
            "was": row.version,
        },
    )


# --------------------------------------------------------------------------- the appended rows


_INSERT_PROMPT = Statement(
    """INSERT INTO prompt (participant_id, run_id, category, action, question, probabilities,
    learner_version, adapts, p_preferred, prompted_at, device_id, actor, zone)
    VALUES (:participant, :run, :category, :action, :question, :probabilities, :learner_version,
    :adapts, :p_preferred, :now, :device, :actor, :zone) RETURNING id"""
)


def insert_prompt(
    cursor: Cursor,
    *,
    participant_id: int,
    run_id: int,
    category: str,
    action: int,
    question: str,
    probabilities: list[float],
    learner_version: int,
    adapts: bool,
    p_preferred: float | None,
    device_id: int | None,
    actor: str,
    zone: str | None = None,
) -> Step:
    """Append a prompt; the new step."""
    step_id = cursor.insert(
        _INSERT_PROMPT,
        {
            "participant": participant_id,
            "run": run_id,
            "category": category,
            "action": action,
            "question": question,
            "probabilities": cursor.json(probabilities),
            "learner_version": learner_version,
            "adapts": adapts,
            "p_preferred": p_preferred,
            "now": cursor.timestamp(),
            "device": device_id,
            "actor": actor,
            "zone": zone,
        },
    )
    return Step(
        step_id,
        participant_id,
        category,
        action,
        question,
        probabilities,
        learner_version,
        adapts,
        None,
    )


@dataclass(frozen=True, slots=True)
class HowAnswered:
    """How the participant gave an answer, as the client says (all None: it did not say)."""

    modality: str | None = None
    transcript: str | None = None
    confidence: float | None = None
    engine: str | None = None


NOT_SAID = HowAnswered()


@dataclass(frozen=True, slots=True)
class NewAnswer:
    """The second half of a step, as appended."""

    prompt_id: int
    participant_id: int
    answer: bool
    reward: float
    probabilities_after: list[float]
    p_preferred: float | None
    probability: float
    confidence_level: int
    confidence: str
    reply: str
    learner_version: int
    idempotency_key: str
    processing_ms: float
    device_id: int | None
    actor: str
    heard: HowAnswered = field(default_factory=lambda: NOT_SAID)


_INSERT_ANSWER = Statement(
    """INSERT INTO answer (prompt_id, participant_id, answer, reward, probabilities_after,
    p_preferred, probability, confidence_level, confidence, reply, learner_version,
    idempotency_key, answered_at, processing_ms, device_id, actor, modality, transcript,
    transcript_confidence, transcript_engine)
    VALUES (:prompt, :participant, :answer, :reward, :after, :p_preferred, :probability, :level,
    :confidence, :reply, :learner_version, :key, :now, :processing_ms, :device, :actor,
    :modality, :transcript, :transcript_confidence, :transcript_engine)
    RETURNING id"""
)


def insert_answer(cursor: Cursor, answer: NewAnswer) -> int:
    """Append an answer (``UNIQUE(prompt_id)``: a second one for a step raises IntegrityError
    through the session's commit or here); its id."""
    return cursor.insert(
        _INSERT_ANSWER,
        {
            "prompt": answer.prompt_id,
            "participant": answer.participant_id,
            "answer": answer.answer,
            "reward": answer.reward,
            "after": cursor.json(answer.probabilities_after),
            "p_preferred": answer.p_preferred,
            "probability": answer.probability,
            "level": answer.confidence_level,
            "confidence": answer.confidence,
            "reply": answer.reply,
            "learner_version": answer.learner_version,
            "key": answer.idempotency_key,
            "now": cursor.timestamp(),
            "processing_ms": answer.processing_ms,
            "device": answer.device_id,
            "actor": answer.actor,
            "modality": answer.heard.modality,
            "transcript": answer.heard.transcript,
            "transcript_confidence": answer.heard.confidence,
            "transcript_engine": answer.heard.engine,
        },
    )


@dataclass(frozen=True, slots=True)
class StoredAnswer:
    """What a stored answer replies when its request is repeated."""

    id: int
    answer: bool
    idempotency_key: str
    reply: str
    confidence_level: int
    confidence: str
    probability: float
    probabilities_after: list[float]


_STORED_ANSWER = Statement(
    """SELECT id, answer, idempotency_key, reply, confidence_level, confidence, probability,
    probabilities_after FROM answer WHERE id = :answer"""
)


def stored_answer(cursor: Cursor, *, answer_id: int) -> StoredAnswer:
    """The answer with this id."""
    found = cursor.row(_STORED_ANSWER, {"answer": answer_id})
    assert found is not None, answer_id
    row_id, answer, key, reply, level, confidence, probability, after = found
    return StoredAnswer(
        row_id, bool(answer), key, reply, level, confidence, probability, cursor.parsed(after)
    )


_INSERT_AUDIT = Statement(
    """INSERT INTO audit_event (occurred_at, actor_kind, actor, action, study_id, subject, details)
    VALUES (:now, :kind, :actor, :action, :study, :subject, :details)"""
)


def insert_audit(
    cursor: Cursor,
    *,
    actor_kind: str,
    actor: str,
    action: str,
    study_id: int | None,
    subject: str,
    details: dict[str, Any],
) -> None:
    """Append an audit event (as app.services.audit.record does through the ORM)."""
    cursor.write(
        _INSERT_AUDIT,
        {
            "now": cursor.timestamp(),
            "kind": actor_kind,
            "actor": actor,
            "action": action,
            "study": study_id,
            "subject": subject,
            "details": cursor.json(details),
        },
    )
