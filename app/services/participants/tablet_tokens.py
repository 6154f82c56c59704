"""Opaque links for the participant's tablet: personal tokens and station kiosk tokens.

A token is derived, not stored: ``HMAC(secret, kind:id:generation)``, URL-safe. The database keeps
only its SHA-256 (for lookup) and the generation, so the experimenter's page can show the QR code
again at any time, while reissuing (generation + 1) or revoking makes every earlier link useless.
Tokens carry no participant id or code: a link reveals nothing and reaches only its own pages.
"""

from __future__ import annotations

import base64
import hashlib
import hmac

from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict, NotAuthenticated
from app.i18n.catalogues import Message
from app.security import token_digest
from app.services import audit
from app.services.audit import Actor
from app.tables import Participant, ParticipantStatus, Station, Study

PARTICIPANT_PREFIX = "tlp_"
KIOSK_PREFIX = "tls_"
LINK_REPLACED = "tablet_link_replaced"


def participant_link_topic(participant_id: int) -> str:
    """Where a participant's link being reissued or revoked is announced: open tablet streams
    of the old link end on it (app/web/tablet_pages.py)."""
    return f"tablet-link:participant:{participant_id}"


def kiosk_link_topic(station_id: int) -> str:
    """Where a station's kiosk link being reissued is announced."""
    return f"tablet-link:station:{station_id}"


def _derive(secret: bytes, prefix: str, kind: str, row_id: int, generation: int) -> str:
    mac = hmac.new(secret, f"{kind}:{row_id}:{generation}".encode(), hashlib.sha256).digest()
    return prefix + base64.urlsafe_b64encode(mac[:24]).decode().rstrip("=")


def participant_token(secret: bytes, participant: Participant) -> str | None:
    """The participant's current tablet token, or None when none is issued (or it was revoked)."""
    if participant.token_hash is None:
        return None
    token = _derive(
        secret, PARTICIPANT_PREFIX, "participant", participant.id, participant.token_generation
    )
    # A changed secret key would silently show a dead link; say nothing rather than lie.
    return token if token_digest(token) == participant.token_hash else None


def issue_participant_token(
    db: Session, *, participant: Participant, secret: bytes, actor: Actor
) -> str:
    """Issue (or reissue) the participant's tablet link; earlier links stop working; commits."""
    token = grant_participant_token(db, participant=participant, secret=secret, actor=actor)
    db.commit()
    return token


def grant_participant_token(
    db: Session, *, participant: Participant, secret: bytes, actor: Actor
) -> str:
    """:func:`issue_participant_token` inside the caller's transaction (an online participant's
    enrolment issues their link with it, app.online.participation)."""
    if participant.status == ParticipantStatus.WITHDRAWN:
        raise Conflict(f"{participant.code} has withdrawn: no tablet link")
    participant.token_generation += 1
    token = _derive(
        secret, PARTICIPANT_PREFIX, "participant", participant.id, participant.token_generation
    )
    participant.token_hash = token_digest(token)
    events.publish(db, topics=[participant_link_topic(participant.id)], type=LINK_REPLACED)
    audit.record(
        db,
        actor=actor,
        action="participant.token_issued",
        study_id=participant.study_id,
        subject=participant.code,
        details={"generation": participant.token_generation},
    )
    return token


def revoke_participant_token(db: Session, *, participant: Participant, actor: Actor) -> None:
    """Make the participant's tablet link useless; commits."""
    participant.token_generation += 1
    participant.token_hash = None
    events.publish(db, topics=[participant_link_topic(participant.id)], type=LINK_REPLACED)
    audit.record(
        db,
        actor=actor,
        action="participant.token_revoked",
        study_id=participant.study_id,
        subject=participant.code,
    )
    db.commit()


def _valid_form(token: str, prefix: str) -> bool:
    return token.startswith(prefix) and len(token) < 100


_BY_TOKEN = (
    select(Participant, Study)
    .join(Study, Study.id == Participant.study_id)
    .where(Participant.token_hash == bindparam("digest"))
)


def participant_for_token(db: Session, token: str) -> tuple[Participant, Study]:
    """The participant a personal token belongs to, with their study (one query);
    NotAuthenticated otherwise."""
    found = (
        db.execute(_BY_TOKEN, {"digest": token_digest(token)}).first()
        if _valid_form(token, PARTICIPANT_PREFIX)
        else None
    )
    if found is None:
        raise NotAuthenticated(Message("this tablet link is not valid (it may have been replaced)"))
    return found[0], found[1]


def kiosk_token(secret: bytes, station: Station) -> str | None:
    """The station's current kiosk token, or None."""
    if station.kiosk_token_hash is None:
        return None
    token = _derive(secret, KIOSK_PREFIX, "kiosk", station.id, station.kiosk_generation)
    return token if token_digest(token) == station.kiosk_token_hash else None


def issue_kiosk_token(db: Session, *, station: Station, secret: bytes, actor: Actor) -> str:
    """Issue (or reissue) a station's kiosk link; commits."""
    station.kiosk_generation += 1
    token = _derive(secret, KIOSK_PREFIX, "kiosk", station.id, station.kiosk_generation)
    station.kiosk_token_hash = token_digest(token)
    events.publish(db, topics=[kiosk_link_topic(station.id)], type=LINK_REPLACED)
    audit.record(
        db,
        actor=actor,
        action="station.kiosk_token_issued",
        subject=station.name,
        details={"generation": station.kiosk_generation},
    )
    db.commit()
    return token


_BY_KIOSK_TOKEN = (
    select(Station, Participant, Study)
    .outerjoin(Participant, Participant.id == Station.participant_id)
    .outerjoin(Study, Study.id == Participant.study_id)
    .where(Station.kiosk_token_hash == bindparam("digest"))
)


def station_for_kiosk_token(
    db: Session, token: str
) -> tuple[Station, Participant | None, Study | None]:
    """The station a kiosk token belongs to, with whoever is seated there and their study (one
    query); NotAuthenticated otherwise."""
    found = (
        db.execute(_BY_KIOSK_TOKEN, {"digest": token_digest(token)}).first()
        if _valid_form(token, KIOSK_PREFIX)
        else None
    )
    if found is None:
        raise NotAuthenticated(Message("this kiosk link is not valid (it may have been replaced)"))
    return found[0], found[1], found[2]
