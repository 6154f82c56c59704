"""Versions of a study's consent text, and where each participant stands with them.

An ethics board asks which words each participant agreed to. A study's protocol, and so its
consent text, is fixed when the study is created; when the board approves a change, an admin adds
the new wording as the next version (``trustlab study consent`` or the study page). Version 1 is
the protocol's own text: it is read from the protocol until a later version is added, and stored
then, so the table holds every version once it holds any. Nothing here is ever edited or deleted.

Every acceptance (and, asked again, every refusal) is a :class:`~app.tables.ConsentRecord`: the
version, the language, the SHA-256 of the exact words shown, and when. A participant who accepted
an older version than the current one needs to consent again; with the protocol's
``reconsent_before_next_session`` the tablet asks them first and their next session waits for it
(app.services.participants.questionnaires, app.services.sessions.runtime), otherwise staff pages
only say so. A refusal does not withdraw anyone: staff see it and decide.
"""

from __future__ import annotations

import hashlib
import tomllib
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import case, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict, InvalidInput
from app.protocol import Protocol, mentions_audio_recording
from app.services import audit, studies
from app.services.audit import Actor
from app.services.privacy.sites import STUDY_WIDE
from app.services.topics import participant_topic, station_topic_of, study_topic
from app.tables import (
    ConsentRecord,
    ConsentVersion,
    Participant,
    ParticipantStatus,
    Station,
    Study,
    utcnow,
)

TEXT_MAX = 2000
"""As for the protocol's own consent text (app.protocol.Text)."""
LABEL_MAX = 64
REASON_MAX = 2000


def digest(text: str) -> str:
    """The SHA-256 of a text's exact words (UTF-8), as every consent record keeps it."""
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class Version:
    """One version of a study's consent text in every language of the study."""

    number: int
    label: str
    texts: dict[str, str]
    sha256: dict[str, str]
    created_at: datetime
    created_by: str
    reason: str


@dataclass(frozen=True)
class Shown:
    """The consent text a participant is shown: the current version in their language."""

    number: int
    label: str
    language: str
    text: str
    sha256: str


def _protocol_version(study: Study, protocol: Protocol) -> Version:
    """Version 1: the protocol's own text, in each of its languages."""
    texts = {
        code: protocol.in_language(code).questionnaires.consent.text
        for code in protocol.study.languages
    }
    return Version(
        number=1,
        label=protocol.questionnaires.consent.version,
        texts=texts,
        sha256={code: digest(text) for code, text in texts.items()},
        created_at=study.created_at,
        created_by=study.created_by,
        reason="the protocol's own text",
    )


def _version(row: ConsentVersion) -> Version:
    return Version(
        number=row.version,
        label=row.label,
        texts=dict(row.texts),
        sha256=dict(row.sha256),
        created_at=row.created_at,
        created_by=row.created_by,
        reason=row.reason,
    )


def _stored(db: Session, study: Study) -> list[Version]:
    rows = db.scalars(
        select(ConsentVersion)
        .where(ConsentVersion.study_id == study.id)
        .order_by(ConsentVersion.version)
    )
    return [_version(row) for row in rows]


def versions(db: Session, study: Study) -> list[Version]:
    """Every version of the study's consent text, oldest first."""
    return _stored(db, study) or [_protocol_version(study, studies.protocol_of(study))]


def shown(db: Session, *, study_id: int, protocol: Protocol) -> Shown:
    """The current consent text as a participant reading ``protocol`` (the study's protocol in
    their language, app.services.participants.languages.protocol_for) sees it."""
    language = protocol.default_language
    row = db.execute(
        select(ConsentVersion.version, ConsentVersion.label, ConsentVersion.texts)
        .where(ConsentVersion.study_id == study_id)
        .order_by(ConsentVersion.version.desc())
        .limit(1)
    ).first()
    if row is None:
        consent = protocol.questionnaires.consent
        return Shown(1, consent.version, language, consent.text, digest(consent.text))
    number, label, texts = row
    text = texts[language]
    return Shown(number, label, language, text, digest(text))


# ------------------------------------------------------------------------------ new versions


