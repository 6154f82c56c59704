"""The tablet as JSON: for custom tablet apps and the bots. Same flow and rules as the pages.

Authenticate with ``Authorization: Bearer tlp_…`` (a participant's link token) or ``tls_…`` (a
station kiosk token, which speaks for whoever is assigned to the station). A submission answers
with the page that follows it, computed inside the submission's own transaction.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field

from app.api.schemas import RequestBody
from app.deps import OneHopRouter, SessionDep
from app.i18n.languages import native_name
from app.inputs import SessionNumber
from app.services import questionnaires
from app.tablet import BearerTablet, Tablet
from app.web import tablet_pages
from app.web.tablet_pages import participant_actor

router = OneHopRouter(prefix="/tablet", tags=["tablet"])


class PageOut(BaseModel):
    """The page the participant should see, with the instrument to fill in if any."""

    participant: str
    kind: str = Field(
        description="language | consent | questionnaire | wait | done | withdrawn "
        "(language: post the participant's choice to /api/v1/tablet/language)"
    )
    language: str = Field(description="The language every text here is in.")
    languages: list[dict[str, str]] = Field(
        default_factory=list,
        description="On the language page: the study's languages as {code, name}.",
    )
    instrument: dict[str, Any] | None = None
    session: int | None = None
    consent: dict[str, str] | None = None
    scales: list[dict[str, Any]] = Field(default_factory=list)


class ConsentIn(RequestBody):
    """Agreement to the consent text."""

    accept: bool


class LanguageIn(RequestBody):
    """The participant's choice on the language page."""

    language: str = Field(max_length=16, examples=["sv"])


class AnswersIn(RequestBody):
    """One questionnaire page's answers: item key → value (numbers may be sent as numbers)."""

    session: SessionNumber | None = None
    answers: dict[str, str | int | float]


def _page_out(tablet: Tablet, page: questionnaires.Page) -> PageOut:
    spec = tablet.protocol.questionnaires
    return PageOut(
        participant=tablet.participant.code,
        kind=page.kind,
        language=tablet.protocol.default_language,
        languages=[
            {"code": code, "name": native_name(code)} for code in tablet.protocol.study.languages
        ]
        if page.kind == "language"
        else [],
        instrument=page.instrument.model_dump(mode="json") if page.instrument else None,
        session=page.session,
        consent={"version": spec.consent.version, "text": spec.consent.text}
        if page.kind == "consent"
        else None,
        scales=[s.model_dump(mode="json") for s in spec.scales] if page.instrument else [],
    )


@router.get("")
def current_page(db: SessionDep, tablet: BearerTablet) -> PageOut:
    """Where the participant is in the flow."""
    return _page_out(tablet, questionnaires.next_page(db, tablet.participant, tablet.protocol))


@router.post("/consent")
def consent(body: ConsentIn, db: SessionDep, tablet: BearerTablet) -> PageOut:
    """Give consent; returns the next page."""
    result = questionnaires.accept_consent(
        db,
        participant=tablet.participant,
        protocol=tablet.protocol,
        accepted=body.accept,
        actor=participant_actor(tablet),
    )
    return _page_out(tablet, result.page)


@router.post("/language")
def language(body: LanguageIn, db: SessionDep, tablet: BearerTablet) -> PageOut:
    """Choose the participant's language (only while the page is ``language``); returns the
    next page, in that language."""
    tablet_pages.choose(db, tablet, body.language)
    chosen = tablet.in_language_of_participant()
    return _page_out(chosen, questionnaires.next_page(db, chosen.participant, chosen.protocol))


@router.post("/questionnaires/{instrument}", responses={422: {"description": "Per-item errors"}})
def submit(instrument: str, body: AnswersIn, db: SessionDep, tablet: BearerTablet) -> PageOut:
    """Submit (or revise) one questionnaire page; returns the next page. Refused (409) while the
    experimenter has locked the participant's answers, for new pages and revisions alike."""
    result = questionnaires.submit(
        db,
        participant=tablet.participant,
        protocol=tablet.protocol,
        instrument_key=instrument,
        session=body.session,
        answers={k: str(v) for k, v in body.answers.items()},
        actor=participant_actor(tablet),
    )
    return _page_out(tablet, result.page)
