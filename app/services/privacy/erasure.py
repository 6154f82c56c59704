"""Withdrawal with erasure: everything a participant gave a study, removed in one transaction.

What goes is what the personal data registry (app.services.privacy.personal_data) says: every prompt
and answer (with transcripts and recorded audio), session and run, learner state, questionnaire
answer and submission (free text included), consent record, their room presence (seated or no
longer), their tablet token, their language and stratification values, a robot's notice naming
them, and every personal detail of the audit events about them. What stays, and why:

- **The allocation row and a participant row under a pseudonym** (``~erased-…``), because the
  concealed sequence is checked slot by slot (app.services.sessions.verify): removing a revealed
  slot would leave a gap, and a later enrolment would then be given an entry someone already had.
  The slot counts as withdrawn, so balance, concealment and dropout replacement hold.
- **The audit events**, rewritten: the participant's code becomes the pseudonym wherever it
  appears, and the details of events about them (answers, free-text edits, reasons) are dropped,
  so the log still shows that things happened, and when, but holds no personal data. The erasure
  itself is recorded the same way.

The pseudonym is a keyed hash (the server's secret) of the study and the code: it cannot be
turned back into the code without the key, and it lets a second erasure of the same code be
refused as "already erased" instead of "unknown". A code may be enrolled again after its erasure
(another person, or the same one back): that participant's erasure gets the hash with ``-2``
(``-3`` …) after it, so every erasure of every enrolment succeeds and the rows stay unique.

The prompt, answer and audit tables are append-only for everyone else: an erasure marks its
participant in ``erasure_in_progress`` inside its own transaction, which opens their guards for
exactly that participant (app.schema.create_erasable_guard), and removes the mark before
committing. Copies made before the erasure (backups, exports, downloads) still hold the data:
:func:`erase_participant` lists the ones the audit log knows of, so the lab can deal with them.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import ColumnElement, String, cast, delete, func, or_, select, update
from sqlalchemy.orm import Session

from app.db import WalCheckpointer
from app.errors import Conflict, InvalidInput, NotFound
from app.services import audit
from app.services.audit import Actor
from app.services.participants import participant_changes
from app.services.participants.enrolment import ERASE, get_participant, require_withdrawal_option
from app.services.participants.participant_changes import Change
from app.services.privacy import personal_data, pseudonyms, sites
from app.services.sessions import learner_cache
from app.services.studies import get_study
from app.tables import (
    AuditEvent,
    Device,
    ErasureInProgress,
    LearnerState,
    Participant,
    ParticipantStatus,
    Station,
    Study,
    utcnow,
)

ERASED_PREFIX = "~erased-"
"""Erased participants' codes start with this; no enrolment code can (app.inputs)."""


def erased_code(secret: bytes, study: Study, code: str) -> str:
    """The pseudonym the first erased participant of ``code`` carries instead of the code; later
    ones carry it with a number after it (:func:`free_erased_code`)."""
    return ERASED_PREFIX + pseudonyms.pseudonym(secret, study.name, code)[len(pseudonyms.PREFIX) :]


def _erased_rows_of(study: Study, first: str) -> ColumnElement[bool]:
    """The study's rows erased under ``code``'s pseudonym: the first, and ``-2``, ``-3`` …"""
    return (Participant.study_id == study.id) & or_(
        Participant.code == first, Participant.code.startswith(f"{first}-", autoescape=True)
    )


def free_erased_code(db: Session, secret: bytes, study: Study, code: str) -> str:
    """The pseudonym for erasing the current participant of ``code``: :func:`erased_code`, or,
    when that code was erased before (and enrolled again), the first of ``-2``, ``-3`` … not
    taken, so the second person's erasure never meets the first's row (UNIQUE(study, code))."""
    first = erased_code(secret, study, code)
    taken = set(db.scalars(select(Participant.code).where(_erased_rows_of(study, first))))
    if first not in taken:
        return first
    number = 2
    while f"{first}-{number}" in taken:
        number += 1
    return f"{first}-{number}"


