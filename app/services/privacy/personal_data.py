"""The personal data registry: every table and file that can hold a participant's data, and what
each of erasure, anonymisation, the participant's own copy and the pseudonymised export does
with it.

Erasure (app.services.privacy.erasure), retention's anonymising (app.services.privacy.retention),
the subject-access record (app.services.privacy.subject_access), the pseudonymised export
(app.services.privacy.pseudonyms) and the erasure's list of earlier copies read this list instead of
naming tables of their own, so a table added here is handled by all of them, and a table left
out is caught by a test that walks the schema (tests/app/test_personal_data_registry.py): every
table is either listed here or in :data:`NOT_PERSONAL` with the reason, every table with a key
to a participant is listed here, and every column that can hold free text is declared.

Before this registry each feature kept its own list, and ``room_presence`` (the words the
recogniser heard, and when) was found only through the station the participant still sat at:
unseated first, it survived erasure and retention (issue 48).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import cast

from sqlalchemy import Table
from sqlalchemy.orm import DeclarativeBase

from app.tables import (
    Allocation,
    Answer,
    AnswerAudio,
    AuditEvent,
    ConsentRecord,
    ConsentVersion,
    Device,
    DeviceSocket,
    ErasureInProgress,
    FittedAnalysis,
    LearnerState,
    LoginAttempt,
    LoginSession,
    OnlineParticipation,
    Participant,
    Prompt,
    ProtocolVersion,
    Response,
    RoomPresence,
    Run,
    Station,
    Study,
    StudySession,
    Submission,
    User,
)


class Erased(StrEnum):
    """What erasing a participant does to a table's rows of theirs."""

    DELETED = "deleted"
    """Their rows (``participant_id``) are deleted."""
    KEPT_AS_SLOT = "kept as the allocation slot"
    """The row stays under the pseudonym with every personal field emptied: the randomisation
    sequence is checked slot by slot (app.services.privacy.erasure)."""
    UNSEATED = "unseated"
    """The row is not theirs (a station): its link to them is set to NULL."""
    REWRITTEN = "rewritten"
    """Rows that name them are rewritten: the pseudonym for the code, their details dropped."""
    NOTICE_DROPPED = "notice dropped"
    """A robot's notice that names their code is removed."""
    TRANSIENT = "never committed"
    """Rows exist only inside an erasure's own transaction."""
    STUDY_DROPPED = "dropped with the study's"
    """The rows are the study's, not theirs, and some hold their data: every row of their study
    is deleted (a cache: what is still needed is computed again)."""


class Anonymised(StrEnum):
    """What a retention run's anonymising does to a table's rows of a participant."""

    DELETED = "deleted"
    KEPT = "kept"
    """Kept for the analysis: any column in ``cleared`` is emptied, any in ``naming`` has the
    code replaced by the random id."""
    FREE_TEXT_DELETED = "free-text answers deleted"
    """The answers to the protocol's free-text items are deleted, the others kept."""
    RANDOM_ID = "random id"
    """The participant row: a random id for the code, reason and tablet link gone."""
    REWRITTEN = "rewritten"
    NOTICE_DROPPED = "notice dropped"
    UNTOUCHED = "untouched"
    """Holds nothing that identifies them once the code is gone (or never committed)."""
    STUDY_DROPPED = "dropped with the study's"
    """As :attr:`Erased.STUDY_DROPPED`: the rows hold the code being replaced."""


@dataclass(frozen=True)
class PersonalTable:
    """One table that can hold a participant's data."""

    table: type[DeclarativeBase]
    holds: str
    """What of the participant it holds (one line, for docs/data-protection.md and reviews)."""
    erased: Erased
    anonymised: Anonymised
    subject_access: str | None
    """The section of the participant's own copy (app.services.privacy.subject_access) showing
    it."""
    not_in_subject_access: str = ""
    """Why it is not in their copy, when ``subject_access`` is None."""
    exported_as: str | None = None
    """The :class:`analysis.dataset.StudyDataset` frame it reaches exports by (its
    ``participant`` column is what the pseudonymised export replaces)."""
    cleared: tuple[str, ...] = ()
    """Columns emptied when anonymising (transcripts)."""
    naming: tuple[str, ...] = ()
    """Columns of their own rows where their code can appear (a kiosk or room acting as them,
    an idempotency key made from it): the random id replaces it when anonymising."""
    free_text: dict[str, str] = field(default_factory=dict)
    """Every free-text or JSON column (column → what it holds): the registry test checks that
    none is added unseen."""

    @property
    def sql(self) -> Table:
        """The table itself, for Core statements (``.c.participant_id``)."""
        return cast(Table, self.table.__table__)

    @property
    def name(self) -> str:
        """The table's name."""
        return self.sql.name


