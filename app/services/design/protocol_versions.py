"""A study's protocol over time: a draft's edits saved as versions, each checked against the
version its editor started from, and the last change undone (issue 50).

Every save is a new :class:`~app.tables.ProtocolVersion` (the text byte for byte), checked by the
rules study creation uses, and the study row takes it as its current protocol. Two people editing
at once: each save names the SHA-256 of the protocol its editor started from, and when that is
no longer the study's, the save is refused with what changed in between (a diff of the two
texts), so the second person can merge by hand and nothing either typed is lost. An undo saves
the previous version's text again as a new version: history is never rewritten.

A draft's protocol changes freely. A live study's changes only as an amendment: with a reason
(audited), and only where its participants stay comparable (app.services.design.comparability);
anything else is a new study started from the changed protocol (a split). Each participant and
session records the version it ran under. A pilot's protocol does not change: its participants
ran under it (reset the pilot and go back to draft; app.services.design.study_phases).
"""

from __future__ import annotations

import difflib

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput
from app.protocol import LoadedProtocol, parse_protocol
from app.services import audit, studies
from app.services.audit import Actor
from app.services.design import comparability
from app.tables import (
    Participant,
    ProtocolVersion,
    SessionStatus,
    Study,
    StudyPhase,
    StudySession,
)

REASON_MAX = 2000


class EditConflict(Conflict):
    """The protocol changed since the editor opened it; ``changes``: what changed, as a diff;
    ``headline``: the message without its advice (a form that carries the edit over itself
    gives its own)."""

    def __init__(self, headline: str, advice: str, changes: str) -> None:
        super().__init__(f"{headline}. {advice}")
        self.headline = headline
        self.changes = changes

    @property
    def extra(self) -> dict[str, object]:
        return {"changes": self.changes}


def versions(db: Session, study: Study) -> list[ProtocolVersion]:
    """Every version of the study's protocol, newest first."""
    query = (
        select(ProtocolVersion)
        .where(ProtocolVersion.study_id == study.id)
        .order_by(ProtocolVersion.number.desc())
    )
    return list(db.scalars(query))


def source_of(db: Session, study: Study, sha256: str) -> str | None:
    """The text of the study's protocol version with this SHA-256 (None: it never had one):
    what a form drawn from that version is written into."""
    if sha256 == study.protocol_sha256:
        return study.protocol_source
    query = (
        select(ProtocolVersion.source)
        .where(ProtocolVersion.study_id == study.id, ProtocolVersion.sha256 == sha256)
        .limit(1)
    )
    return db.scalar(query)


def current_number(db: Session, study: Study) -> int:
    """The number of the study's current protocol version (1 for a study never edited)."""
    query = select(func.max(ProtocolVersion.number)).where(ProtocolVersion.study_id == study.id)
    return db.scalar(query) or 1


class NotComparable(Conflict):
    """A live study's new version would break comparability; ``problems``: why, one each."""

    def __init__(self, study: str, problems: list[str]) -> None:
        super().__init__(
            f"this change would make the participants of {study!r} incomparable, so it needs a "
            f"new study (a split): {'; '.join(problems)}"
        )
        self.problems = problems

    @property
    def extra(self) -> dict[str, object]:
        return {"problems": self.problems}


def require_editable(study: Study) -> None:
    """Refuse to change a pilot's protocol, saying what to do (a draft's changes freely, a live
    study's as an amendment)."""
    if study.phase == StudyPhase.PILOT:
        raise Conflict(
            f"study {study.name!r} is in its pilot: its pilot participants run under this "
            "protocol. Reset the pilot and take it back to draft to change it"
        )


def frozen_because(study: Study) -> str:
    """Why the study's protocol cannot change now ('' when it can)."""
    try:
        require_editable(study)
    except Conflict as exc:
        return exc.message
    return ""


def is_amendment(study: Study) -> bool:
    """Whether a change to the study's protocol is an amendment of a live study."""
    return study.phase == StudyPhase.LIVE


def amendment_changes(db: Session, study: Study, text: str) -> str:
    """For a live study: what ``text`` changes against the version in force, as a diff (''
    for a draft, or no change)."""
    if not is_amendment(study) or text == study.protocol_source:
        return ""
    number = current_number(db, study)
    return changes_between(
        study.protocol_source,
        text,
        older_name=f"version {number} (in force)",
        newer_name="your change",
    )


def check_amendment(db: Session, study: Study, loaded: LoadedProtocol, reason: str) -> None:
    """Refuse a live study's new version without a reason, while a session runs (a session runs
    under one version), or one that breaks comparability."""
    running = db.scalar(
        select(func.count())
        .select_from(StudySession)
        .join(Participant, Participant.id == StudySession.participant_id)
        .where(Participant.study_id == study.id, StudySession.status == SessionStatus.RUNNING)
    )
    if running:
        raise Conflict(
            f"{running} session(s) of {study.name!r} are running: save the amendment once they "
            "have ended (each session runs under one protocol version)"
        )
    if not reason:
        raise InvalidInput(
            f"study {study.name!r} is live: a change to its protocol is an amendment; say what "
            "changed and why (kept with the version and in the audit log)"
        )
    current = studies.protocol_of(study)
    used = comparability.in_use(db, study, current)
    problems = comparability.problems(current, loaded.protocol, used)
    if problems:
        raise NotComparable(study.name, problems)


