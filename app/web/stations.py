"""Stations, device keys and the operator console (with Wizard-of-Oz).

The console's buttons go through exactly the operations the robot API uses (app/api/station_ops.py
and app/services/sessions/runtime.py): a Wizard-of-Oz prompt or answer is indistinguishable from a
robot's, apart from who the step log says did it.
"""

from __future__ import annotations

import uuid
from collections import defaultdict
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import Depends, Form, Request
from fastapi.responses import RedirectResponse, Response
from sqlalchemy import select

from app.api import station_ops
from app.api.runtime_schemas import AnswerRequest, PromptRequest
from app.deps import (
    AdminUser,
    ExperimenterUser,
    OneHopRouter,
    SessionDep,
    SettingsDep,
    set_private_cookie,
    station_in_scope,
)
from app.errors import Conflict, InvalidInput, NotFound, TrustlabError
from app.inputs import RowId
from app.security import sign, unsign
from app.services import blinding, studies
from app.services.audit import Actor
from app.services.participants import enrolment, languages, tablet_tokens
from app.services.privacy import sites
from app.services.sessions import learners, room_presence, runtime, stations
from app.tables import (
    Device,
    LearnerState,
    Participant,
    ParticipantStatus,
    RoomPresence,
    Station,
    Study,
    User,
    utcnow,
)
from app.web.qr import TabletLink, tablet_link
from app.web.templating import redirect_with_notice, render

# A site-limited account meets a station seating another site's participant as if it did not
# exist (app.services.privacy.sites), on every route of a named station.
router = OneHopRouter(
    tags=["pages"], include_in_schema=False, dependencies=[Depends(station_in_scope)]
)


def _stations_context(
    request: Request, db: SessionDep, settings: SettingsDep, user: User, *, archived: bool = False
) -> dict[str, Any]:
    actor = Actor.of_user(user)
    found = sites.visible_stations(db, stations.list_stations(db, archived=archived), actor)
    ids = [station.id for station in found]
    seated = {
        station_id: (participant, study)
        for station_id, participant, study in db.execute(
            select(Station.id, Participant, Study)
            .join(Participant, Participant.id == Station.participant_id)
            .join(Study, Study.id == Participant.study_id)
            .where(Station.id.in_(ids))
        )
    }
    devices: dict[int, list[Device]] = defaultdict(list)
    for device in db.scalars(select(Device).where(Device.station_id.in_(ids)).order_by(Device.id)):
        devices[device.station_id].append(device)
    rows = []
    for station in found:
        kiosk = (
            tablet_tokens.kiosk_token(settings.secret, station) if user.role == "admin" else None
        )
        participant, study = seated.get(station.id, (None, None))
        contact = sites.contact(station, participant.site if participant else None, actor)
        rows.append(
            {
                "station": station,
                "participant": participant,
                "study": study,
                "devices": devices[station.id],
                "contact": contact,
                "kiosk": tablet_link(request, f"/k/{kiosk}") if kiosk else None,
            }
        )
    hidden = (
        len(sites.visible_stations(db, stations.list_stations(db, archived=True), actor))
        if not archived
        else 0
    )
    return {
        "rows": rows,
        "site_choices": sites.declared_anywhere(db) if user.role == "admin" else {},
        "archived": archived,
        "archived_count": hidden,
        "form_error": "",
        "form_values": {},
    }


@router.get("/stations")
def station_list(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    user: ExperimenterUser,
    archived: bool = False,
) -> Response:
    """The stations in use (``?archived=true``: the hidden ones), who is seated there, and
    their devices."""
    context = _stations_context(request, db, settings, user, archived=archived)
    return render(request, "stations.html", context)


@router.post("/stations")
def create_station(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    admin: AdminUser,
    name: Annotated[str, Form(max_length=64)],
    site: Annotated[str, Form(max_length=40)] = "",
) -> Response:
    """Create a station, of a site or shared; a refusal is explained next to the form, as the
    server words it."""
    try:
        stations.create_station(db, name=name.strip(), site=site, actor=Actor.of_user(admin))
    except (InvalidInput, Conflict) as exc:
        db.rollback()
        context = _stations_context(request, db, settings, admin)
        context |= {"form_error": exc.message, "form_values": {"name": name, "site": site}}
        return render(request, "stations.html", context, status_code=exc.status_code)
    return redirect_with_notice(request, "/stations", f"Created station {name.strip()}.")


