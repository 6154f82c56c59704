"""The online participant's pages: the public link, the browser check, the room in the same tab,
and the way back to the recruitment platform.

``/join/STUDY?PROLIFIC_PID=…`` shows the browser check (static/js/online_check.js), which posts
what it found; the server decides (app.online.participation.BrowserCheck) and either screens the
participant out politely or enrols them and sets two cookies: the tablet's (their questionnaire
pages are the lab tablet's own) and ``tl_online`` (their participation). ``/online`` then always
sends them where they should be, as the tablet's home does: a questionnaire page, the room when a
session comes next (its device key in the page, a button that starts the session), or the
completion page that returns them to the platform with its code.

Every handler is one admitted unit of work (app.db): a join may commit more than once (an
enrolment that lost a race is tried again), so it does not use the request's one-write session.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any, TypeVar
from urllib.parse import parse_qsl

from fastapi import APIRouter, Form, Request
from fastapi.responses import RedirectResponse, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.db import Database
from app.deps import SettingsDep, set_private_cookie
from app.errors import NotAuthenticated
from app.i18n.catalogues import Catalogue, Message, catalogue
from app.inputs import ScreenPixels
from app.online import participation as online
from app.online.monitor import step_of
from app.online.participation import BrowserCheck, Outcome
from app.security import sign, unsign
from app.services.participants import languages, questionnaires
from app.services.studies import get_study, protocol_of
from app.settings import Settings
from app.tables import OnlineParticipation, OnlineStatus, Participant, Station, Study, utcnow
from app.tablet import ONLINE_COOKIE, TABLET_COOKIE
from app.web.room import ROOM_PERMISSIONS
from app.web.templating import render

router = APIRouter(tags=["online"], include_in_schema=False)

COOKIE_DAYS = 2
QUERY_MAX = 4000
"""The longest query string a join keeps (platforms send a handful of short parameters)."""
T = TypeVar("T")


async def _unit(request: Request, work: Callable[[Session], T]) -> T:
    """``work(db)`` in a write session of its own, as one admitted unit of work."""
    database: Database = request.app.state.database

    def run() -> T:
        with database.write_session() as db:
            return work(db)

    async with database.admission():
        return await database.run_unit_of_work(run, write=True)


def _words(study: Study, participant: Participant | None = None) -> Catalogue:
    """The interface words of the participant's language (before enrolment: the study's)."""
    protocol = protocol_of(study)
    language = participant.language if participant is not None else None
    return catalogue(languages.protocol_for(language, protocol).default_language)


def _message(
    request: Request,
    study: Study,
    outcome: Outcome,
    *,
    participation: OnlineParticipation | None = None,
    participant: Participant | None = None,
    status_code: int = 200,
) -> Response:
    """The page for a join or a visit that does not go on (screened out, full, expired…)."""
    spec = protocol_of(study).online
    assert spec is not None
    context = {
        "catalogue": _words(study, participant),
        "study_title": protocol_of(study).study.title,
        "outcome": outcome.value,
        "reason": participation.reason if participation is not None else "",
        "screen_out_url": spec.screen_out_url,
        "completion": spec.completion_link() if outcome is Outcome.COMPLETED else None,
        "completion_code": spec.completion_code if outcome is Outcome.COMPLETED else None,
        "spec": spec,
    }
    return render(request, "online_message.html", context, status_code=status_code)


@router.get("/join/{study}")
def join_page(request: Request, study: str) -> Response:
    """The public link: the browser check, then on to the study."""
    database: Database = request.app.state.database
    with database.read_session() as db:
        found = get_study(db, study)
        spec = online.online_spec(found)
        protocol = protocol_of(found)
    context = {
        "catalogue": catalogue(protocol.default_language),
        "study_title": protocol.study.title,
        "study": found.name,
        "query": str(request.url.query)[:QUERY_MAX],
        "spec": spec,
        "has_id": bool(dict(parse_qsl(request.url.query)).get(spec.id_parameter)),
        "id_parameter": spec.id_parameter,
    }
    return render(request, "online_join.html", context)


def _flag(value: str) -> bool:
    return value == "1"


@router.post("/join/{study}")
async def join(
    request: Request,
    study: str,
    query: Annotated[str, Form(max_length=QUERY_MAX)] = "",
    webgl: Annotated[str, Form(max_length=1)] = "",
    audio: Annotated[str, Form(max_length=1)] = "",
    width: Annotated[ScreenPixels, Form()] = 0,
    height: Annotated[ScreenPixels, Form()] = 0,
    keyboard: Annotated[str, Form(max_length=1)] = "",
    touch: Annotated[str, Form(max_length=1)] = "",
    browser: Annotated[str, Form(max_length=64)] = "",
    *,
    settings: SettingsDep,
) -> Response:
    """Join with what the browser check found: enrolled or resumed (to ``/online``), or why
    not."""
    check = BrowserCheck(
        webgl=_flag(webgl),
        audio=_flag(audio),
        width=width,
        height=height,
        keyboard=_flag(keyboard),
        touch=_flag(touch),
    )
    parameters = dict(parse_qsl(query, max_num_fields=50))

    def work(db: Session) -> tuple[online.Joined, Study]:
        joined = online.join(
            db,
            study_name=study,
            query=parameters,
            browser_id=browser,
            check=check,
            secret=settings.secret,
            checkpoint_dir=settings.checkpoint_dir,
        )
        found = get_study(db, study)
        protocol_of(found)  # loaded while the session is open
        return joined, found

    joined, found = await _unit(request, work)
    if joined.outcome in (Outcome.ENROLLED, Outcome.RESUMED):
        assert joined.participation is not None and joined.token is not None
        response = RedirectResponse("/online", status_code=303)
        _remember(request, response, joined.participation, joined.token, settings)
        return response
    return _message(request, found, joined.outcome, participation=joined.participation)


def _remember(
    request: Request,
    response: Response,
    participation: OnlineParticipation,
    token: str,
    settings: Settings,
) -> None:
    age = COOKIE_DAYS * 86400
    set_private_cookie(response, request, TABLET_COOKIE, token, max_age=age)
    cookie = sign(settings.secret, f"online:{participation.id}")
    set_private_cookie(response, request, ONLINE_COOKIE, cookie, max_age=age)


def participation_of(request: Request, db: Session, secret: bytes) -> OnlineParticipation:
    """The participation of this browser's ``tl_online`` cookie."""
    value = unsign(secret, request.cookies.get(ONLINE_COOKIE, ""))
    found = None
    if value is not None and value.startswith("online:") and value[7:].isdigit():
        found = db.get(OnlineParticipation, int(value[7:]))
    if found is None:
        raise NotAuthenticated(
            Message("open the study from the link the recruitment platform gave you")
        )
    return found