TABLES: tuple[PersonalTable, ...] = (
    # Children before parents: erasure deletes in this order.
    PersonalTable(
        FittedAnalysis,
        "analyses fitted from their study's data, with per-participant rows under their code",
        Erased.STUDY_DROPPED,
        Anonymised.STUDY_DROPPED,
        None,
        not_in_subject_access=(
            "computed from their answers, which their copy lists; the rows of the others are "
            "not theirs"
        ),
        free_text={"settings": "the analysis's settings (a measure's key, the model)"},
    ),
    PersonalTable(
        AnswerAudio,
        "their recorded voice for spoken answers (when the protocol records audio)",
        Erased.DELETED,
        Anonymised.DELETED,
        "robot_steps",
    ),
    PersonalTable(
        Answer,
        "their yes/no answers, how given, what the recogniser heard, the robot's replies",
        Erased.DELETED,
        Anonymised.KEPT,
        "robot_steps",
        exported_as="steps",
        cleared=("transcript",),
        naming=("actor", "idempotency_key"),
        free_text={
            "reply": "the robot's reply (protocol wording)",
            "probabilities_after": "the learner's probabilities",
            "idempotency_key": "a client's key, which may be made from the code",
            "transcript": "the words the recogniser heard",
        },
    ),
    PersonalTable(
        Prompt,
        "the questions asked them, when, in which zone",
        Erased.DELETED,
        Anonymised.KEPT,
        "robot_steps",
        exported_as="steps",
        naming=("actor",),
        free_text={
            "question": "the question (protocol wording)",
            "probabilities": "the learner's probabilities",
        },
    ),
    PersonalTable(
        Run,
        "their runs (each category asked once)",
        Erased.DELETED,
        Anonymised.KEPT,
        "robot_steps",
    ),
    PersonalTable(
        StudySession,
        "their sessions: when, at which station, started and ended by whom",
        Erased.DELETED,
        Anonymised.KEPT,
        "robot_steps",
        naming=("started_by", "ended_by"),
    ),
    PersonalTable(
        LearnerState,
        "their learners' state, learnt from their answers",
        Erased.DELETED,
        Anonymised.KEPT,
        None,
        not_in_subject_access=(
            "derived from their answers, which their copy lists step by step; the learner's "
            "kind would reveal a blinded condition"
        ),
        free_text={
            "config": "the learner's settings",
            "initial_state": "the learner's state",
            "state": "the learner's state",
        },
    ),
    PersonalTable(
        Response,
        "their questionnaire answers, free text included",
        Erased.DELETED,
        Anonymised.FREE_TEXT_DELETED,
        "questionnaires",
        exported_as="responses",
        free_text={"value": "their answer, free text included"},
    ),
    PersonalTable(
        Submission,
        "when they submitted each questionnaire page",
        Erased.DELETED,
        Anonymised.KEPT,
        "questionnaires",
    ),
    PersonalTable(
        ConsentRecord,
        "their answers to each version of the consent text",
        Erased.DELETED,
        Anonymised.KEPT,
        "consent",
    ),
    PersonalTable(
        RoomPresence,
        "where the room client last saw them and the last line said there (words heard)",
        Erased.DELETED,
        Anonymised.DELETED,
        "room",
        free_text={"utterance": "the last line said: the robot's, or the words heard"},
    ),
    PersonalTable(
        OnlineParticipation,
        "an online participant's recruitment ID (a keyed hash), the platform's parameters, "
        "their browser's hash, steps, time limit and data-quality flags",
        Erased.DELETED,
        Anonymised.KEPT,
        "enrolment",
        cleared=("recruitment_hash", "browser", "parameters"),
        free_text={
            "parameters": "the platform's URL parameters (a study's or session's id)",
            "reason": "why they were screened out (the browser check's finding)",
            "flags": "data-quality flags (names and figures)",
        },
    ),
    PersonalTable(
        Station,
        "the station they are seated at",
        Erased.UNSEATED,
        Anonymised.UNTOUCHED,
        "enrolment",
    ),
    PersonalTable(
        Allocation,
        "their condition and allocation slot",
        Erased.KEPT_AS_SLOT,
        Anonymised.KEPT,
        "enrolment",
        exported_as="participants",
        free_text={"stratum": "their stratum's name (shared by all of the stratum; kept)"},
    ),
    PersonalTable(
        AuditEvent,
        "what was done about them, by whom (their code as subject or actor, details)",
        Erased.REWRITTEN,
        Anonymised.REWRITTEN,
        "audit_log",
        free_text={
            "subject": "what the event is about: their code",
            "details": "details of the event: answers, edits, reasons about them",
        },
    ),
    PersonalTable(
        Device,
        "a robot's notice to the console may name their code",
        Erased.NOTICE_DROPPED,
        Anonymised.NOTICE_DROPPED,
        None,
        not_in_subject_access="a line for staff about the robot, gone with the code",
        free_text={"notice": "the robot's line to the console (may name a code)"},
    ),
    PersonalTable(
        ErasureInProgress,
        "the participant being erased, inside the erasure's transaction only",
        Erased.TRANSIENT,
        Anonymised.UNTOUCHED,
        None,
        not_in_subject_access="never committed",
    ),
    PersonalTable(
        Participant,
        "their code, status, stratification values, language, site, withdrawal reason, tablet link",
        Erased.KEPT_AS_SLOT,
        Anonymised.RANDOM_ID,
        "enrolment",
        exported_as="participants",
        free_text={
            "withdrawal_reason": "why they withdrew, in staff's words",
            "stratum": "their stratification values, joined",
            "strata": "their stratification values",
        },
    ),
)


