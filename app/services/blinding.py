"""What a blinded study hides, from whom, and until when.

A protocol with ``[study] blinded = true`` hides two things from staff:

- **the conditions**: experimenters see the neutral labels (*Group A*, *Group B*); admins and
  analysts see the real ones (:attr:`app.services.audit.Actor.sees_conditions`);
- **the learners**: their probabilities, the confidence level behind each reply and the history
  of replies. C1's Exp3 starts at exactly 1/K for every question and C2's policy does not, so any
  of these would show an experimenter the condition at the first prompt. While the study is
  *sealed* (blinded and not yet unblinded) nobody on the staff sees them, whatever their role.

The robot still receives everything it needs (its own routes and WebSocket are not staff
responses), and the command line, run by whoever holds the server and its database, is not
blinded.

A study stays sealed until an admin unblinds it (:func:`unblind`, audited, once and for good);
from then on everyone sees conditions and learners. Unblinding needs the study closed for
enrolment, and an unblinded study cannot be reopened: a participant enrolled after it would run
unblinded.
"""

from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict
from app.protocol import Protocol
from app.services import audit, stations
from app.services.audit import Actor
from app.services.studies import get_study, protocol_of
from app.tables import Participant, ParticipantStatus, Study, StudyStatus, utcnow

LEARNERS_SEALED = (
    "this study is blinded: the learners' probabilities and confidence levels are hidden until an "
    "admin unblinds it"
)
"""Why learner data is missing, in the words every page and refusal uses."""


def sealed(protocol: Protocol, *, unblinded: bool) -> bool:
    """The rule itself: a blinded protocol whose study has not been unblinded (the runtime asks
    with the seat it has read, app.services.step_store; pages with the study row)."""
    return protocol.study.blinded and not unblinded


def is_sealed(study: Study) -> bool:
    """Whether the study is blinded and has not been unblinded yet."""
    return sealed(protocol_of(study), unblinded=study.unblinded_at is not None)


def shows_conditions(study: Study, actor: Actor) -> bool:
    """Whether ``actor`` may see the study's real condition ids (else the neutral labels)."""
    return not is_sealed(study) or actor.sees_conditions


def shows_learners(study: Study) -> bool:
    """Whether staff may see the learners' probabilities, confidence levels and reply history."""
    return not is_sealed(study)


def unfinished_participants(db: Session, study: Study) -> int:
    """Active participants: after unblinding, their experimenters would see their learners."""
    active = (Participant.study_id == study.id) & (Participant.status == ParticipantStatus.ACTIVE)
    return db.scalar(select(func.count()).select_from(Participant).where(active)) or 0


def unblind(db: Session, *, name: str, actor: Actor) -> Study:
    """Lift a blinded study's blinding for good (admins only; the caller checks); commits."""
    study = get_study(db, name, for_update=True)
    if not protocol_of(study).study.blinded:
        raise Conflict(f"study {name!r} is not blinded: there is nothing to unblind")
    if study.unblinded_at is not None:
        raise Conflict(f"study {name!r} was unblinded on {study.unblinded_at:%Y-%m-%d %H:%M} UTC")
    if study.status != StudyStatus.CLOSED:
        raise Conflict(
            f"close study {name!r} for enrolment first: participants enrolled after unblinding "
            "would run unblinded"
        )
    study.unblinded_at = utcnow()
    audit.record(
        db,
        actor=actor,
        action="study.unblinded",
        study_id=study.id,
        subject=study.name,
        details={"active_participants": unfinished_participants(db, study)},
    )
    # Open dashboards refetch, and their data now carries the learners and the real conditions.
    events.publish(db, topics=[stations.study_topic(study.id)], type="study.unblinded")
    db.commit()
    return study
