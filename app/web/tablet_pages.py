"""The participant's tablet pages: one instrument per page, the server always decides which.

Every GET of a tablet page that is not the participant's current page redirects to it, and every
page is sent with ``Cache-Control: no-store``, so the back button, a reload, a second tab or a
restarted tablet all land on the right page. Answers typed but not submitted are kept in the
browser (static/js/tablet.js) until the page is submitted.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Form, Request
from fastapi.responses import RedirectResponse, Response
from starlette.concurrency import run_in_threadpool

from app.deps import FormFields, OneHopRouter, SessionDep, SettingsDep, set_private_cookie
from app.errors import Conflict, InvalidInput, NotAuthenticated, PermissionDenied, TrustlabError
from app.i18n.catalogues import Catalogue, Message, catalogue
from app.i18n.languages import native_name
from app.inputs import SessionNumber, VersionNumber
from app.online.participation import is_online
from app.protocol import InstrumentSpec
from app.security import same
from app.services.audit import Actor
from app.services.participants import languages, questionnaires
from app.services.privacy import consent
from app.services.privacy.sites import Scope
from app.tables import ActorKind
from app.tablet import TABLET_COOKIE, CookieTablet, Tablet, form_token, resolve
from app.web.streams import event_stream
from app.web.templating import render, tablet_catalogue

router = OneHopRouter(tags=["tablet"], include_in_schema=False)


def participant_actor(tablet: Tablet) -> Actor:
    """How the participant appears in the audit log."""
    via = f"kiosk {tablet.station.name}" if tablet.station else "tablet link"
    return Actor(ActorKind.PARTICIPANT, f"{tablet.participant.code} ({via})"[:64])


def _no_store(response: Response) -> Response:
    response.headers["Cache-Control"] = "no-store"
    return response


def _open_link(request: Request, token: str, db: SessionDep) -> Response:
    try:
        resolve(db, token)
    except (NotAuthenticated, Conflict) as exc:
        raise NotAuthenticated(exc.message) from exc
    response = RedirectResponse("/tablet", status_code=303)
    set_private_cookie(response, request, TABLET_COOKIE, token, max_age=7 * 86400)
    return response


@router.get("/t/{token}")
def personal_link(request: Request, token: str, db: SessionDep) -> Response:
    """A participant's personal link (from the QR code): remember it on this tablet."""
    return _open_link(request, token, db)


@router.get("/k/{token}")
def kiosk_link(request: Request, token: str, db: SessionDep) -> Response:
    """A station's kiosk link: this tablet shows whoever is assigned to the station."""
    return _open_link(request, token, db)


def _catalogue(tablet: Tablet) -> Catalogue:
    """The interface words in the participant's language."""
    return catalogue(tablet.protocol.default_language)


def _context(request: Request, tablet: Tablet, settings: SettingsDep) -> dict[str, Any]:
    return {
        "tablet": tablet,
        "form_token": form_token(settings.secret, tablet.credential),
        "study_title": tablet.protocol.study.title,
        "catalogue": _catalogue(tablet),
        # Every page of a participant listens for their changes (static/js/tablet.js): a
        # withdrawal moves even the consent page on. The withdrawn page does not: nothing
        # after it is for them, and it must not reload into a link their erasure ended.
        "tablet_events": True,
    }


@router.get("/tablet")
def tablet_home(db: SessionDep, tablet: CookieTablet) -> Response:
    """Send the tablet to the page its participant should be on."""
    page = questionnaires.next_page(db, tablet.participant, tablet.protocol)
    return _no_store(RedirectResponse(page.path, status_code=303))


def _current_or_redirect(
    db: SessionDep,
    tablet: Tablet,
    kind: str,
    instrument: str | None = None,
    session: int | None = None,
) -> questionnaires.Page | Response:
    page = questionnaires.next_page(db, tablet.participant, tablet.protocol)
    wanted = page.kind == kind and (
        instrument is None
        or (
            page.instrument is not None
            and page.instrument.key == instrument
            and page.session == session
        )
    )
    return page if wanted else _no_store(RedirectResponse(page.path, status_code=303))


