"""What a blinded study hides, from whom, and until when.

A protocol with ``[study] blinded = true`` hides two things from staff:

- **the conditions**: experimenters see the neutral labels (*Group A*, *Group B*); admins and
  analysts see the real ones (:attr:`app.services.audit.Actor.sees_conditions`). Which condition
  carries which label is drawn at random when the study is created (app.services.studies) and
  kept with the study's secrets: the protocol, which experimenters read, only says which labels
  there are. Neutral labels are listed in label order, never in the protocol's order of the
  conditions (the first would be C1). The assignment is shown only once the study is unblinded
  (recorded in the audit entry ``study.unblinded`` and on the study page);
- **the learners**: their probabilities, the confidence level behind each reply and the history
  of replies. C1's Exp3 (like a ``bayes`` condition's exact filter at its uniform prior) starts at
  exactly 1/K for every question and C2's policy does not, so any of these would show an
  experimenter the condition at the first prompt. While the study is *sealed* (blinded and not
  yet unblinded) nobody on the staff sees them, whatever their role.

The robot still receives everything it needs (its own routes and WebSocket are not staff
responses), and the command line, run by whoever holds the server and its database, is not
blinded.

**Allocation concealment** is a third secret, kept from everyone (admins too) while the study
enrols: where each allocation stands in its stratum's sequence (its index, its block's number and
size, its place in the block) and the seed. Knowing the blocks, one can tell the rest of a block
before it is allocated. Nothing shows them before :func:`allocation_disclosed`; the audit log has
stopped recording them, and older entries that did are shown without them until then
(:func:`visible_details`). The seed itself is never shown (exports carry its SHA-256 only).

A study stays sealed until an admin unblinds it (:func:`unblind`, audited, once and for good);
from then on everyone sees conditions and learners. Unblinding needs the study closed for
enrolment, and an unblinded study cannot be reopened: a participant enrolled after it would run
unblinded.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict
from app.protocol import Protocol
from app.services import audit, topics
from app.services.audit import Actor
from app.services.privacy.sites import STUDY_WIDE
from app.services.studies import get_study, protocol_of
from app.tables import Participant, ParticipantStatus, Study, StudyStatus, utcnow

LEARNERS_SEALED = (
    "this study is blinded: the learners' probabilities and confidence levels are hidden until an "
    "admin unblinds it"
)
"""Why learner data is missing, in the words every page and refusal uses."""


def sealed(protocol: Protocol, *, unblinded: bool) -> bool:
    """The rule itself: a blinded protocol whose study has not been unblinded (the runtime asks
    with the seat it has read, app.services.sessions.step_store; pages with the study row)."""
    return protocol.study.blinded and not unblinded


def is_sealed(study: Study) -> bool:
    """Whether the study is blinded and has not been unblinded yet."""
    return sealed(protocol_of(study), unblinded=study.unblinded_at is not None)


def shows_conditions(study: Study, actor: Actor) -> bool:
    """Whether ``actor`` may see the study's real condition ids (else the neutral labels)."""
    return not is_sealed(study) or actor.sees_conditions


HIDDEN_GROUP = "Hidden group"
"""What a blinded role sees of a condition the study has no neutral label for (none should exist:
a blinded study gets its labels when it is created, migration 0012 gave older ones theirs)."""


def neutral_label(study: Study, condition_id: str) -> str:
    """The neutral label this study gave ``condition_id``."""
    return (study.neutral_labels or {}).get(condition_id, HIDDEN_GROUP)


def condition_labels(study: Study, actor: Actor) -> dict[str, str]:
    """Each condition id → what ``actor`` may see of it, in the order to list them: the
    protocol's for real ids, the labels' own (alphabetical) for neutral ones."""
    ids = [condition.id for condition in protocol_of(study).conditions]
    if shows_conditions(study, actor):
        return {condition_id: condition_id for condition_id in ids}
    labelled = {condition_id: neutral_label(study, condition_id) for condition_id in ids}
    return dict(sorted(labelled.items(), key=lambda pair: (pair[1], pair[0])))


def shows_learners(study: Study) -> bool:
    """Whether staff may see the learners' probabilities, confidence levels and reply history."""
    return not is_sealed(study)


CONCEALED_ALLOCATION_DETAILS = frozenset(
    {"sequence_index", "block_number", "block_size", "position_in_block"}
)
"""Audit-detail keys that place an allocation in its sequence (older entries recorded them)."""


def allocation_disclosed(study: Study) -> bool:
    """Whether where each allocation stands in the sequence may be shown: once the study is
    closed for enrolment, and if it is blinded, once it has been unblinded too (which also keeps
    it closed for good). Only audit entries written before issue 35 hold these details: a study
    that is not blinded and is reopened after they were read continues the same sequence."""
    return study.status == StudyStatus.CLOSED and not is_sealed(study)


def visible_details(details: dict[str, Any], *, disclosed: bool) -> dict[str, Any]:
    """An audit entry's details as staff may read them: without the allocation's place in its
    sequence unless its study has :func:`allocation_disclosed` it."""
    if disclosed:
        return details
    return {key: value for key, value in details.items() if key not in CONCEALED_ALLOCATION_DETAILS}


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
        details={
            "active_participants": unfinished_participants(db, study),
            "neutral_labels": study.neutral_labels or {},
        },
    )
    # Open dashboards refetch, and their data now carries the learners and the real conditions.
    events.publish(
        db, topics=[topics.study_topic(study.id)], type="study.unblinded", site=STUDY_WIDE
    )
    db.commit()
    return study