@dataclass(frozen=True)
class NotPersonal:
    """A table that holds no participant's data, and why; its free-text columns declared."""

    why: str
    free_text: dict[str, str] = field(default_factory=dict)


NOT_PERSONAL: dict[type[DeclarativeBase], NotPersonal] = {
    User: NotPersonal(
        "staff accounts", {"password_hash": "a hash", "sites": "the sites an account sees"}
    ),
    LoginSession: NotPersonal("staff sign-ins", {"user_agent": "a staff browser"}),
    LoginAttempt: NotPersonal("staff password checks"),
    Study: NotPersonal(
        "the protocol and its settings, written by staff",
        {
            "title": "the study's title",
            "protocol": "the protocol",
            "protocol_source": "the protocol",
            "neutral_labels": "blinded labels",
        },
    ),
    ProtocolVersion: NotPersonal(
        "every version of a study's protocol, written by staff",
        {"source": "the protocol", "reason": "why staff changed it"},
    ),
    ConsentVersion: NotPersonal(
        "the consent texts, written by staff",
        {
            "texts": "the consent text",
            "sha256": "hashes of the text",
            "reason": "why staff changed it",
        },
    ),
    DeviceSocket: NotPersonal("a robot's open connections"),
}


def exported_frames() -> tuple[str, ...]:
    """The dataset frames holding participant data: the pseudonymised export replaces the
    ``participant`` column of each."""
    return tuple(dict.fromkeys(t.exported_as for t in TABLES if t.exported_as))


SUBJECT_ACCESS_SECTIONS = (
    "enrolment",
    "consent",
    "questionnaires",
    "robot_steps",
    "room",
    "audit_log",
)
"""The sections of a participant's own copy, in the order it shows them; every table's
``subject_access`` names one (the registry test checks), and app.services.privacy.subject_access
builds each."""


def erased_by_deletion() -> tuple[PersonalTable, ...]:
    """The tables whose rows of an erased participant are deleted, children first."""
    return tuple(t for t in TABLES if t.erased == Erased.DELETED)


def erased_with_study() -> tuple[PersonalTable, ...]:
    """The tables whose rows of the erased participant's study (``study_id``) the erasure
    deletes: derived from everyone's data, theirs included."""
    return tuple(t for t in TABLES if t.erased == Erased.STUDY_DROPPED)


def anonymised(how: Anonymised) -> tuple[PersonalTable, ...]:
    """The tables anonymising treats ``how``."""
    return tuple(t for t in TABLES if t.anonymised == how)


@dataclass(frozen=True)
class PersonalFile:
    """A kind of file outside the database that can hold a participant's data."""

    kind: str
    holds: str
    erased: str
    """What an erasure does about it (the lab's part, when trustlab cannot)."""
    audit_action: str | None = None
    """The audit event recording each such file (erasure lists them as earlier copies)."""


FILES: tuple[PersonalFile, ...] = (
    PersonalFile(
        "backup",
        "the whole database as it was",
        "listed by the erasure with where it is; the lab deletes it or lets it expire",
        "db.backed_up",
    ),
    PersonalFile(
        "export",
        "the study's data (codes, or pseudonyms when pseudonymised; free text as given)",
        "listed by the erasure; the lab deletes or replaces it",
        "export.written",
    ),
    PersonalFile(
        "download",
        "an export downloaded from the analysis page",
        "listed by the erasure with who downloaded it",
        "export.downloaded",
    ),
    PersonalFile(
        "subject-access export",
        "the participant's own copy",
        "listed by the erasure; it is theirs",
        "participant.exported",
    ),
    PersonalFile(
        "SQLite write-ahead log",
        "pages as they were before a change",
        "emptied after each erasure (a TRUNCATE checkpoint); deleted content is zeroed "
        "(secure_delete)",
    ),
    PersonalFile(
        "PostgreSQL write-ahead log and archives",
        "every change, erased text included, until its segments are recycled",
        "docs/data-protection.md: checkpoint and segment recycling; archives and base "
        "backups until they expire",
    ),
    PersonalFile(
        "server access log",
        "participant codes in request paths",
        "kept out by TRUSTLAB_ACCESS_LOG (docs/data-protection.md)",
    ),
)


def copy_actions() -> dict[str, str]:
    """Audit action → kind of file, for the erasure's list of earlier copies."""
    return {f.audit_action: f.kind for f in FILES if f.audit_action}