def _check_form_token(tablet: Tablet, settings: SettingsDep, submitted: str) -> None:
    if not same(submitted, form_token(settings.secret, tablet.credential)):
        raise PermissionDenied(
            Message("this form expired; the page will reload with your answers kept")
        )


def _consent(
    request: Request,
    db: SessionDep,
    tablet: Tablet,
    settings: SettingsDep,
    *,
    error: str = "",
    status_code: int = 200,
) -> Response:
    text = consent.shown(db, study_id=tablet.study.id, protocol=tablet.protocol)
    standing = consent.standing(db, tablet.participant, tablet.study)
    again = standing.accepted is not None  # a new version, after an earlier acceptance
    return _no_store(
        render(
            request,
            "tablet_consent.html",
            {
                **_context(request, tablet, settings),
                "paragraphs": [p.strip() for p in text.text.split("\n\n") if p.strip()],
                "version": text.number,
                "again": again,
                "declined": standing.declined == text.number,
                "rules": tablet.protocol.study.rules,
                "error": _catalogue(tablet).say(error) if error else "",
                # Asked again between sessions, the consent is a sitting of one page.
                "position": (1, 1)
                if again
                else questionnaires.position(tablet.protocol, questionnaires.Page("consent")),
            },
            status_code=status_code,
        )
    )


@router.get("/tablet/consent")
def consent_page(
    request: Request, db: SessionDep, tablet: CookieTablet, settings: SettingsDep
) -> Response:
    """The consent text and the box to tick."""
    current = _current_or_redirect(db, tablet, "consent")
    if isinstance(current, Response):
        return current
    return _consent(request, db, tablet, settings)


@router.post("/tablet/consent")
def give_consent(
    request: Request,
    db: SessionDep,
    tablet: CookieTablet,
    settings: SettingsDep,
    csrf_token: Annotated[str, Form(max_length=200)] = "",
    accept: Annotated[str, Form(max_length=10)] = "",
    decline: Annotated[str, Form(max_length=10)] = "",
    version: Annotated[VersionNumber | None, Form()] = None,
) -> Response:
    """Record consent (with the text's version), or a refusal of a new version."""
    _check_form_token(tablet, settings, csrf_token)
    actor = participant_actor(tablet)
    try:
        if decline == "yes":
            questionnaires.decline_consent(
                db,
                participant=tablet.participant,
                protocol=tablet.protocol,
                actor=actor,
                version=version,
            )
        else:
            questionnaires.accept_consent(
                db,
                participant=tablet.participant,
                protocol=tablet.protocol,
                accepted=accept == "yes",
                actor=actor,
                version=version,
            )
    except questionnaires.QuestionnaireInvalid as exc:
        db.rollback()
        return _consent(request, db, tablet, settings, error=exc.errors["accept"], status_code=422)
    except questionnaires.ConsentChanged:  # show the new words; nothing was recorded
        db.rollback()
        return _consent(request, db, tablet, settings, status_code=409)
    return RedirectResponse("/tablet", status_code=303)


def _questionnaire(
    request: Request,
    tablet: Tablet,
    settings: SettingsDep,
    instrument: InstrumentSpec,
    session: int | None,
    values: dict[str, str],
    errors: dict[str, str],
    status_code: int = 200,
) -> Response:
    scales = {s.name: s for s in tablet.protocol.questionnaires.scales}
    page = questionnaires.Page("questionnaire", instrument, session)
    return _no_store(
        render(
            request,
            "tablet_questionnaire.html",
            {
                **_context(request, tablet, settings),
                "instrument": instrument,
                "session": session,
                "scales": scales,
                "values": values,
                "errors": {key: _catalogue(tablet).say(text) for key, text in errors.items()},
                "description_suffix": questionnaires.DESCRIPTION_SUFFIX,
                "action": page.path,
                "position": questionnaires.position(tablet.protocol, page),
                "draft_key": hashlib.sha256(
                    f"{tablet.credential}:{instrument.key}:{session}".encode()
                ).hexdigest()[:24],
            },
            status_code=status_code,
        )
    )


