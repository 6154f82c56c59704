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
from app.errors import InvalidInput
from app.i18n.languages import native_name
from app.inputs import SessionNumber, VersionNumber
from app.services.participants import questionnaires
from app.services.privacy import consent as consent_versions
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
    consent: dict[str, Any] | None = Field(
        default=None,
        description="On the consent page: version (the lab's label), number (1, 2…: send it "
        "back with the answer), text, and again (true: asked again after the text changed; "
        "the participant may decline).",
    )
    scales: list[dict[str, Any]] = Field(default_factory=list)


class ConsentIn(RequestBody):
    """Agreement to the consent text (or, asked again after it changed, a refusal)."""

    accept: bool
    decline: bool = Field(
        default=False,
        description="Refuse a new version after accepting an earlier one (staff are shown it).",
    )
    version: VersionNumber | None = Field(
        default=None,
        description="The number of the version shown; refused with 409 if it is no longer "
        "the current one.",
    )


class LanguageIn(RequestBody):
    """The participant's choice on the language page."""

    language: str = Field(max_length=16, examples=["sv"])


class AnswersIn(RequestBody):
    """One questionnaire page's answers: item key → value (numbers may be sent as numbers)."""

    session: SessionNumber | None = None
    answers: dict[str, str | int | float]


def _consent_out(db: SessionDep, tablet: Tablet) -> dict[str, Any]:
    text = consent_versions.shown(db, study_id=tablet.study.id, protocol=tablet.protocol)
    standing = consent_versions.standing(db, tablet.participant, tablet.study)
    return {
        "version": text.label,
        "number": text.number,
        "text": text.text,
        "again": standing.accepted is not None,
    }


HIDDEN_FROM_PARTICIPANTS = {"items": {"__all__": {"expected"}}}


def _page_out(db: SessionDep, tablet: Tablet, page: questionnaires.Page) -> PageOut:
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
        # An attention check's expected answer is for the analysis, not for the participant's
        # browser to read.
        instrument=page.instrument.model_dump(mode="json", exclude=HIDDEN_FROM_PARTICIPANTS)
        if page.instrument
        else None,
        session=page.session,
        consent=_consent_out(db, tablet) if page.kind == "consent" else None,
        scales=[s.model_dump(mode="json") for s in spec.scales] if page.instrument else [],
    )


@router.get("")
def current_page(db: SessionDep, tablet: BearerTablet) -> PageOut:
    """Where the participant is in the flow."""
    return _page_out(db, tablet, questionnaires.next_page(db, tablet.participant, tablet.protocol))


@router.post("/consent")
def consent(body: ConsentIn, db: SessionDep, tablet: BearerTablet) -> PageOut:
    """Give consent (or decline a new version of the text); returns the next page."""
    if body.decline:
        if body.accept:
            raise InvalidInput("accept or decline, not both")
        page = questionnaires.decline_consent(
            db,
            participant=tablet.participant,
            protocol=tablet.protocol,
            actor=participant_actor(tablet),
            version=body.version,
        )
        return _page_out(db, tablet, page)
    result = questionnaires.accept_consent(
        db,
        participant=tablet.participant,
        protocol=tablet.protocol,
        accepted=body.accept,
        actor=participant_actor(tablet),
        version=body.version,
    )
    return _page_out(db, tablet, result.page)


@router.post("/language")
def language(body: LanguageIn, db: SessionDep, tablet: BearerTablet) -> PageOut:
    """Choose the participant's language (only while the page is ``language``); returns the
    next page, in that language."""
    tablet_pages.choose(db, tablet, body.language)
    chosen = tablet.in_language_of_participant()
    return _page_out(db, chosen, questionnaires.next_page(db, chosen.participant, chosen.protocol))


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
    return _page_out(db, tablet, result.page)