def changes_between(older: str, newer: str, *, older_name: str, newer_name: str) -> str:
    """What changed from one protocol text to another, as a unified diff (for people)."""
    lines = difflib.unified_diff(
        older.splitlines(),
        newer.splitlines(),
        fromfile=older_name,
        tofile=newer_name,
        lineterm="",
    )
    return "\n".join(lines)


def _check_base(db: Session, study: Study, base_sha256: str) -> None:
    """Refuse a save whose editor started from another version than the study's current one."""
    if base_sha256 == study.protocol_sha256:
        return
    history = versions(db, study)
    current = history[0]
    base = next((v for v in history if v.sha256 == base_sha256), None)
    who = f"version {current.number}, saved by {current.saved_by or 'someone'} at " + (
        f"{current.saved_at:%Y-%m-%d %H:%M} UTC"
    )
    if base is None:
        changes = ""
        started = "a version this study never had"
    else:
        changes = changes_between(
            base.source,
            current.source,
            older_name=f"version {base.number} (where your edit started)",
            newer_name=who,
        )
        started = f"version {base.number}"
    raise EditConflict(
        f"the protocol of {study.name!r} changed while you edited it: you started from "
        f"{started}, and it is now {who}",
        "Your text is kept below, now to be saved over that version: carry the changes shown "
        "into it (or your save undoes them), then save again",
        changes,
    )


def _apply(
    db: Session,
    study: Study,
    loaded: LoadedProtocol,
    *,
    actor: Actor,
    reason: str,
    action: str,
) -> ProtocolVersion:
    """Make ``loaded`` the study's protocol as a new version; audited; no commit."""
    population = studies.check_population_use(db, loaded.protocol)
    number = current_number(db, study) + 1
    before = study.protocol_sha256
    version = ProtocolVersion(
        study_id=study.id,
        number=number,
        sha256=loaded.sha256,
        source=loaded.source_text,
        saved_by=actor.name,
        reason=reason,
        phase=study.phase,
    )
    db.add(version)
    study.protocol = loaded.protocol.model_dump(mode="json")
    study.protocol_source = loaded.source_text
    study.protocol_sha256 = loaded.sha256
    if study.phase == StudyPhase.DRAFT:
        # Nobody has been allocated in a draft: a blinded draft's labels are drawn again for
        # the conditions it has now (a live study's conditions cannot change).
        study.neutral_labels = studies.draw_neutral_labels(loaded.protocol)
    audit.record(
        db,
        actor=actor,
        action=action,
        study_id=study.id,
        subject=study.name,
        details={
            "version": number,
            "from_sha256": before,
            "protocol_sha256": loaded.sha256,
            "phase": study.phase,
        }
        | ({"reason": reason} if reason else {})
        | (population or {}),
    )
    return version


def save_protocol(
    db: Session,
    *,
    name: str,
    loaded: LoadedProtocol,
    base_sha256: str,
    actor: Actor,
    reason: str = "",
) -> ProtocolVersion | None:
    """Save ``loaded`` as the draft study's next protocol version; commits. None when it is the
    current protocol already (nothing to save).

    A live study's version is an amendment: ``reason`` is required and the change must keep
    its participants comparable (:func:`check_amendment`).

    Raises Conflict for a pilot, EditConflict when the protocol changed since the editor opened
    it (``base_sha256``), NotComparable for an amendment that needs a split, and InvalidInput as
    study creation does (and for an amendment without a reason)."""
    study = studies.get_study(db, name, for_update=True)
    require_editable(study)
    _check_base(db, study, base_sha256)
    reason = reason.strip()[:REASON_MAX]
    if loaded.sha256 == study.protocol_sha256:
        return None
    if is_amendment(study):
        check_amendment(db, study, loaded, reason)
    version = _apply(db, study, loaded, actor=actor, reason=reason, action="study.protocol_saved")
    db.commit()
    return version


def undo_last_change(db: Session, *, name: str, base_sha256: str, actor: Actor) -> ProtocolVersion:
    """Save the version before the current one again, as the next version; commits.

    Raises Conflict for a study that is not a draft or has nothing to undo, and EditConflict
    when the protocol changed since the page offering the undo was drawn."""
    study = studies.get_study(db, name, for_update=True)
    require_editable(study)
    _check_base(db, study, base_sha256)
    history = versions(db, study)
    if len(history) < 2:
        raise Conflict(f"the protocol of {study.name!r} has not been changed: nothing to undo")
    current, previous = history[0], history[1]
    loaded = parse_protocol(previous.source, source=f"version {previous.number}")
    reason = f"undid version {current.number} (back to version {previous.number})"
    if is_amendment(study):
        check_amendment(db, study, loaded, reason)
    version = _apply(db, study, loaded, actor=actor, reason=reason, action="study.protocol_saved")
    db.commit()
    return version
