"""Who is holding the tablet: a participant's personal link or a station's kiosk link.

Pages identify the tablet by a cookie set when a link is opened; the JSON API by a bearer token.
Either way the identity resolves to exactly one participant (a kiosk: whoever is assigned to the
station now), and the tablet can reach only that participant's pages. The token is looked up with
the participant and study in one query, as the request's first read (:func:`app.deps.identify`).
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from app.deps import SessionDep, bearer_key, identify
from app.errors import Conflict, NotAuthenticated
from app.i18n.catalogues import Message
from app.protocol import Protocol
from app.security import sign
from app.services.participants import languages, tablet_tokens
from app.services.studies import protocol_of
from app.tables import Participant, Station, Study

TABLET_COOKIE = "tl_tablet"
ONLINE_COOKIE = "tl_online"
"""An online participant's participation (app.online.pages); beside the tablet's, so that their
questionnaire pages and their errors know there is no experimenter to turn to."""


@dataclass(frozen=True)
class Tablet:
    """A resolved tablet: the participant it shows, and the kiosk station when it is one."""

    participant: Participant
    study: Study
    protocol: Protocol
    station: Station | None
    credential: str

    @property
    def link_topic(self) -> str:
        """The topic on which this tablet's link is replaced or revoked (its streams end)."""
        if self.station is not None:
            return tablet_tokens.kiosk_link_topic(self.station.id)
        return tablet_tokens.participant_link_topic(self.participant.id)

    def in_language_of_participant(self) -> Tablet:
        """This tablet after the participant's language changed (its texts in the new one)."""
        protocol = languages.protocol_for(self.participant.language, protocol_of(self.study))
        return dataclasses.replace(self, protocol=protocol)

    def topics(self) -> list[str]:
        """Live topics whose events should refresh this tablet."""
        topics = [f"participant:{self.participant.id}"]
        if self.station is not None:
            topics.append(f"station:{self.station.id}")
        return topics


def resolve(db: Session, credential: str) -> Tablet:
    """The tablet behind a token (``tlp_…`` personal or ``tls_…`` kiosk)."""
    station = None
    if credential.startswith(tablet_tokens.KIOSK_PREFIX):
        station, seated, seated_study = tablet_tokens.station_for_kiosk_token(db, credential)
        if seated is None or seated_study is None:
            raise Conflict(
                Message(
                    "nobody is at station '%(station)s' yet: "
                    "the experimenter assigns a participant",
                    station=station.name,
                )
            )
        participant, study = seated, seated_study
    else:
        participant, study = tablet_tokens.participant_for_token(db, credential)
    protocol = languages.protocol_for(participant.language, protocol_of(study))
    return Tablet(participant, study, protocol, station, credential)


async def _resolved(db: Session, credential: str) -> Tablet:
    return await run_in_threadpool(identify, db, lambda read: resolve(read, credential))


async def cookie_tablet(request: Request, db: SessionDep) -> Tablet:
    """The tablet identified by its cookie (pages)."""
    credential = request.cookies.get(TABLET_COOKIE, "")
    if not credential:
        raise NotAuthenticated(
            Message("open the tablet link (or scan the QR code) the experimenter gave you")
        )
    return await _resolved(db, credential)


async def bearer_tablet(request: Request, db: SessionDep) -> Tablet:
    """The tablet identified by ``Authorization: Bearer tlp_…|tls_…`` (JSON API)."""
    credential = bearer_key(request)
    if not credential:
        raise NotAuthenticated("send the tablet token as 'Authorization: Bearer tlp_…'")
    return await _resolved(db, credential)


CookieTablet = Annotated[Tablet, Depends(cookie_tablet)]
BearerTablet = Annotated[Tablet, Depends(bearer_tablet)]


def form_token(secret: bytes, credential: str) -> str:
    """The CSRF token of a tablet's forms: bound to its (secret) cookie value."""
    return sign(secret, hashlib.sha256(credential.encode()).hexdigest()[:32])