def _show(
    request: Request,
    db: SessionDep,
    tablet: Tablet,
    settings: SettingsDep,
    instrument: str,
    session: int | None,
) -> Response:
    current = _current_or_redirect(db, tablet, "questionnaire", instrument, session)
    if isinstance(current, Response):
        return current
    assert current.instrument is not None
    stored = questionnaires.stored_answers(db, tablet.participant, instrument, session)
    return _questionnaire(request, tablet, settings, current.instrument, session, stored, {})


def _submit(
    request: Request,
    db: SessionDep,
    tablet: Tablet,
    settings: SettingsDep,
    instrument: str,
    session: int | None,
    fields: dict[str, str],
) -> Response:
    _check_form_token(tablet, settings, fields.pop("csrf_token", ""))
    timing = questionnaires.PageTiming.from_form(fields)
    answers = {k: v for k, v in fields.items() if k not in questionnaires.TIMING_FIELDS}
    try:
        questionnaires.submit(
            db,
            participant=tablet.participant,
            protocol=tablet.protocol,
            instrument_key=instrument,
            session=session,
            answers=answers,
            actor=participant_actor(tablet),
            timing=timing,
        )
    except questionnaires.QuestionnaireInvalid as exc:
        db.rollback()
        spec = next(i for i in tablet.protocol.questionnaires.instruments if i.key == instrument)
        return _questionnaire(
            request, tablet, settings, spec, session, answers, exc.errors, status_code=422
        )
    return RedirectResponse("/tablet", status_code=303)


@router.get("/tablet/q/{instrument}")
def questionnaire_page(
    request: Request, db: SessionDep, tablet: CookieTablet, settings: SettingsDep, instrument: str
) -> Response:
    """A pre- or post-study instrument."""
    return _show(request, db, tablet, settings, instrument, None)


@router.get("/tablet/q/{instrument}/{session}")
def session_questionnaire_page(
    request: Request,
    db: SessionDep,
    tablet: CookieTablet,
    settings: SettingsDep,
    instrument: str,
    session: SessionNumber,
) -> Response:
    """A per-session instrument."""
    return _show(request, db, tablet, settings, instrument, session)


@router.post("/tablet/q/{instrument}")
def submit_questionnaire(
    request: Request,
    db: SessionDep,
    tablet: CookieTablet,
    settings: SettingsDep,
    instrument: str,
    fields: FormFields,
) -> Response:
    """Submit (or revise) a pre- or post-study instrument."""
    return _submit(request, db, tablet, settings, instrument, None, dict(fields))


@router.post("/tablet/q/{instrument}/{session}")
def submit_session_questionnaire(
    request: Request,
    db: SessionDep,
    tablet: CookieTablet,
    settings: SettingsDep,
    instrument: str,
    session: SessionNumber,
    fields: FormFields,
) -> Response:
    """Submit (or revise) a per-session instrument."""
    return _submit(request, db, tablet, settings, instrument, session, dict(fields))


def _simple_page(kind: str, template: str) -> Callable[..., Response]:
    def page(
        request: Request, db: SessionDep, tablet: CookieTablet, settings: SettingsDep
    ) -> Response:
        current = _current_or_redirect(db, tablet, kind)
        if isinstance(current, Response):
            return current
        if is_online(db, tablet.participant.id):  # no experimenter to wait for: the room
            return _no_store(RedirectResponse("/online", status_code=303))
        return _no_store(render(request, template, _context(request, tablet, settings)))

    page.__doc__ = f"The {kind} page."
    return page


