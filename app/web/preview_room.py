"""The room previewed by staff (issue 50, item 3): the browser's room client (static/js/room.js)
with its API pointed here instead of at a station: the floor plan, the speech settings, the
robot's lines spoken, and a socket answering ``state``, ``prompt`` and ``answer`` from an
in-memory preview (app.services.design.preview_room). Signed-in staff only; nothing is stored:
no participant, no step, no answer, no audit entry.

The socket speaks the station socket's subset the room client uses (app.api.station_ws): the
client's ``auth`` first (its key is ignored: the login cookie decides), then ``hello`` with the
state, requests answered with ``result`` or ``error``, and ``pong`` to the client's pings. Its
results are checked against the station's own output models, so the client cannot tell them
apart.
"""

from __future__ import annotations

import asyncio
import json
from datetime import timedelta
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, WebSocket
from fastapi.responses import Response
from pydantic import BaseModel
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect

from app.api.runtime_schemas import (
    AnswerOut,
    PromptOut,
    RoomCategory,
    RoomOut,
    SpeechOut,
    StationStateOut,
)
from app.deps import SESSION_COOKIE, CurrentUser, SessionDep
from app.errors import NotFound, TrustlabError
from app.protocol import Protocol
from app.services import blinding, studies
from app.services.audit import Actor
from app.services.design.preview_room import PreviewRoom
from app.services.staff import users
from app.speech.lines import spoken_lines
from app.speech.synthesis import Synthesiser
from app.web.preview import in_offered_language
from app.web.templating import render

router = APIRouter(tags=["pages"], include_in_schema=False)

BASE = "/studies/{name}/preview/room/{language}"
CLOSE_UNAUTHENTICATED = 4401
"""As the station socket closes for an unknown key (the room client then stops trying)."""


def _protocol(db: Session, name: str, language: str) -> Protocol:
    """The study's protocol in ``language`` (404 for one the study does not offer)."""
    study = studies.get_study(db, name)
    return in_offered_language(study, studies.protocol_of(study), language)


def station_of(name: str, language: str) -> str:
    """The station name the preview's room client uses for its own storage and greeting."""
    return f"preview-{name}-{language}"


@router.get(BASE)
def room_preview(
    request: Request, db: SessionDep, user: CurrentUser, name: str, language: str
) -> Response:
    """The room as a participant of the study walks it, in ``language`` (``?condition=C2``:
    that condition's learner; the first one's otherwise)."""
    protocol = _protocol(db, name, language)
    study = studies.get_study(db, name)
    # Only roles that see conditions choose one (a blinded study's experimenters walk the first).
    shown = blinding.shows_conditions(study, Actor.of_user(user))
    chosen = request.query_params.get("condition", "") if shown else ""
    conditions = [c.id for c in protocol.conditions]
    condition = chosen if chosen in conditions else conditions[0]
    base = BASE.format(name=name, language=language)
    return render(
        request,
        "room.html",
        {
            "station": station_of(name, language),
            "room_preview": {
                "api": f"{base}/api",
                "socket_query": f"?condition={condition}",
                "study": study,
                "language": protocol.default_language,
                "condition": condition,
                "conditions": conditions if shown else [],
                # Every level's lines side by side would tell a blinded experimenter what each
                # reply on the console means of a learner: listed for those who see conditions.
                "levels": protocol.replies.levels if shown else [],
                "speech_api": f"{base}/api/speech/audio",
                "index": f"/studies/{name}/preview",
            },
        },
    )


@router.get(BASE + "/api/room")
def preview_room_plan(db: SessionDep, user: CurrentUser, name: str, language: str) -> RoomOut:
    """The floor plan, as a station's ``GET /api/v1/station/room`` gives it."""
    protocol = _protocol(db, name, language)
    return RoomOut(
        study=name,
        categories=[RoomCategory(name=c.name, title=c.title) for c in protocol.categories],
        rules=list(protocol.study.rules),
        layout=protocol.room_layout(),
    )


@router.get(BASE + "/api/speech")
def preview_speech(db: SessionDep, user: CurrentUser, name: str, language: str) -> SpeechOut:
    """The study's speech settings; answers by button or key (the preview records no voice)."""
    protocol = _protocol(db, name, language)
    return SpeechOut(
        study=name,
        language=protocol.default_language,
        offline_recognition=False,
        **protocol.speech.model_dump() | {"cloud_recognizer": False},
    )