@router.post("/stations/{name}/archive")
def archive_station(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    name: str,
    archived: Annotated[bool, Form()],
) -> Response:
    """Hide a station from the list (the bots' stations after the demo), or show it again."""
    stations.set_archived(db, station_name=name, archived=archived, actor=Actor.of_user(admin))
    notice = f"Archived station {name}." if archived else f"Station {name} is shown again."
    return redirect_with_notice(request, "/stations", notice)


NEW_KEY_COOKIE = "tl_new_key"
"""Carries a key just issued from the POST to the page that shows it (signed, a minute, read
once): the page has a URL of its own, so a reload shows it again or says it was shown, and never
issues a second key."""


@router.post("/stations/{name}/devices")
def issue_key(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    admin: AdminUser,
    name: str,
    label: Annotated[str, Form(max_length=64)] = "robot",
) -> Response:
    """Issue a device key, then show it on its own page, this once."""
    issued = stations.issue_device_key(
        db, station_name=name, label=label, actor=Actor.of_user(admin)
    )
    response = RedirectResponse(f"/stations/{name}/devices/{issued.device.id}", status_code=303)
    value = sign(settings.secret, f"{issued.device.id}:{issued.key}")
    set_private_cookie(response, request, NEW_KEY_COOKIE, value, max_age=60, samesite="strict")
    return response


@router.get("/stations/{name}/devices/{device_id}")
def issued_key(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    admin: AdminUser,
    name: str,
    device_id: RowId,
) -> Response:
    """A device key just issued, shown this once with what to do next; later visits say it was
    shown and how to replace a lost one."""
    device = db.get(Device, device_id)
    if device is None or device.station.name != name:
        raise NotFound(f"no device {device_id} at station {name!r}")
    carried = unsign(settings.secret, request.cookies.get(NEW_KEY_COOKIE, "")) or ""
    shown_id, _, key = carried.partition(":")
    context = {
        "device": device,
        "key": key if shown_id == str(device.id) and device.revoked_at is None else "",
        "room": tablet_link(request, f"/stations/{name}/room"),
    }
    response = render(request, "device_key.html", context)
    response.headers["Cache-Control"] = "no-store"
    response.delete_cookie(NEW_KEY_COOKIE)
    return response


@router.post("/devices/{device_id}/revoke")
def revoke_key(request: Request, db: SessionDep, admin: AdminUser, device_id: RowId) -> Response:
    """Revoke a device key at once."""
    device = stations.revoke_device(db, device_id=device_id, actor=Actor.of_user(admin))
    return redirect_with_notice(
        request,
        "/stations",
        f"Revoked {device.label} ({device.key_prefix}…) at {device.station.name}.",
    )


@router.post("/stations/{name}/kiosk")
def issue_kiosk(
    request: Request, db: SessionDep, settings: SettingsDep, admin: AdminUser, name: str
) -> Response:
    """Issue (or reissue) the station's kiosk link for a shared tablet."""
    station = stations.get_station(db, name, for_update=True)
    tablet_tokens.issue_kiosk_token(
        db, station=station, secret=settings.secret, actor=Actor.of_user(admin)
    )
    return redirect_with_notice(request, "/stations", f"New kiosk link for {name}.")


# ------------------------------------------------------------------------------ the console


def _probabilities(db: SessionDep, participant: Participant) -> list[dict[str, Any]]:
    """The participant's current probabilities per category, for the live bars."""
    study = db.get(Study, participant.study_id)
    assert study is not None
    protocol = studies.protocol_of(study)
    rows = {
        row.category: row
        for row in db.scalars(
            select(LearnerState).where(LearnerState.participant_id == participant.id)
        )
    }
    bars = []
    for category in protocol.categories:
        row = rows.get(category.name)
        values = learners.probabilities_list(learners.restore(row)) if row else []
        bars.append(
            {
                "category": category,
                "bars": [
                    {
                        "question": q,
                        "p": values[i] if values else 0.0,
                        "preferred": i == category.preferred,
                    }
                    for i, q in enumerate(category.questions)
                ],
                "updates": row.version if row else 0,
            }
        )
    return bars