@router.get("/online")
async def where_now(request: Request, settings: SettingsDep) -> Response:
    """Send the participant where they should be now (the tablet home's online twin).

    Most visits change nothing (the same step, seen within ``SEEN_EVERY``): they are answered
    from a read session, off SQLite's single writer and beside each other. A visit that changes
    something (a new step, a sighting due, an expiry, the end) is looked at again as a write."""
    database: Database = request.app.state.database

    def visit(write: bool) -> Response | None:
        with database.write_session() if write else database.read_session() as db:
            return _visit(request, db, settings, write=write)

    async with database.admission():
        response = await database.run_unit_of_work(visit, False, write=False)
        if response is None:
            response = await database.run_unit_of_work(visit, True, write=True)
    assert response is not None
    return response


def _visit(request: Request, db: Session, settings: Settings, *, write: bool) -> Response | None:
    """Where the participant goes now, with what that changes written (commits); None, without
    ``write``, when the visit has something to write."""
    participation = participation_of(request, db, settings.secret)
    study = db.get(Study, participation.study_id)
    assert study is not None
    participant = (
        db.get(Participant, participation.participant_id)
        if participation.participant_id is not None
        else None
    )
    now = utcnow()
    if online.status_due(participation, participant, at=now) != participation.status:
        if not write:
            return None
        online.refresh(db, participation, at=now)
    if participation.status != OnlineStatus.ACTIVE or participant is None:
        return _message(
            request,
            study,
            Outcome(participation.status),
            participation=participation,
            participant=participant,
        )
    protocol = languages.protocol_for(participant.language, protocol_of(study))
    page = questionnaires.next_page(db, participant, protocol)
    if page.kind in ("done", "withdrawn"):
        if not write:
            return None
        status = OnlineStatus.COMPLETED if page.kind == "done" else OnlineStatus.ENDED
        online.finish(db, participation, status, at=now)
        return _message(request, study, Outcome(status), participant=participant)
    step = step_of(page)
    if online.step_due(participation, step, at=now):
        if not write:
            return None
        online.record_step(db, participation, step, at=now)
    if page.kind != "wait":
        return RedirectResponse(page.path, status_code=303)
    return _room(request, db, participation, participant, study, settings)


def _room(
    request: Request,
    db: Session,
    participation: OnlineParticipation,
    participant: Participant,
    study: Study,
    settings: Settings,
) -> Response:
    station = db.scalar(select(Station.name).where(Station.id == participation.station_id))
    assert station is not None
    context: dict[str, Any] = {
        "station": station,
        "catalogue": _words(study, participant),
        "online": {
            "key": online.station_key(settings.secret, participation),
            "start": "/online/start",
            "leave": "/online",
            "away": "/online/away",
        },
    }
    response = render(request, "room.html", context)
    response.headers["permissions-policy"] = ROOM_PERMISSIONS
    return response


@router.post("/online/start", status_code=204)
async def start_session(request: Request, settings: SettingsDep) -> Response:
    """The participant is ready: start their next session (the room goes on by itself)."""

    def work(db: Session) -> None:
        participation = participation_of(request, db, settings.secret)
        online.refresh(db, participation, at=utcnow())
        online.start_session(db, participation)

    await _unit(request, work)
    return Response(status_code=204)


AwaySeconds = Annotated[float, Form(ge=0.0, le=online.LONGEST_AWAY_SECONDS, allow_inf_nan=False)]


@router.post("/online/away", status_code=204)
async def away(request: Request, settings: SettingsDep, seconds: AwaySeconds) -> Response:
    """The room's tab was hidden for ``seconds`` (a beacon from static/js/room.js)."""

    def work(db: Session) -> None:
        online.record_away(db, participation_of(request, db, settings.secret), seconds)

    await _unit(request, work)
    return Response(status_code=204)