@router.get("/tablet/language")
def language_page(
    request: Request, db: SessionDep, tablet: CookieTablet, settings: SettingsDep
) -> Response:
    """The participant chooses the language of the whole study (when the protocol lets them)."""
    current = _current_or_redirect(db, tablet, "language")
    if isinstance(current, Response):
        return current
    # Nobody knows the participant's language yet: the page asks in every language offered,
    # each in its own words, as each button names its language in itself.
    choices = [
        LanguageChoice(code, native_name(code), catalogue(code).gettext(CHOOSE_LANGUAGE))
        for code in tablet.protocol.study.languages
    ]
    return _no_store(
        render(
            request,
            "tablet_language.html",
            {**_context(request, tablet, settings), "choices": choices},
        )
    )


CHOOSE_LANGUAGE = Message("Choose your language")


@dataclass(frozen=True)
class LanguageChoice:
    """A language the participant may choose: its code, its name and the page's question in it."""

    code: str
    name: str
    question: str


@router.post("/tablet/language")
def choose_language(
    db: SessionDep,
    tablet: CookieTablet,
    settings: SettingsDep,
    csrf_token: Annotated[str, Form(max_length=200)] = "",
    language: Annotated[str, Form(max_length=16)] = "",
) -> Response:
    """Record the participant's language, then go on to the consent page in it."""
    _check_form_token(tablet, settings, csrf_token)
    try:
        choose(db, tablet, language)
    except InvalidInput:  # not one of the buttons: show the page again
        db.rollback()
        return RedirectResponse("/tablet/language", status_code=303)
    return RedirectResponse("/tablet", status_code=303)


def choose(db: SessionDep, tablet: Tablet, language: str) -> None:
    """The participant's own choice of language, allowed only while the tablet asks for it
    (the page and the JSON tablet share it)."""
    if not languages.needs_choice(tablet.participant, tablet.protocol):
        raise Conflict(Message("the language has already been chosen"))
    languages.set_language(
        db,
        participant=tablet.participant,
        protocol=tablet.protocol,
        study_name=tablet.study.name,
        language=language,
        actor=participant_actor(tablet),
    )


router.get("/tablet/wait")(_simple_page("wait", "tablet_wait.html"))
router.get("/tablet/done")(_simple_page("done", "tablet_done.html"))


@router.get("/tablet/withdrawn")
def withdrawn_page(
    request: Request, db: SessionDep, tablet: CookieTablet, settings: SettingsDep
) -> Response:
    """The withdrawn page: thanks, and the tablet goes back to the experimenter."""
    current = _current_or_redirect(db, tablet, "withdrawn")
    if isinstance(current, Response):
        return current
    context = {**_context(request, tablet, settings), "tablet_events": False}
    return _no_store(render(request, "tablet_withdrawn.html", context))


@router.get("/tablet/left")
def left_page(request: Request) -> Response:
    """The same thanks for a participant whose data was erased, whose link died with it.

    Their tablet comes here when the erasure's event reaches it (static/js/tablet.js), so the
    server keeps nothing of theirs to show it: the page needs no link, names nobody, and is in
    the language this browser last showed a participant page in (app.web.templating). Keeping
    the link's hash and language on the erased row instead would keep what erasure removes."""
    context = {"catalogue": tablet_catalogue(request), "study_title": ""}
    return _no_store(render(request, "tablet_withdrawn.html", context))


@router.get("/tablet/events")
async def tablet_events(request: Request) -> Response:
    """Server-sent events telling the tablet to look for its next page."""
    database = request.app.state.database
    credential = request.cookies.get(TABLET_COOKIE, "")

    def topics() -> tuple[list[str], str]:
        with database.read_session() as db:
            tablet = resolve(db, credential)
            return tablet.topics(), tablet.link_topic

    try:
        subscribed, link = await run_in_threadpool(topics)
    except TrustlabError as exc:
        return Response(exc.message, status_code=exc.status_code)

    # Ends when the link is reissued or revoked: its EventSource then reconnects and is refused.
    # The participant's own topics: whatever they carry is about this participant.
    return event_stream(database.hub, subscribed, scope=Scope.every_site(), ends_with=link)
