"""Retention deadlines: identifiable data kept for the declared period after a study closes, then
anonymised or erased by ``trustlab retention run``.

A protocol declares ``[retention] identifiable_for = "5 years"`` (app.periods) and what happens
then (``then = "anonymise"`` or ``"erase"``). The deadline counts from the moment the study was
last closed for enrolment: an open study (or one reopened) is never due. Nothing runs by itself:
a lab schedules ``trustlab retention run`` (cron, a systemd timer) or runs it by hand; ``--dry-run``
shows what is due without changing anything, and every run that changes something is audited.

**Anonymising** keeps the study's results analysable and removes what links them to a person:
each participant's code becomes a random id (``~anon-`` and 12 hex digits; no enrolment code can
look like that), and free-text answers, spoken transcripts and recordings, room presence (seated
or no longer), tablet links and withdrawal reasons are dropped (the tables and columns are the
personal data registry's, app.services.privacy.personal_data); in the audit log the random id
replaces the code and events about them keep no details. Nothing keeps the old code, so nobody — the
lab included — can link the data back. **Erasing** removes each participant as a withdrawal with
erasure does (app.services.privacy.erasure), allocation slots kept.

The clock is a parameter (``now``) so tests, and a lab checking its plan, can ask "what is due
on that day?" without waiting for it.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass, field
from datetime import datetime

from sqlalchemy import Executable, and_, delete, or_, select, update
from sqlalchemy.orm import Session

from app.errors import InvalidInput
from app.protocol import ItemKind, Protocol
from app.services import audit
from app.services.audit import Actor
from app.services.participants import participant_changes
from app.services.participants.participant_changes import Change
from app.services.privacy import erasure, personal_data
from app.services.privacy.personal_data import Anonymised
from app.services.studies import get_study, list_studies, protocol_of
from app.tables import (
    Participant,
    Response,
    Study,
    StudyStatus,
)

ANONYMOUS_PREFIX = "~anon-"
"""Anonymised participants' ids start with this; no enrolment code can (app.inputs)."""


@dataclass
class StudyRetention:
    """One study's retention deadline and what a run does (or did) about it."""

    study: str
    period: str | None
    then: str
    closed_at: datetime | None
    due_at: datetime | None
    due: bool
    participants: int
    """Participants still identifiable (neither anonymised nor erased)."""
    done: dict[str, int] = field(default_factory=dict)

    def describe(self) -> str:
        """One line for the command line."""
        if self.period is None:
            return f"{self.study}: no retention period declared (kept until erased by hand)"
        if self.due_at is None:
            return (
                f"{self.study}: identifiable data kept {self.period} after the study closes "
                "(it is open)"
            )
        when = f"{self.due_at:%Y-%m-%d}"
        if not self.due:
            return f"{self.study}: identifiable data kept until {when}, then {self.then}d"
        if self.participants == 0:
            return f"{self.study}: past {when}; nothing identifiable left"
        return (
            f"{self.study}: past {when}: {self.participants} participant"
            f"{'s' if self.participants != 1 else ''} to {self.then}"
        )

    def to_json(self) -> dict[str, object]:
        """For ``--json``."""
        return {
            "study": self.study,
            "period": self.period,
            "then": self.then,
            "closed_at": self.closed_at.isoformat() if self.closed_at else None,
            "due_at": self.due_at.isoformat() if self.due_at else None,
            "due": self.due,
            "participants": self.participants,
            "done": self.done,
        }


def deadline(study: Study) -> datetime | None:
    """When the study's identifiable data is due (None: no period declared, or still open)."""
    period = protocol_of(study).retention.period
    if period is None or study.status != StudyStatus.CLOSED or study.closed_at is None:
        return None
    return period.after(study.closed_at)


def _identifiable(db: Session, study: Study) -> list[Participant]:
    return list(
        db.scalars(
            select(Participant)
            .where(
                Participant.study_id == study.id,
                Participant.erased_at.is_(None),
                Participant.anonymised_at.is_(None),
            )
            .order_by(Participant.id)
        )
    )


def status(db: Session, study: Study, *, now: datetime) -> StudyRetention:
    """Where one study stands on ``now``."""
    spec = protocol_of(study).retention
    due_at = deadline(study)
    return StudyRetention(
        study=study.name,
        period=spec.period.describe() if spec.period else None,
        then=spec.then,
        closed_at=study.closed_at,
        due_at=due_at,
        due=due_at is not None and now >= due_at,
        participants=len(_identifiable(db, study)),
    )


