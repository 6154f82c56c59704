"""A study's tablet pages as a participant meets them, for staff, without participant data.

The consent page and every questionnaire, in any of the study's languages, rendered by the
tablet's own templates with the study's protocol in that language, and checked by the tablet's
own rules (app.services.participants.questionnaires) when sent: a missing answer or a value out
of range is said beside its item, as the participant would see it. Nothing is stored, no
participant is made and no allocation is drawn; the page says so in a banner. A staff member's
sign-in and CSRF token guard the forms, as on every staff page.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fastapi import Request
from fastapi.responses import RedirectResponse, Response

from app.deps import CurrentUser, FormFields, OneHopRouter, SessionDep
from app.errors import NotFound
from app.i18n.catalogues import catalogue
from app.i18n.languages import native_name
from app.inputs import PageNumber
from app.protocol import Protocol
from app.services import studies
from app.services.participants import languages, questionnaires
from app.services.privacy import consent
from app.tables import Study
from app.web.templating import render

router = OneHopRouter(tags=["pages"], include_in_schema=False)


def _preview_path(study: str, language: str, number: int | None = None) -> str:
    base = f"/studies/{study}/preview"
    return base if number is None else f"{base}/{language}/{number}"


def in_offered_language(study: Study, protocol: Protocol, language: str) -> Protocol:
    """The protocol in ``language``, one the study offers."""
    if language not in protocol.study.languages:
        offered = ", ".join(protocol.study.languages)
        raise NotFound(f"study {study.name!r} is not offered in {language!r} (it is in {offered})")
    return languages.protocol_for(language, protocol)


@router.get("/studies/{name}/preview")
def preview_index(
    request: Request,
    db: SessionDep,
    user: CurrentUser,
    name: str,
    language: str = "",
    finished: bool = False,
) -> Response:
    """Each page a participant meets, in order, in one of the study's languages (``finished``:
    the preview's last page was just sent)."""
    study = studies.get_study(db, name)
    protocol = studies.protocol_of(study)
    language = language or protocol.default_language
    shown = in_offered_language(study, protocol, language)
    return render(
        request,
        "preview.html",
        {
            "study": study,
            "language": language,
            "languages": [(code, native_name(code)) for code in protocol.study.languages],
            "pages": [
                (_preview_path(name, language, number), page)
                for number, page in enumerate(questionnaires.every_page(shown), start=1)
            ],
            "sessions": protocol.schedule.sessions,
            "finished": finished,
        },
    )


@dataclass(frozen=True)
class _Previewed:
    """One page of a study's preview: the study, its protocol in the page's language, how many
    pages there are and which this is."""

    study: Study
    protocol: Protocol
    pages: int
    page: questionnaires.Page


def _previewed(db: SessionDep, name: str, language: str, number: int) -> _Previewed:
    study = studies.get_study(db, name)
    protocol = in_offered_language(study, studies.protocol_of(study), language)
    pages = questionnaires.every_page(protocol)
    if not 1 <= number <= len(pages):
        raise NotFound(f"the preview of {name!r} has pages 1 to {len(pages)}")
    return _Previewed(study, protocol, len(pages), pages[number - 1])


def _page(
    request: Request,
    db: SessionDep,
    name: str,
    language: str,
    number: int,
    *,
    values: dict[str, str] | None = None,
    errors: dict[str, Any] | None = None,
    status_code: int = 200,
) -> Response:
    shown = _previewed(db, name, language, number)
    study, protocol, page = shown.study, shown.protocol, shown.page
    words = catalogue(language)
    said = {key: words.say(text) for key, text in (errors or {}).items()}
    viewer = request.state.viewer
    context: dict[str, Any] = {
        "preview": {
            "study": study,
            "language": native_name(language),
            "index": f"{_preview_path(name, language)}?language={language}",
            "number": number,
            "of": shown.pages,
        },
        "study_title": protocol.study.title,
        "catalogue": words,
        "form_token": viewer.csrf_token,
        "position": questionnaires.position(protocol, page),
        "action": _preview_path(name, language, number),
        "draft_key": "",  # nothing typed here is kept, not even in the browser
    }
    if page.kind == "consent":
        text = consent.shown(db, study_id=study.id, protocol=protocol)
        context |= {
            "paragraphs": [p.strip() for p in text.text.split("\n\n") if p.strip()],
            "version": text.number,
            "again": False,
            "declined": False,
            "rules": protocol.study.rules,
            "error": said.get("accept", ""),
        }
        return render(request, "tablet_consent.html", context, status_code=status_code)
    assert page.instrument is not None
    context |= {
        "instrument": page.instrument,
        "session": page.session,
        "scales": {s.name: s for s in protocol.questionnaires.scales},
        "values": values or {},
        "errors": said,
        "description_suffix": questionnaires.DESCRIPTION_SUFFIX,
    }
    return render(request, "tablet_questionnaire.html", context, status_code=status_code)


@router.get("/studies/{name}/preview/{language}/{number}")
def preview_page(
    request: Request,
    db: SessionDep,
    user: CurrentUser,
    name: str,
    language: str,
    number: PageNumber,
) -> Response:
    """Page ``number`` of the participant's pages, in ``language``."""
    return _page(request, db, name, language, number)


@router.post("/studies/{name}/preview/{language}/{number}")
def check_preview_page(
    request: Request,
    db: SessionDep,
    user: CurrentUser,
    name: str,
    language: str,
    number: PageNumber,
    fields: FormFields,
) -> Response:
    """Check what was entered as the tablet would, store nothing, and go on to the next page
    (or show the problems beside their items)."""
    shown = _previewed(db, name, language, number)
    page = shown.page
    answers = {k: v for k, v in fields.items() if k not in ("csrf_token", "version")}
    try:
        if page.kind == "consent":
            questionnaires.check_consent_given(answers.get("accept") == "yes")
        else:
            assert page.instrument is not None
            questionnaires.validate_answers(page.instrument, shown.protocol, answers)
    except questionnaires.QuestionnaireInvalid as exc:
        return _page(
            request, db, name, language, number, values=answers, errors=exc.errors, status_code=422
        )
    if number < shown.pages:
        return RedirectResponse(_preview_path(name, language, number + 1), status_code=303)
    return RedirectResponse(
        f"{_preview_path(name, language)}?language={language}&finished=true", status_code=303
    )