def is_erased_code(code: str) -> bool:
    """Whether a participant code is an erased participant's pseudonym."""
    return code.startswith(ERASED_PREFIX)


@dataclass(frozen=True)
class EarlierCopy:
    """A file made before the erasure that may still hold the participant (from the audit log)."""

    kind: str  # backup | export | download | subject-access export
    made_at: datetime
    where: str
    exists: bool | None  # on this server; None when trustlab cannot tell (a browser download)

    def describe(self) -> str:
        """One line for the command line and the web page."""
        when = self.made_at.strftime("%Y-%m-%d %H:%M UTC")
        state = {True: "", False: " (no longer there)", None: ""}[self.exists]
        return f"{self.kind} of {when}: {self.where}{state}"


@dataclass
class Erasure:
    """What one erasure removed, and the copies that predate it."""

    code: str
    study: str
    erased_at: datetime
    removed: dict[str, int] = field(default_factory=dict)
    earlier_copies: list[EarlierCopy] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """For the API and ``--json``."""
        return {
            "code": self.code,
            "study": self.study,
            "erased_at": self.erased_at.isoformat(),
            "removed": self.removed,
            "earlier_copies": [
                {
                    "kind": copy.kind,
                    "made_at": copy.made_at.isoformat(),
                    "where": copy.where,
                    "exists": copy.exists,
                }
                for copy in self.earlier_copies
            ],
        }


def erase_participant(
    db: Session,
    *,
    study_name: str,
    code: str,
    actor: Actor,
    secret: bytes,
    reason: str = "",
) -> Erasure:
    """Withdraw (if still active) and erase one participant, in one transaction; commits.

    Refused, with nothing changed: a study whose protocol does not allow erasure, a code that
    was already erased, a participant who does not exist."""
    study = get_study(db, study_name)
    require_withdrawal_option(study, ERASE)
    try:
        participant = get_participant(db, study, code, actor=actor, for_update=True)
    except NotFound:
        earlier = db.scalar(
            select(func.max(Participant.erased_at)).where(
                _erased_rows_of(study, erased_code(secret, study, code)), sites.visible(actor)
            )
        )
        if earlier is not None:
            raise Conflict(
                f"participant {code!r} was already erased from {study.name!r} on "
                f"{earlier:%Y-%m-%d}: nothing of theirs is stored"
            ) from None
        raise
    if participant.erased_at is not None:  # pragma: no cover - erased rows carry the pseudonym
        raise Conflict(f"participant {code!r} was already erased")
    if len(reason) > 2000:
        raise InvalidInput("the reason is longer than 2000 characters")
    now = utcnow()
    pseudonym = free_erased_code(db, secret, study, code)
    earlier_copies = list(_earlier_copies(db, study, participant, code))
    seat = seat_of(db, participant)
    with opened_guards(db, study, [participant]):
        removed = erase(db, study, participant, now=now, pseudonym=pseudonym)
    audit.record(
        db,
        actor=actor,
        action="participant.erased",
        study_id=study.id,
        subject=pseudonym,
        details={"removed": removed, "reason_given": bool(reason.strip())},
    )
    # The console and the room of the station they sat at, and their tablet, learn it too: the
    # tablet shows its thank-you page before its link stops working (static/js/tablet.js).
    participant_changes.participant_changed(db, participant, Change.ERASED, station=seat)
    db.commit()
    after_erasures(db)
    return Erasure(
        code=code,
        study=study.name,
        erased_at=now,
        removed=removed,
        earlier_copies=earlier_copies,
    )


def seat_of(db: Session, participant: Participant) -> Station | None:
    """The station the participant sits at (erasure frees it: its views are told after)."""
    return db.scalar(select(Station).where(Station.participant_id == participant.id))


@contextmanager
def opened_guards(db: Session, study: Study, participants: list[Participant]) -> Iterator[None]:
    """Inside the caller's transaction: open the append-only guards for these participants'
    prompts and answers and their study's audit events, and close them again (the marker rows
    are never committed)."""
    for participant in participants:
        db.add(ErasureInProgress(participant_id=participant.id, study_id=study.id))
    db.flush()
    yield
    db.flush()
    db.execute(
        delete(ErasureInProgress).where(
            ErasureInProgress.participant_id.in_([p.id for p in participants])
        )
    )