def run(
    db: Session,
    *,
    now: datetime,
    actor: Actor,
    secret: bytes,
    dry_run: bool,
    study_name: str | None = None,
) -> list[StudyRetention]:
    """Anonymise or erase what is due on ``now`` (each study in one transaction, audited), or
    with ``dry_run`` only say what is due. Every study with a period declared is reported."""
    chosen = [get_study(db, study_name)] if study_name else list_studies(db, archived=None)
    if study_name and protocol_of(chosen[0]).retention.period is None:
        raise InvalidInput(f"study {study_name!r} declares no retention period ([retention])")
    report = []
    for study in chosen:
        state = status(db, study, now=now)
        if state.period is None and not study_name:
            continue
        if state.due and state.participants and not dry_run:
            state.done = _apply(db, study, now=now, actor=actor, secret=secret)
            db.commit()
            erasure.after_erasures(db)
        report.append(state)
    return report


def _apply(
    db: Session, study: Study, *, now: datetime, actor: Actor, secret: bytes
) -> dict[str, int]:
    protocol = protocol_of(get_study(db, study.name, for_update=True))
    participants = _identifiable(db, study)
    then = protocol.retention.then
    done: dict[str, int] = {}
    with erasure.opened_guards(db, study, participants):
        for participant in participants:
            seat = erasure.seat_of(db, participant)
            if then == "erase":
                pseudonym = erasure.free_erased_code(db, secret, study, participant.code)
                removed = erasure.erase(db, study, participant, now=now, pseudonym=pseudonym)
                change = Change.ERASED
            else:
                removed = _anonymise(db, study, protocol, participant, now=now)
                change = Change.ANONYMISED
            for table, n in removed.items():
                done[table] = done.get(table, 0) + n
            # every view of each participant (the study's pages, a tablet, a station) learns it
            participant_changes.participant_changed(db, participant, change, station=seat)
    audit.record(
        db,
        actor=actor,
        action=f"retention.{'erased' if then == 'erase' else 'anonymised'}",
        study_id=study.id,
        subject=study.name,
        details={"participants": len(participants), "rows": done},
    )
    return {"participants": len(participants), **done}


def _anonymous_id(db: Session, study: Study) -> str:
    while True:
        candidate = ANONYMOUS_PREFIX + secrets.token_hex(6)
        taken = db.scalar(
            select(Participant.id).where(
                Participant.study_id == study.id, Participant.code == candidate
            )
        )
        if taken is None:
            return candidate


def _anonymise(
    db: Session, study: Study, protocol: Protocol, participant: Participant, *, now: datetime
) -> dict[str, int]:
    """Inside :func:`erasure.opened_guards`: a random id for the code, and free text,
    transcripts, recordings, presence, tablet link and reasons gone, as the personal data
    registry says (app.services.privacy.personal_data); rows changed per kind."""
    owned = participant.id
    code = participant.code
    anonymous = _anonymous_id(db, study)
    text_items = [
        and_(Response.instrument == instrument.key, Response.item == item.key)
        for instrument in protocol.questionnaires.instruments
        for item in instrument.items
        if item.kind == ItemKind.TEXT
    ]
    changed: dict[str, int] = {}
    statements: dict[str, Executable] = {}
    for entry in personal_data.anonymised(Anonymised.FREE_TEXT_DELETED):
        assert entry.table is Response, entry  # the free-text items are questionnaire items
        if text_items:
            statements["free_text"] = delete(Response).where(
                Response.participant_id == owned, or_(*text_items)
            )
    for entry in personal_data.anonymised(Anonymised.DELETED):
        table = entry.sql
        statements[entry.name] = delete(table).where(table.c.participant_id == owned)
    erasure.drop_study_derived(db, study.id, personal_data.anonymised(Anonymised.STUDY_DROPPED))
    for entry in personal_data.TABLES:
        table = entry.sql
        for column in entry.cleared:
            statements[column] = (
                update(table)
                .where(table.c.participant_id == owned, table.c[column].is_not(None))
                .values({column: None})
            )
    for kind, statement in statements.items():
        result = db.execute(statement)
        if result.rowcount:  # type: ignore[attr-defined]
            changed[kind] = int(result.rowcount)  # type: ignore[attr-defined]
    for entry in personal_data.TABLES:  # their own rows: any occurrence is their code
        if not entry.naming:
            continue
        table = entry.sql
        rows = db.execute(
            select(table.c.id, *(table.c[c] for c in entry.naming)).where(
                table.c.participant_id == owned
            )
        )
        for row_id, *values in rows:
            renamed = {
                column: value.replace(code, anonymous)
                for column, value in zip(entry.naming, values, strict=True)
                if value and code in value
            }
            if renamed:
                db.execute(update(table).where(table.c.id == row_id).values(renamed))
                changed["names"] = changed.get("names", 0) + len(renamed)
    erasure.scrub_audit(db, study, code, anonymous, about={"anonymised": True})
    erasure.scrub_devices(db, code)
    db.expire_all()
    participant = db.get_one(Participant, owned)
    participant.code = anonymous
    participant.anonymised_at = now
    participant.withdrawal_reason = ""
    participant.token_hash = None
    participant.token_generation += 1
    return changed