def texts_from_toml(source: str, *, name: str = "the consent file") -> tuple[str, dict[str, str]]:
    """``(label, texts by language)`` from a consent file: ``text`` in the study's first
    language, ``[translations.<code>] text`` for each further one, and optionally ``version``
    (the label). The languages themselves are checked by :func:`add_version`; the label is
    '' when the file gives none."""
    try:
        data = tomllib.loads(source)
    except tomllib.TOMLDecodeError as exc:
        raise InvalidInput(f"{name}: not valid TOML: {exc}") from exc
    unknown = sorted(set(data) - {"version", "text", "translations"})
    if unknown:
        raise InvalidInput(
            f"{name}: unknown key {unknown[0]!r}; a consent file has version, text and "
            "[translations.<language>] text"
        )
    label = data.get("version", "")
    if not isinstance(label, str):
        raise InvalidInput(f'{name}: version must be a text, e.g. version = "2.0"')
    texts: dict[str, Any] = {"": data.get("text")}
    translations = data.get("translations", {})
    if not isinstance(translations, dict):
        raise InvalidInput(f"{name}: translations must be tables: [translations.sv] text = …")
    for code, table in translations.items():
        if not isinstance(table, dict) or set(table) - {"text"}:
            raise InvalidInput(f'{name}: translations.{code} must hold only text = "…"')
        texts[code] = table.get("text")
    return label, texts


def _normalised(protocol: Protocol, given: dict[str, Any]) -> dict[str, str]:
    """The texts by language, stripped; InvalidInput naming the first thing wrong. ``given``
    may name the study's first language '' (a file's own ``text``)."""
    first, further = protocol.default_language, protocol.study.languages[1:]
    given = dict(given)
    if "" in given:
        if first in given:
            raise InvalidInput(
                f"translations.{first}: {first!r} is the study's first language: its text is "
                "the file's own text, not a translation"
            )
        given[first] = given.pop("")
    for code in given:
        if code not in protocol.study.languages:
            raise InvalidInput(
                f"translations.{code}: {code!r} is not one of the study's languages "
                f"({', '.join(protocol.study.languages)})"
            )
    texts: dict[str, str] = {}
    for code in protocol.study.languages:
        where = "text" if code == first else f"translations.{code}.text"
        value = given.get(code)
        if value is None:
            raise InvalidInput(
                f"{where}: missing"
                + (f" in {code!r}: every language of the study needs the text" if further else "")
            )
        if not isinstance(value, str):
            raise InvalidInput(f"{where}: must be a text")
        text = value.strip()
        if not text:
            raise InvalidInput(f"{where}: empty in {code!r}: give the text")
        if len(text) > TEXT_MAX:
            raise InvalidInput(f"{where}: at most {TEXT_MAX} characters in {code!r}")
        texts[code] = text
    if protocol.speech.record_audio and not mentions_audio_recording(texts[first]):
        raise InvalidInput(
            "text: this study records answers' audio ([speech] record_audio), so the consent "
            "text must tell participants that their voice is recorded"
        )
    return texts


def add_version(
    db: Session,
    *,
    study_name: str,
    texts: dict[str, Any],
    actor: Actor,
    label: str = "",
    reason: str = "",
) -> Version:
    """Add the next version of a study's consent text (audited); commits.

    ``texts``: language → text, every language of the study (the first may be given as '').
    Refused with one line, nothing written: an unknown study, a missing, empty or unknown
    language, a text that is the current version's in every language ("unchanged"), a label
    another version has, or a recording study's text that no longer says it records voices."""
    study = studies.get_study(db, study_name, for_update=True)
    protocol = studies.protocol_of(study)
    cleaned = _normalised(protocol, texts)
    label, reason = " ".join(label.split()), reason.strip()
    if len(label) > LABEL_MAX:
        raise InvalidInput(f"version: at most {LABEL_MAX} characters")
    if len(reason) > REASON_MAX:
        raise InvalidInput(f"reason: at most {REASON_MAX} characters")
    stored = _stored(db, study)
    known = stored or [_protocol_version(study, protocol)]
    current = known[-1]
    if cleaned == current.texts:
        raise InvalidInput(
            f"unchanged: the text is version {current.number}'s ({current.label}) in every "
            "language; nothing added"
        )
    number = current.number + 1
    label = label or str(number)
    taken = next((v for v in known if v.label == label), None)
    if taken is not None:
        raise InvalidInput(
            f"version: {label!r} is version {taken.number}'s label already; give another"
        )
    if not stored:  # version 1 was the protocol's text only: keep it beside its successor
        _store(db, study, known[0])
    added = Version(
        number=number,
        label=label,
        texts=cleaned,
        sha256={code: digest(text) for code, text in cleaned.items()},
        created_at=utcnow(),
        created_by=actor.name,
        reason=reason,
    )
    _store(db, study, added)
    try:
        db.flush()
    except IntegrityError:
        db.rollback()
        raise Conflict(
            f"another version of {study_name!r}'s consent text was added at the same time; "
            "look at the versions and try again"
        ) from None
    # Tablets waiting for their participant move on to the new text (when the protocol asks
    # for it) and staff pages show who needs to consent again.
    # Robots and consoles learn that their participant's next session now waits.
    active = db.execute(
        select(Participant.id, Station.id)
        .outerjoin(Station, Station.participant_id == Participant.id)
        .where(Participant.study_id == study.id, Participant.status != ParticipantStatus.WITHDRAWN)
    ).all()
    events.publish(
        db,
        topics=[
            study_topic(study.id),
            *(participant_topic(pid) for pid, _ in active),
            *(station_topic_of(sid) for _, sid in active if sid is not None),
        ],
        type="consent_changed",
        version=number,
        site=STUDY_WIDE,  # a new text for everyone, not a participant's activity
    )
    audit.record(
        db,
        actor=actor,
        action="consent.version_added",
        study_id=study.id,
        subject=study.name,
        details={
            "version": number,
            "label": label,
            "sha256": added.sha256,
            "reason": reason,
            "previous": current.number,
        },
    )
    db.commit()
    return added