def erase(
    db: Session, study: Study, participant: Participant, *, now: datetime, pseudonym: str
) -> dict[str, int]:
    """Remove everything of one participant inside :func:`opened_guards` (no commit, no audit
    event of its own); the rows removed per table."""
    removed = remove_data(db, study, participant, pseudonym=pseudonym, about={"erased": True})
    participant = db.get_one(Participant, participant.id)
    if participant.status != ParticipantStatus.WITHDRAWN:
        participant.status = ParticipantStatus.WITHDRAWN
        participant.withdrawn_at = now
    participant.code = pseudonym
    participant.erased_at = now
    participant.withdrawal_reason = ""
    participant.strata = {}
    participant.language = None
    participant.token_hash = None
    participant.token_generation += 1
    return removed


def remove_data(
    db: Session, study: Study, participant: Participant, *, pseudonym: str, about: dict[str, Any]
) -> dict[str, int]:
    """Inside :func:`opened_guards`: delete every row of the participant's data, unseat them,
    and rewrite the audit events naming them (``pseudonym`` for the code, ``about`` for the
    details of events about them); the rows removed per table. The participant and allocation
    rows stay: an erasure keeps them as the slot, a pilot reset deletes them after
    (app.services.design.study_phases)."""
    code = participant.code
    learner_ids = list(
        db.scalars(select(LearnerState.id).where(LearnerState.participant_id == participant.id))
    )
    db.info.setdefault(_FORGET_KEY, []).extend(learner_ids)
    removed = _remove_data(db, participant)
    scrub_audit(db, study, code, pseudonym, about=about)
    scrub_devices(db, code)
    return removed


_FORGET_KEY = "trustlab.erased_learners"


def after_erasures(db: Session) -> None:
    """After the erasures' transaction committed: forget their learners in the cache (row ids
    can be reused once deleted, on SQLite) and empty SQLite's WAL."""
    cache = learner_cache.of(db)
    for learner_id in db.info.pop(_FORGET_KEY, []):
        cache.forget(learner_id)
    _empty_sqlite_wal(db)


def drop_study_derived(
    db: Session, study_id: int, tables: tuple[personal_data.PersonalTable, ...]
) -> None:
    """Delete the rows of ``study_id`` in ``tables`` (results derived from the whole study's
    data: the fitted analyses). A worker's copy in memory is used only while its row exists
    (app.services.analysis_views.fit_cache), so it goes with the row."""
    for entry in tables:
        db.execute(delete(entry.sql).where(entry.sql.c.study_id == study_id))


def _empty_sqlite_wal(db: Session) -> None:
    """SQLite zeroes deleted content (app.db: secure_delete), but the WAL still holds the pages
    as they were before; a TRUNCATE checkpoint empties it (best effort: with a reader still on
    an old snapshot, a later checkpoint does it)."""
    url = db.get_bind().engine.url
    if url.get_backend_name() == "sqlite" and url.database not in (None, "", ":memory:"):
        WalCheckpointer(str(url.database)).truncate()


def _remove_data(db: Session, participant: Participant) -> dict[str, int]:
    """Delete every row of the participant's data (the registry's tables whose rows erasure
    deletes, children first) and unseat them; counts per table."""
    owned = participant.id
    removed = {}
    for entry in personal_data.erased_by_deletion():
        result = db.execute(delete(entry.sql).where(entry.sql.c.participant_id == owned))
        removed[entry.name] = int(result.rowcount or 0)  # type: ignore[attr-defined]
    drop_study_derived(db, participant.study_id, personal_data.erased_with_study())
    db.execute(
        update(Station)
        .where(Station.participant_id == owned)
        .values(participant_id=None, assigned_at=None),
        execution_options={"synchronize_session": False},
    )
    db.expire_all()
    return {table: count for table, count in removed.items() if count}