@dataclass(frozen=True)
class SeatingQuestion:
    """A seating the console asks about before doing it (app.services.sessions.stations.
    seating_questions): the reasons, and the form's study and code that "Seat anyway" sends
    again, confirmed."""

    reasons: list[str]
    study: str
    code: str


def _active_codes(db: SessionDep, study: Study, actor: Actor) -> list[str]:
    return list(
        db.scalars(
            select(Participant.code)
            .where(
                Participant.study_id == study.id,
                Participant.status == ParticipantStatus.ACTIVE,
                sites.visible(actor),
            )
            .order_by(Participant.code)
        )
    )


def _console(
    request: Request,
    db: SessionDep,
    user: User,
    name: str,
    *,
    error: str = "",
    question: SeatingQuestion | None = None,
    status_code: int = 200,
) -> Response:
    station = stations.get_station(db, name)
    view = runtime.station_view(db, station_name=name)
    participant = station.participant
    devices = list(
        db.scalars(
            select(Device).where(Device.station_id == station.id, Device.revoked_at.is_(None))
        )
    )
    station_study = db.get(Study, station.study_id) if station.study_id is not None else None
    # The studies a station may run: those in use, and its own even once archived.
    choices = studies.list_studies(db, archived=False)
    if station_study is not None and station_study not in choices:
        choices.append(station_study)
    last = runtime.last_step(db, participant_id=participant.id) if participant else None
    # While the seated participant's study is blinded, the learners stay off the page entirely:
    # bars, levels and probabilities would each show the condition (app.services.blinding).
    learners_shown = view.learners_shown
    response = render(
        request,
        "console.html",
        {
            "station": station,
            "view": view,
            "participant": participant,
            "devices": devices,
            "contact": sites.contact(
                station, participant.site if participant else None, Actor.of_user(user)
            ),
            "station_study": station_study,
            "study_choices": choices,
            "codes": _active_codes(db, station_study, Actor.of_user(user)) if station_study else [],
            "question": question,
            "bars": _probabilities(db, participant) if participant and learners_shown else [],
            "learners_shown": learners_shown,
            "last": last,
            "error": error,
            "answer_key": uuid.uuid4().hex,
            "room_panel": room_panel_context(db, station),
            "tablet": _tablet_of(request, participant) if view.expected.action == "wait" else None,
            "glosses": _glosses(participant, view.open_prompts, last),
        },
        block="console",
        status_code=status_code,
    )
    return response


def _glosses(
    participant: Participant | None,
    open_prompts: list[Any],
    last: tuple[Any, Any] | None,
) -> dict[int, str]:
    """Step id → its question in the protocol's own language, for the questions the console
    shows that were asked in another (staff read the protocol's language, not necessarily the
    participant's)."""
    if participant is None:
        return {}
    protocol = studies.protocol_of(participant.study)
    asked = [*open_prompts, *([last[0]] if last else [])]
    glosses = {
        step.id: languages.gloss(
            protocol, category=step.category, action=step.action, asked=step.question
        )
        for step in asked
    }
    return {step: words for step, words in glosses.items() if words}


def _tablet_of(request: Request, participant: Participant | None) -> TabletLink | None:
    """The seated participant's tablet link while the console waits for the tablet."""
    if participant is None:
        return None
    token = tablet_tokens.participant_token(request.app.state.settings.secret, participant)
    return tablet_link(request, f"/t/{token}") if token else None