def _store(db: Session, study: Study, version: Version) -> None:
    db.add(
        ConsentVersion(
            study_id=study.id,
            version=version.number,
            label=version.label,
            texts=version.texts,
            sha256=version.sha256,
            created_at=version.created_at,
            created_by=version.created_by,
            reason=version.reason,
        )
    )


# ------------------------------------------------------------------------- participants


@dataclass(frozen=True)
class Standing:
    """Where a participant stands with the study's consent text."""

    current: int
    """The study's current version."""
    accepted: int | None
    """The latest version they accepted (None: they have not consented yet)."""
    declined: int | None = None
    """The latest version they declined, if later than the one they accepted."""
    required: bool = False
    """Whether the protocol has them consent again before their next session."""

    @property
    def outdated(self) -> bool:
        """They accepted an older version than the current one."""
        return self.accepted is not None and self.accepted < self.current

    @property
    def note(self) -> str:
        """What staff pages say ('' when nothing is due)."""
        if not self.outdated:
            return ""
        if self.declined == self.current:
            return f"declined consent version {self.current}"
        return f"re-consent needed (accepted version {self.accepted} of {self.current})"


def current_number(db: Session, study_id: int) -> int:
    """The study's current version (1 until a later one is added)."""
    return (
        db.scalar(
            select(func.max(ConsentVersion.version)).where(ConsentVersion.study_id == study_id)
        )
        or 1
    )


def _answered(participant_ids: Any) -> Any:
    return (
        select(
            ConsentRecord.participant_id,
            func.max(case((ConsentRecord.accepted, ConsentRecord.version))),
            func.max(case((ConsentRecord.accepted.is_(False), ConsentRecord.version))),
        )
        .where(ConsentRecord.participant_id.in_(participant_ids))
        .group_by(ConsentRecord.participant_id)
    )


def standings(db: Session, study: Study) -> dict[int, Standing]:
    """Every participant's :class:`Standing` (by participant id) who has answered (two
    queries for the whole study)."""
    current = current_number(db, study.id)
    required = studies.protocol_of(study).questionnaires.consent.reconsent_before_next_session
    in_study = select(Participant.id).where(Participant.study_id == study.id)
    return {
        pid: _standing(current, accepted, declined, required)
        for pid, accepted, declined in db.execute(_answered(in_study))
    }


def standing(db: Session, participant: Participant, study: Study) -> Standing:
    """One participant's :class:`Standing`."""
    current = current_number(db, study.id)
    required = studies.protocol_of(study).questionnaires.consent.reconsent_before_next_session
    row = db.execute(_answered([participant.id])).first()
    if row is None:
        return Standing(current, None, None, required)
    return _standing(current, row[1], row[2], required)


def _standing(current: int, accepted: int | None, declined: int | None, required: bool) -> Standing:
    later = declined if declined is not None and (accepted is None or declined > accepted) else None
    return Standing(current, accepted, later, required)


def records(db: Session, participant: Participant) -> list[ConsentRecord]:
    """Every answer the participant gave to a consent text, oldest first."""
    return list(
        db.scalars(
            select(ConsentRecord)
            .where(ConsentRecord.participant_id == participant.id)
            .order_by(ConsentRecord.answered_at, ConsentRecord.id)
        )
    )


def reconsent_blocker(code: str, current: int, accepted: int | None) -> str:
    """Why a session cannot start for a participant who must consent again ('' when not)."""
    if accepted is None or accepted >= current:
        return ""
    return (
        f"waiting for {code} to accept version {current} of the consent text on the tablet "
        f"(they accepted version {accepted})"
    )