def code_pattern(code: str) -> re.Pattern[str]:
    """The code as a whole word: ``P01`` must not match inside ``P017``."""
    return re.compile(rf"(?<![A-Za-z0-9_-]){re.escape(code)}(?![A-Za-z0-9_-])")


def _replace_in(value: Any, pattern: re.Pattern[str], replacement: str) -> Any:
    if isinstance(value, str):
        return pattern.sub(replacement, value)
    if isinstance(value, list):
        return [_replace_in(item, pattern, replacement) for item in value]
    if isinstance(value, dict):
        return {
            _replace_in(key, pattern, replacement): _replace_in(item, pattern, replacement)
            for key, item in value.items()
        }
    return value


def scrub_audit(
    db: Session, study: Study, code: str, pseudonym: str, *, about: dict[str, Any]
) -> None:
    """Rewrite the study's audit events that name the participant: the pseudonym for the code;
    ``about`` instead of the details of events about them (answers, edits, reasons are personal
    data)."""
    pattern = code_pattern(code)
    candidates = select(AuditEvent).where(
        AuditEvent.study_id == study.id,
        or_(
            AuditEvent.subject == code,
            AuditEvent.actor.contains(code, autoescape=True),
            cast(AuditEvent.details, String).contains(code, autoescape=True),
        ),
    )
    for event in db.scalars(candidates):
        is_about = event.subject == code
        names = is_about or pattern.search(event.actor) or pattern.search(str(event.details))
        if not names:
            continue
        event.subject = pseudonym if is_about else pattern.sub(pseudonym, event.subject)
        event.actor = pattern.sub(pseudonym, event.actor)[:64]
        if is_about:
            event.details = about
        else:
            event.details = _replace_in(event.details, pattern, pseudonym)
    db.flush()


def scrub_devices(db: Session, code: str) -> None:
    """A robot's last notice may name the participant ("waiting for P017 …"): drop it."""
    pattern = code_pattern(code)
    for device in db.scalars(select(Device).where(Device.notice.is_not(None))):
        if device.notice and pattern.search(device.notice):
            device.notice = None
            device.notice_attention = False


def _earlier_copies(
    db: Session, study: Study, participant: Participant, code: str
) -> Iterator[EarlierCopy]:
    """Backups and exports made since the participant enrolled, as the audit log records them."""
    kinds = personal_data.copy_actions()
    query = (
        select(AuditEvent)
        .where(AuditEvent.occurred_at >= participant.enrolled_at, AuditEvent.action.in_(kinds))
        .order_by(AuditEvent.occurred_at)
    )
    for event in db.scalars(query):
        kind = kinds[event.action]
        if event.action == "db.backed_up":
            where, exists = _on_disk(str(event.details.get("file", "?")))
            yield EarlierCopy(kind, event.occurred_at, where, exists)
        elif event.study_id != study.id:
            continue
        elif event.action == "export.written":
            for spec in (event.details.get("files") or {}).values():
                where, exists = _on_disk(str(spec.get("path", "?")))
                yield EarlierCopy(kind, event.occurred_at, where, exists)
        elif event.action == "export.downloaded":
            where = f"{event.subject} downloaded by {event.actor}"
            yield EarlierCopy(kind, event.occurred_at, where, None)
        elif event.subject == code:
            where = f"their own data, written by {event.actor}"
            yield EarlierCopy(kind, event.occurred_at, where, None)


def _on_disk(recorded: str) -> tuple[str, bool | None]:
    """Where an audited backup or export is, and whether it is still there.

    Backups and exports are recorded with absolute paths. Entries made before (issue 48) hold
    the path as typed, relative to a folder the audit log does not know: found from the folder
    this command runs in, it is shown absolute; otherwise trustlab cannot tell (None) and says
    so, rather than calling a copy that may well exist "no longer there"."""
    path = Path(recorded)
    if path.is_absolute():
        return recorded, path.exists()
    if path.exists():
        return str(path.resolve()), True
    return f"{recorded} (relative to the folder it was written from)", None