def room_panel_context(db: SessionDep, station: Station) -> dict[str, Any]:
    """What the console's room panel shows: the floor plan of the study the station runs (the
    seated participant's, else its own) and where the room client last saw the participant. A
    reply's words stay hidden while that study is sealed: the reply level shows the condition."""
    participant = station.participant
    study_id = participant.study_id if participant is not None else station.study_id
    study = db.get(Study, study_id) if study_id is not None else None
    presence = room_presence.read(db, station_id=station.id)
    # Only what the room reported about whoever sits there now: an earlier participant's place
    # and words are not theirs (and nobody's once the station is free).
    seated_at = station.assigned_at if participant is not None else None
    earlier = presence is not None and (seated_at is None or presence.updated_at < seated_at)
    if earlier:
        presence = None
    said = _said_since(presence, seated_at)
    sealed = study is not None and blinding.is_sealed(study)
    return {
        "station": station,
        "room": studies.protocol_of(study).room_layout() if study is not None else None,
        "presence": presence,
        "said": said,
        "earlier": earlier,
        "reply_hidden": sealed and said is not None and said.kind == "reply",
        "age": (utcnow() - presence.updated_at).total_seconds() if presence is not None else None,
        "alone": False,  # within the whole console (the room-panel route serves it alone)
    }


def _said_since(
    presence: RoomPresence | None, seated_at: datetime | None
) -> room_presence.Said | None:
    """The last line said in the room, if it was said since the seated participant sat down.

    The presence row keeps its last line until a new one is said, so a position reported after
    the next participant is seated would otherwise carry the previous participant's words."""
    if presence is None or presence.utterance is None or presence.utterance_kind is None:
        return None
    if seated_at is None or presence.utterance_at is None or presence.utterance_at < seated_at:
        return None
    return room_presence.Said(presence.utterance_kind, presence.utterance)


@router.get("/stations/{name}/room-panel")
def room_panel(request: Request, db: SessionDep, user: ExperimenterUser, name: str) -> Response:
    """The console's room panel alone (refreshed when the room client reports)."""
    context = room_panel_context(db, stations.get_station(db, name))
    return render(request, "_room_panel.html", {"room_panel": context | {"alone": True}})


@router.get("/stations/{name}")
def console(request: Request, db: SessionDep, user: ExperimenterUser, name: str) -> Response:
    """The operator console of one station."""
    return _console(request, db, user, name)


def _act(
    request: Request, db: SessionDep, user: User, name: str, action: Any, notice: str = ""
) -> Response:
    """Run a console action; show its refusal beside the buttons instead of an error page, or
    the question it asks before acting (an action returning a :class:`SeatingQuestion`)."""
    try:
        outcome = action()
    except TrustlabError as exc:
        db.rollback()
        return _console(request, db, user, name, error=exc.message, status_code=exc.status_code)
    question = outcome if isinstance(outcome, SeatingQuestion) else None
    return _console(request, db, user, name, question=question)


@router.post("/stations/{name}/study")
def choose_study(
    request: Request,
    db: SessionDep,
    user: ExperimenterUser,
    name: str,
    study: Annotated[str, Form(max_length=64)] = "",
) -> Response:
    """Tie the station's console to a study."""

    def action() -> None:
        if not study:
            raise InvalidInput("choose the study this station runs")
        stations.set_station_study(
            db, station_name=name, study=studies.get_study(db, study), actor=Actor.of_user(user)
        )

    return _act(request, db, user, name, action)


def _participant_to_seat(
    db: SessionDep, study: Study, code: str, actor: Actor
) -> tuple[Participant, list[str]]:
    """The participant a typed code names, and why to ask first when it is not this study's.

    A code the station's study does not know but another study in use does is most often a
    typo'd console or a returning participant of the other study: offered, never taken silently.
    """
    try:
        return enrolment.get_participant(db, study, code, actor=actor), []
    except NotFound:
        others = db.scalars(
            select(Participant)
            .join(Study, Study.id == Participant.study_id)
            .where(
                Participant.code == code,
                Study.archived_at.is_(None),
                Study.id != study.id,
                sites.visible(actor),
            )
            .order_by(Study.created_at.desc())
        ).all()
        if len(others) != 1:
            raise
        return others[0], [f"{study.title!r} ({study.name}) has no participant {code!r}."]


