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
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

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
    }


def _one_of(column: str, values: type[StrEnum]) -> CheckConstraint:
    allowed = ", ".join(f"'{member.value}'" for member in values)
    return CheckConstraint(f"{column} IN ({allowed})", name=f"{column}_known")


class Role(StrEnum):
    """What a signed-in person may do: admin ⊇ experimenter and analyst rights."""

    ADMIN = "admin"
    EXPERIMENTER = "experimenter"
    ANALYST = "analyst"


class StudyStatus(StrEnum):
    """Whether a study accepts new participants."""

    OPEN = "open"
    CLOSED = "closed"


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

    user: Mapped[User] = relationship(lazy="joined")


class Study(Base):
    """A study: its validated protocol, its concealed allocation seed and whether it is open."""

    __tablename__ = "study"
    __table_args__ = (_one_of("status", StudyStatus),)

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    title: Mapped[str] = mapped_column(String(200))
    status: Mapped[str] = mapped_column(String(16), default=StudyStatus.OPEN)
    protocol: Mapped[dict[str, Any]]
    protocol_source: Mapped[str] = mapped_column(Text)
    protocol_sha256: Mapped[str] = mapped_column(String(64))
    allocation_seed: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    created_by: Mapped[str] = mapped_column(String(64), default="")
    closed_at: Mapped[datetime | None]


class Participant(Base):
    """An enrolled person, known only by a code; their condition lives in :class:`Allocation`."""

    __tablename__ = "participant"
    __table_args__ = (
        UniqueConstraint("study_id", "code"),
        _one_of("status", ParticipantStatus),
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

    study: Mapped[Study] = relationship()
    allocation: Mapped[Allocation] = relationship(
        back_populates="participant", foreign_keys="Allocation.participant_id", uselist=False
    )


class Allocation(Base):
    """A revealed allocation: the n-th entry of a stratum's sequence, or a dropout replacement.

    Rows exist only once revealed (at enrolment); the sequence itself is a pure function of the
    study's secret seed (see :mod:`app.randomisation`), so nothing unrevealed is ever stored or
    shown. ``UNIQUE(study_id, stratum, sequence_index)`` makes a reused entry impossible even under
    concurrent enrolments; a replacement has no sequence entry and points at whom it replaces.
    """

    __tablename__ = "allocation"
    __table_args__ = (
        UniqueConstraint("study_id", "stratum", "sequence_index"),
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
    revealed_at: Mapped[datetime] = mapped_column(default=utcnow)

    participant: Mapped[Participant] = relationship(
        back_populates="allocation", foreign_keys=[participant_id]
    )


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
