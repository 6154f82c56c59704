"""A study's phase: draft, pilot, live (issue 50), as REDCap's development and production.

- **draft**: the protocol may still change (app.web.protocol_editor); nobody enrols. A study a
  lab designs in the browser starts here.
- **pilot**: the study runs as it will, but everyone enrolled is a *pilot participant*: allocated
  from the pilot's own sequence (app.randomisation.pilot_seed), marked as pilot on every page and
  export, left out of the analyses and reports, and deleted by a reset.
- **live**: the protocol is frozen (its SHA-256 is in the audit event, as a pre-registration
  names it) and the concealed sequence starts at its first entry, whatever the pilot drew.
  A study created from a finished protocol file (the command line, the API) starts live.

"Closed" is not a phase: it is whether a study enrols (app.services.studies.set_study_status),
in any phase. The way back is short on purpose: a pilot may go back to draft once its
participants are reset (their data were collected under the protocol a draft may change); a live
study never goes back.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput
from app.services import audit
from app.services.audit import Actor
from app.services.participants import participant_changes
from app.services.participants.participant_changes import Change
from app.services.privacy import erasure
from app.services.studies import get_study
from app.tables import Allocation, Participant, Study, StudyPhase, utcnow

RESET_PSEUDONYM_PREFIX = "~pilot-"
"""What a reset pilot's code becomes in the audit log (with their row id): automatic pilot codes
start again at ``pilot-001`` after a reset, and the log must not mix the two."""

NEXT_PHASES = {
    StudyPhase.DRAFT: (StudyPhase.PILOT, StudyPhase.LIVE),
    StudyPhase.PILOT: (StudyPhase.DRAFT, StudyPhase.LIVE),
    StudyPhase.LIVE: (),
}
"""Where each phase may go (the pages offer exactly these)."""


def phase_of(study: Study) -> StudyPhase:
    """The study's phase as the enumeration."""
    return StudyPhase(study.phase)


def parse_phase(value: str) -> StudyPhase:
    """A phase typed or sent (``draft``, ``pilot``, ``live``), or a one-line refusal."""
    try:
        return StudyPhase(value.strip().lower())
    except ValueError:
        names = ", ".join(phase.value for phase in StudyPhase)
        raise InvalidInput(f"phase {value!r}: choose one of {names}") from None


def pilot_count(db: Session, study: Study) -> int:
    """How many pilot participants the study holds (withdrawn ones included)."""
    query = select(func.count()).where(Participant.study_id == study.id, Participant.pilot)
    return db.scalar(query) or 0


def set_phase(db: Session, *, name: str, phase: StudyPhase, actor: Actor) -> Study:
    """Move study ``name`` to ``phase``; commits. Going live records the frozen protocol's
    SHA-256; the same phase again changes nothing.

    Raises Conflict for a live study (it stays live) and for a pilot going back to draft while
    pilot participants remain."""
    study = get_study(db, name, for_update=True)
    current = phase_of(study)
    if phase == current:
        return study
    if phase not in NEXT_PHASES[current]:
        raise Conflict(
            f"study {study.name!r} is live: its protocol and its sequence are frozen, so it "
            "stays live (close its enrolment, or start a new study from a copy of its protocol)"
        )
    if phase == StudyPhase.DRAFT:
        pilots = pilot_count(db, study)
        if pilots:
            raise Conflict(
                f"study {study.name!r} has {pilots} pilot participant(s), whose data were "
                "collected under the protocol a draft may change: reset the pilot first"
            )
    details: dict[str, object] = {"from": current.value, "to": phase.value}
    if phase == StudyPhase.LIVE:
        study.live_at = utcnow()
        details |= {"protocol_sha256": study.protocol_sha256, "pilots": pilot_count(db, study)}
    study.phase = phase
    audit.record(
        db,
        actor=actor,
        action="study.phase_changed",
        study_id=study.id,
        subject=study.name,
        details=details,
    )
    db.commit()
    return study


@dataclass
class PilotReset:
    """What a pilot reset deleted."""

    study: str
    participants: list[str] = field(default_factory=list)
    removed: dict[str, int] = field(default_factory=dict)

    def describe(self) -> str:
        """One line for the command line and the page."""
        if not self.participants:
            return f"study {self.study!r} has no pilot participants: nothing to reset"
        rows = sum(self.removed.values())
        return (
            f"reset the pilot of {self.study!r}: deleted {len(self.participants)} pilot "
            f"participant(s) ({', '.join(self.participants)}) and {rows} row(s) of their data"
        )


def reset_pilot(db: Session, *, name: str, actor: Actor) -> PilotReset:
    """Delete every pilot participant of study ``name`` and everything of theirs, in one
    transaction; commits. Their audit events stay, under ``~pilot-<id>`` with their details
    dropped, and the reset itself is recorded. Live participants are not touched; neither is
    the live sequence (the pilot's has its own seed). Any phase: pilots of a study that has
    gone live can still be reset."""
    study = get_study(db, name, for_update=True)
    pilots = list(
        db.scalars(
            select(Participant)
            .where(Participant.study_id == study.id, Participant.pilot)
            .order_by(Participant.id)
        )
    )
    result = PilotReset(study=study.name, participants=[p.code for p in pilots])
    if not pilots:
        return result
    for participant in pilots:  # their tablets and consoles learn it when this commits
        seat = erasure.seat_of(db, participant)
        participant_changes.participant_changed(db, participant, Change.ERASED, station=seat)
    ids = [participant.id for participant in pilots]
    with erasure.opened_guards(db, study, pilots):
        for participant_id in ids:
            removed = erasure.remove_data(
                db,
                study,
                db.get_one(Participant, participant_id),  # remove_data expires what it read
                pseudonym=f"{RESET_PSEUDONYM_PREFIX}{participant_id}",
                about={"pilot_reset": True},
            )
            for table, n in removed.items():
                result.removed[table] = result.removed.get(table, 0) + n
    # A pilot replacement points at the pilot it replaces: the allocations go first.
    allocations = db.execute(delete(Allocation).where(Allocation.participant_id.in_(ids)))
    people = db.execute(delete(Participant).where(Participant.id.in_(ids)))
    result.removed["allocation"] = int(allocations.rowcount or 0)  # type: ignore[attr-defined]
    result.removed["participant"] = int(people.rowcount or 0)  # type: ignore[attr-defined]
    audit.record(
        db,
        actor=actor,
        action="study.pilot_reset",
        study_id=study.id,
        subject=study.name,
        details={"participants": len(pilots), "removed": dict(result.removed)},
    )
    db.commit()
    erasure.after_erasures(db)
    return result