@router.post("/stations/{name}/assign")
def assign(
    request: Request,
    db: SessionDep,
    user: ExperimenterUser,
    name: str,
    code: Annotated[str, Form(max_length=32)],
    study: Annotated[str, Form(max_length=64)] = "",
    confirmed: Annotated[bool, Form()] = False,
) -> Response:
    """Seat a participant at the station; ask first when the seating looks like a slip."""
    code = code.strip()

    def action() -> SeatingQuestion | None:
        station = stations.get_station(db, name)
        if not study:
            raise InvalidInput("choose the study this station runs, then type the code")
        chosen = studies.get_study(db, study)
        participant, reasons = _participant_to_seat(db, chosen, code, Actor.of_user(user))
        reasons += stations.seating_questions(db, station=station, participant=participant)
        if reasons and not confirmed:
            return SeatingQuestion(reasons, chosen.name, participant.code)
        stations.assign_participant(  # the first seating ties the station to the study chosen
            db,
            station_name=name,
            participant=participant,
            actor=Actor.of_user(user),
            tie_untied_to=chosen,
        )
        return None

    return _act(request, db, user, name, action)


@router.post("/stations/{name}/unassign")
def unassign(request: Request, db: SessionDep, user: ExperimenterUser, name: str) -> Response:
    """Free the station."""
    return _act(
        request,
        db,
        user,
        name,
        lambda: stations.unassign(db, station_name=name, actor=Actor.of_user(user)),
    )


@router.post("/stations/{name}/session/start")
def start_session(request: Request, db: SessionDep, user: ExperimenterUser, name: str) -> Response:
    """Start the participant's next session."""
    return _act(
        request,
        db,
        user,
        name,
        lambda: runtime.start_session(db, station_name=name, actor=Actor.of_user(user)),
    )


@router.post("/stations/{name}/session/end")
def end_session(request: Request, db: SessionDep, user: ExperimenterUser, name: str) -> Response:
    """End the running session early."""
    return _act(
        request,
        db,
        user,
        name,
        lambda: runtime.end_session(db, station_name=name, actor=Actor.of_user(user)),
    )


@router.post("/stations/{name}/run/start")
def start_run(request: Request, db: SessionDep, user: ExperimenterUser, name: str) -> Response:
    """Start the next run."""
    return _act(
        request,
        db,
        user,
        name,
        lambda: runtime.start_run(db, station_name=name, actor=Actor.of_user(user)),
    )


@router.post("/stations/{name}/run/end")
def end_run(request: Request, db: SessionDep, user: ExperimenterUser, name: str) -> Response:
    """End the running run early."""
    return _act(
        request,
        db,
        user,
        name,
        lambda: runtime.end_run(db, station_name=name, actor=Actor.of_user(user)),
    )


@router.post("/stations/{name}/woz/prompt")
def woz_prompt(
    request: Request,
    db: SessionDep,
    user: ExperimenterUser,
    name: str,
    category: Annotated[str, Form(max_length=40)],
) -> Response:
    """Wizard-of-Oz: trigger a category as the robot would."""
    return _act(
        request,
        db,
        user,
        name,
        lambda: station_ops.prompt(
            db,
            station=name,
            body=PromptRequest(category=category),
            actor=Actor.of_user(user),
            device_id=None,
        ),
    )


@router.post("/stations/{name}/woz/answer")
def woz_answer(
    request: Request,
    db: SessionDep,
    user: ExperimenterUser,
    name: str,
    step_id: Annotated[RowId, Form()],
    answer: Annotated[Literal["yes", "no"], Form()],
    idempotency_key: Annotated[str, Form(max_length=100)],
) -> Response:
    """Wizard-of-Oz: record the participant's yes/no answer as the robot would."""

    def action() -> None:
        body = AnswerRequest(answer=answer, idempotency_key=idempotency_key)
        station_ops.answer(
            db, station=name, step_id=step_id, body=body, actor=Actor.of_user(user), device_id=None
        )

    return _act(request, db, user, name, action)
