"""Each participant's language: which one applies, who may set it, and when it may change.

Every participant-facing text comes from the study's protocol in the participant's language
(:meth:`app.protocol.Protocol.in_language`), so the tablet, the room and the robots all follow
this one value. It is set at enrolment, or chosen on the tablet's first page when the protocol
allows; once the participant's first session has started it stays, since answers given in two
languages are not comparable, unless an admin overrides it with a recorded reason.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import exists, select
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput, PermissionDenied
from app.i18n import protocol_texts
from app.i18n.languages import UnknownLanguage, check_code
from app.protocol import Protocol
from app.services import audit
from app.services.audit import Actor
from app.services.participants import participant_changes
from app.services.participants.participant_changes import Change
from app.tables import Participant, ParticipantStatus, Role, StudySession


def language_of(participant_language: str | None, protocol: Protocol) -> str:
    """The language a participant sees: their own, or the protocol's first when not chosen."""
    return participant_language or protocol.default_language


def protocol_for(participant_language: str | None, protocol: Protocol) -> Protocol:
    """The protocol as this participant sees and hears it."""
    return protocol.in_language(language_of(participant_language, protocol))


def translation_summary(protocol: Protocol) -> dict[str, dict[str, Any]]:
    """Each further language's translation as the codebook and the report cite it: its
    ``source`` ('' when the protocol does not say) and, per instrument, its title, citation
    and items in that language."""
    summary: dict[str, dict[str, Any]] = {}
    for code in protocol.study.languages[1:]:
        localised = protocol.in_language(code)
        source = protocol.translations.get(code, {}).get(protocol_texts.SOURCE, "")
        summary[code] = {
            "source": source.strip() if isinstance(source, str) else "",
            "instruments": {
                instrument.key: {
                    "title": instrument.title,
                    "citation": instrument.citation,
                    "items": {item.key: item.text for item in instrument.items},
                }
                for instrument in localised.questionnaires.instruments
            },
        }
    return summary


def gloss(protocol: Protocol, *, category: str, action: int, asked: str) -> str:
    """The question ``asked`` (as stored: in the participant's words) in the protocol's own
    language, for staff who do not read the participant's; '' when it is already in it (or the
    protocol no longer has that question)."""
    try:
        own = protocol.category(category).questions[action]
    except (KeyError, IndexError):
        return ""
    return "" if own == asked else own


def offered(protocol: Protocol, language: str, *, study_name: str) -> str:
    """``language`` if the study offers it; InvalidInput naming the ones it does otherwise."""
    try:
        check_code(language)
    except UnknownLanguage as exc:
        raise InvalidInput(str(exc)) from None
    if language not in protocol.study.languages:
        raise InvalidInput(
            f"study {study_name!r} is not run in {language!r}: its languages are "
            f"{', '.join(protocol.study.languages)}"
        )
    return language


def chooses_on_tablet(protocol: Protocol) -> bool:
    """Whether a participant enrolled without a language chooses one on the tablet."""
    return protocol.study.language_choice and len(protocol.study.languages) > 1


def needs_choice(participant: Participant, protocol: Protocol) -> bool:
    """Whether the tablet should ask this participant for their language first."""
    return participant.language is None and chooses_on_tablet(protocol)


def has_started(db: Session, participant: Participant) -> bool:
    """Whether any of the participant's sessions has been started."""
    return bool(db.scalar(select(exists().where(StudySession.participant_id == participant.id))))


def set_language(
    db: Session,
    *,
    participant: Participant,
    protocol: Protocol,
    study_name: str,
    language: str,
    actor: Actor,
    actor_role: Role | None = None,
    override_reason: str = "",
) -> Participant:
    """Set the participant's language; audited; commits.

    Refused (Conflict) once a session has started, unless ``override_reason`` is given by an
    admin (``actor_role``); refused for a withdrawn participant and for a language the study does
    not offer."""
    offered(protocol, language, study_name=study_name)
    if participant.status == ParticipantStatus.WITHDRAWN:
        raise Conflict(f"participant {participant.code!r} has withdrawn")
    previous = language_of(participant.language, protocol)
    reason = override_reason.strip()[:500]
    if has_started(db, participant) and language != previous:
        if not reason:
            raise Conflict(
                f"{participant.code} has started a session in {previous!r}: their answers must "
                "stay comparable, so the language stays; an admin may override with a reason"
            )
        if actor_role is not Role.ADMIN:
            raise PermissionDenied("only an admin may change the language after a session began")
    participant.language = language
    audit.record(
        db,
        actor=actor,
        action="participant.language_set",
        study_id=participant.study_id,
        subject=participant.code,
        details={"from": previous, "to": language, **({"override": reason} if reason else {})},
    )
    # the tablet and the room now speak it; the console and the study's pages show it
    participant_changes.participant_changed(db, participant, Change.LANGUAGE)
    db.commit()
    return participant