@router.get(BASE + "/api/speech/audio")
def preview_spoken_line(
    request: Request,
    user: CurrentUser,
    db: SessionDep,
    name: str,
    language: str,
    text: Annotated[str, Query(min_length=1, max_length=2000)],
) -> Response:
    """One of the study's lines in this language, spoken by the server (its questions, replies,
    request to answer again and rules only)."""
    protocol = _protocol(db, name, language)
    if text not in spoken_lines(protocol):
        raise NotFound(f"not a line of study {name!r} in {protocol.default_language!r}")
    synthesiser: Synthesiser = request.app.state.synthesiser
    wav = synthesiser.wav(text, protocol.default_language)  # a synchronous route: in a thread
    return Response(wav, media_type="audio/wav")


def _signed_in(websocket: WebSocket) -> bool:
    """Whether the socket's browser is signed in (the login cookie, as every staff page)."""
    token = websocket.cookies.get(SESSION_COOKIE)
    if not token:
        return False
    database = websocket.app.state.database
    minutes = websocket.app.state.settings.idle_minutes
    with database.read_session() as db:
        login = users.resolve_login(db, token=token, idle_timeout=timedelta(minutes=minutes))
    return login is not None


def _preview(websocket: WebSocket, name: str, language: str) -> PreviewRoom:
    database = websocket.app.state.database
    with database.read_session() as db:
        protocol = _protocol(db, name, language)
    condition = websocket.query_params.get("condition") or protocol.conditions[0].id
    return PreviewRoom(
        study=name,
        station=station_of(name, language),
        protocol=protocol,
        condition=condition,
        checkpoint_dir=websocket.app.state.settings.checkpoint_dir,
    )


def _result(room: PreviewRoom, message: dict[str, Any]) -> tuple[BaseModel | None, str]:
    """Carry out one request of the room client: its checked result (None for a report)."""
    kind = message.get("type")
    if kind == "state":
        return StationStateOut.model_validate(room.state()), "state"
    if kind == "prompt":
        return PromptOut.model_validate(room.prompt(str(message.get("category", "")))), "prompt"
    if kind == "answer":
        said = message.get("answer")
        if said not in ("yes", "no"):
            raise TrustlabError('answer: "yes" or "no"')
        step = message.get("step_id")
        if not isinstance(step, int):
            raise TrustlabError("step_id: a step's number")
        return AnswerOut.model_validate(room.answer(step, said_yes=said == "yes")), "answer"
    if kind in ("presence", "notice"):
        return None, str(kind)  # where the previewer walks is nobody's business
    raise TrustlabError(f"unknown request {kind!r}")


@router.websocket(BASE + "/api/ws")
async def preview_socket(websocket: WebSocket, name: str, language: str) -> None:
    """The preview's station socket (module docstring)."""
    await websocket.accept()
    try:
        first = json.loads(await asyncio.wait_for(websocket.receive_text(), timeout=10))
        if not isinstance(first, dict) or first.get("type") != "auth":
            raise ValueError("auth first")
        if not await run_in_threadpool(_signed_in, websocket):
            await websocket.close(CLOSE_UNAUTHENTICATED, "sign in to preview the room")
            return
        room = await run_in_threadpool(_preview, websocket, name, language)
    except (ValueError, TimeoutError, WebSocketDisconnect):
        await websocket.close(1008, "send the auth message first")
        return
    except TrustlabError as exc:
        await websocket.close(1008, exc.message[:120])
        return
    state = StationStateOut.model_validate(room.state()).model_dump(mode="json")
    await websocket.send_json(
        {"type": "hello", "station": room.station, "heartbeat_seconds": 15, "state": state}
    )
    try:
        while True:
            try:
                message = json.loads(await websocket.receive_text())
            except ValueError:
                continue
            if not isinstance(message, dict):
                continue
            if message.get("type") == "ping":
                await websocket.send_json({"type": "pong", "id": message.get("id")})
                continue
            if message.get("type") == "pong":
                continue
            try:
                out, op = await run_in_threadpool(_result, room, message)
            except TrustlabError as exc:
                await websocket.send_json(
                    {
                        "type": "error",
                        "id": message.get("id"),
                        "status": exc.status_code,
                        "detail": exc.message,
                    }
                )
                continue
            await websocket.send_json(
                {
                    "type": "result",
                    "id": message.get("id"),
                    "op": op,
                    "data": None if out is None else out.model_dump(mode="json"),
                }
            )
    except WebSocketDisconnect:
        return
