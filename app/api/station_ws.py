"""The station WebSocket: the robot API over one connection, plus server pushes.

Protocol (JSON text frames; docs/robot-integration.md has a transcript):

- Authenticate with the header ``Authorization: Bearer tlk_…``, or, for clients that cannot set
  headers, with ``{"type": "auth", "key": "tlk_…"}`` as the first message (within
  ``websocket_auth_seconds``, 10 s by default).
- The server greets with ``{"type": "hello", "station": …, "heartbeat_seconds": …, "state": …}``.
- Requests carry an ``id`` echoed in the reply: ``state``, ``prompt`` (``category``), ``answer``
  (``step_id``, ``answer``, ``idempotency_key``), ``start_run``, ``presence`` (a room client's
  position, zone and last line; the reply's data is null), ``ping``. Replies are
  ``{"type": "result", "id": …, "op": …, "data": …}`` or
  ``{"type": "error", "id": …, "status": 4xx, "detail": …}`` with the same bodies and statuses as
  the REST routes.
- Pushes: ``{"type": "event", "event": "session_started", "data": …, "state": …}`` whenever the
  station changes (participant assigned, session/run started or ended, prompt, answer).
- Heartbeats: the server sends ``{"type": "ping"}`` every ``heartbeat_seconds`` and closes the
  connection (code 4408) after three intervals without hearing from the client.
- A revoked key's connection is closed with code 4401: at once when the revocation's event
  arrives (any worker), on its next request, and at the latest at its next heartbeat (which
  re-checks the key: covers a revocation from another process on SQLite, which sends no event).

A client that reconnects gets the current state (open prompts included) in ``hello``; prompts and
answers are idempotent, so resuming never duplicates a step.

A frame the server cannot use (binary, not JSON, nested too deeply, a number too long, a field of
the wrong type) is answered with an error message (400 or 422, with the request's ``id`` whenever
it can be read) and the connection stays open; only a socket that never authenticated is closed
(4401, with the reason). Fields are checked exactly as the REST routes check them (app/inputs.py):
``"step_id": true`` or ``8.0`` is a 422 here as ``/steps/true/answer`` is there.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta
from typing import Annotated, Any, Literal

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError
from sqlalchemy.exc import DataError, OperationalError
from starlette.concurrency import run_in_threadpool

from app.api import station_ops
from app.api.device_work import as_device, device_actor
from app.api.runtime_schemas import AnswerRequest, PresenceRequest, PromptRequest
from app.db import Database
from app.errors import NotAuthenticated, TrustlabError
from app.events import Event
from app.http import refused_value_message
from app.inputs import MAX_DIGITS, Count, RowId
from app.services.sessions import stations

log = logging.getLogger(__name__)

router = APIRouter(tags=["robot"])

MISSED_HEARTBEATS = 3
CLOSE_UNAUTHENTICATED = 4401
CLOSE_HEARTBEAT_TIMEOUT = 4408


RequestId = Annotated[str, Field(max_length=200)] | Count | None
"""A request's ``id``: the client's string or whole number (``true`` is neither), echoed back."""


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid")
    id: RequestId = None


class StateMessage(_Message):
    """Ask for the station's state."""

    type: Literal["state"]


class PromptMessage(_Message, PromptRequest):
    """Ask for a category's question (the fields of the REST route's body)."""

    type: Literal["prompt"]


class AnswerMessage(_Message, AnswerRequest):
    """Record an answer (the REST route's body, plus the step id its path carries)."""

    type: Literal["answer"]
    step_id: RowId


class StartRunMessage(_Message):
    """Start the next run."""

    type: Literal["start_run"]


class PresenceMessage(_Message, PresenceRequest):
    """Where the participant is in the room (the REST route's body); the reply's data is null."""

    type: Literal["presence"]


class PingMessage(_Message):
    """Liveness check (any message counts as a heartbeat)."""

    type: Literal["ping", "pong"]


ClientMessage = Annotated[
    StateMessage | PromptMessage | AnswerMessage | StartRunMessage | PresenceMessage | PingMessage,
    Field(discriminator="type"),
]
_parse = TypeAdapter(ClientMessage)


@dataclass(frozen=True)
class AuthenticatedDevice:
    """A device whose key was accepted: its key, id and station."""

    key: str
    id: int
    station: str
    station_id: int


class BadFrame(Exception):
    """A frame the server cannot read; ``detail`` says why in one line."""

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


def _json_int(digits: str) -> int | str:
    """JSON integers as Python ints, except one too long to be any id: kept as its text, which the
    field's own check then refuses by name (json.loads would raise a bare ValueError past 4,300
    digits, losing the request id)."""
    return int(digits) if len(digits.lstrip("-")) <= MAX_DIGITS else digits


def decode_frame(raw: str | None) -> Any:
    """The JSON value of a text frame, or BadFrame (``None`` stands for a binary frame)."""
    if raw is None:
        raise BadFrame("binary frames are not supported: send JSON as text frames")
    try:
        return json.loads(raw, parse_int=_json_int)
    except json.JSONDecodeError as exc:
        raise BadFrame(f"not JSON: {exc.msg}") from None
    except RecursionError:
        raise BadFrame("not JSON this server reads: nested too deeply") from None
    except ValueError as exc:  # e.g. an exponent too large for a float
        raise BadFrame(f"not JSON this server reads: {exc}") from None


def _request_id(data: Any) -> str | int | None:
    """The ``id`` to echo: a client's string or integer id, None when there is none to echo."""
    value = data.get("id") if isinstance(data, dict) else None
    return value if isinstance(value, str | int) and not isinstance(value, bool) else None


async def receive_frame(websocket: WebSocket) -> str | None:
    """The next frame's text, ``None`` for a binary frame; WebSocketDisconnect when it closes.

    ``receive_text`` fails with a KeyError on a binary frame, which used to drop the socket."""
    message = await websocket.receive()
    if message["type"] == "websocket.disconnect":
        raise WebSocketDisconnect(message.get("code", 1000), message.get("reason"))
    text = message.get("text")
    return text if isinstance(text, str) else None


def _authenticate(database: Database, key: str) -> AuthenticatedDevice:
    with database.read_session() as db:
        device = stations.authenticate_seat(db, key=key)
        return AuthenticatedDevice(
            key=key,
            id=device.device_id,
            station=device.seat.station_name,
            station_id=device.seat.station_id,
        )


def describe_invalid(exc: ValidationError) -> str:
    parts = []
    for error in exc.errors()[:5]:
        location = ".".join(str(p) for p in error.get("loc", ()))
        parts.append(f"{location}: {error['msg']}" if location else error["msg"])
    return "; ".join(parts)


class _Connection:
    def __init__(
        self,
        websocket: WebSocket,
        database: Database,
        device: AuthenticatedDevice,
        heartbeat: float,
    ) -> None:
        self.websocket = websocket
        self.database = database
        self.device = device
        self.heartbeat = heartbeat
        self._send_lock = asyncio.Lock()
        self._heard = asyncio.get_running_loop().time()
        self.socket_id = uuid.uuid4().hex
        """This socket's row in ``device_socket`` (the console counts a device's open sockets)."""

    async def send(self, message: dict[str, Any]) -> None:
        async with self._send_lock:
            await self.websocket.send_text(json.dumps(message, default=str))

    async def send_error(self, request_id: RequestId, status: int, detail: str) -> None:
        """An error reply to one request; the connection stays open (docs/robot-integration.md)."""
        await self.send({"type": "error", "id": request_id, "status": status, "detail": detail})

    async def state(self) -> dict[str, Any]:
        out = await as_device(
            self.websocket.app,
            self.device.key,
            write=False,
            op=lambda db, device: station_ops.state(db, station=device.seat),
        )
        return out.model_dump(mode="json")

    async def record_socket(self, change: Callable[..., None]) -> None:
        """Record that this socket opened, is alive or closed (``change``: one of
        :func:`stations.socket_opened`, ``socket_alive``, ``socket_closed``), for the console's
        connected badge. By the device's id, not its key: a socket whose key was revoked meanwhile
        still has its row removed. A database that is away is not the client's problem: the row
        comes back at the next heartbeat, or lapses."""
        options: dict[str, Any] = {"device_id": self.device.id, "socket_id": self.socket_id}
        if change is not stations.socket_closed:
            options["lasts"] = timedelta(seconds=self.heartbeat * (MISSED_HEARTBEATS + 1))

        def work() -> None:
            with self.database.write_session() as db:
                change(db, **options)
                db.commit()

        with contextlib.suppress(OperationalError):
            async with self.database.admission():
                await self.database.run_unit_of_work(work, write=True)

    async def close_revoked(self) -> None:
        """Close the connection of a key that is no longer valid (code 4401)."""
        await self.websocket.close(CLOSE_UNAUTHENTICATED, "device key revoked")

    async def key_still_valid(self) -> bool:
        """Whether the key still authenticates (True when the database cannot say right now)."""
        try:
            await run_in_threadpool(_authenticate, self.database, self.device.key)
        except NotAuthenticated:
            return False
        except OperationalError:
            return True
        return True

    async def handle(self, raw: str | None) -> bool:
        """Answer one client message; False when the connection was closed (key revoked)."""
        request_id: str | int | None = None
        try:
            data = decode_frame(raw)
            request_id = _request_id(data)
            message = _parse.validate_python(data)
        except BadFrame as exc:
            await self.send_error(None, 400, exc.detail)
            return True
        except ValidationError as exc:
            await self.send_error(request_id, 422, describe_invalid(exc))
            return True
        if isinstance(message, PingMessage):
            if message.type == "ping":
                await self.send({"type": "pong", "id": message.id})
            return True
        try:
            result = await self._run(message)
        except NotAuthenticated:
            await self.close_revoked()
            return False
        except TrustlabError as exc:
            await self.send_error(message.id, exc.status_code, exc.message)
            return True
        except DataError as exc:
            await self.send_error(message.id, 422, refused_value_message(exc))
            return True
        except OperationalError:
            await self.send_error(
                message.id, 503, "the database is unavailable right now; please retry"
            )
            return True
        except Exception:  # a defect, not the client's mistake: say so, log it, keep serving
            log.exception("station %s: %s request failed", self.device.station, message.type)
            await self.send_error(
                message.id, 500, "the server failed to handle this request; its log has the details"
            )
            return True
        await self.send({"type": "result", "id": message.id, "op": message.type, "data": result})
        return True

    async def _run(self, message: _Message) -> dict[str, Any] | None:
        if isinstance(message, StateMessage):
            return await self.state()
        if isinstance(message, PresenceMessage):
            presence = PresenceRequest.model_validate(message.model_dump(exclude={"type", "id"}))

            def presence_op(db: Any, device: Any) -> None:
                station_ops.presence(
                    db, station=device.seat, device_id=device.device_id, body=presence
                )

            await as_device(self.websocket.app, self.device.key, write=True, op=presence_op)
            return None
        if isinstance(message, PromptMessage):
            body = PromptRequest(category=message.category, zone=message.zone)

            def prompt_op(db: Any, device: Any) -> Any:
                return station_ops.prompt(
                    db,
                    station=device.seat,
                    body=body,
                    actor=device_actor(device),
                    device_id=device.device_id,
                )

            out = await as_device(self.websocket.app, self.device.key, write=True, op=prompt_op)
        elif isinstance(message, AnswerMessage):
            answer_body = AnswerRequest(
                answer=message.answer,
                idempotency_key=message.idempotency_key,
                modality=message.modality,
                transcript=message.transcript,
                transcript_confidence=message.transcript_confidence,
                transcript_engine=message.transcript_engine,
            )
            step_id = message.step_id

            def answer_op(db: Any, device: Any) -> Any:
                return station_ops.answer(
                    db,
                    station=device.seat,
                    step_id=step_id,
                    body=answer_body,
                    actor=device_actor(device),
                    device_id=device.device_id,
                )

            out = await as_device(self.websocket.app, self.device.key, write=True, op=answer_op)
        else:

            def run_op(db: Any, device: Any) -> Any:
                return station_ops.start_run(db, station=device.seat, actor=device_actor(device))

            out = await as_device(self.websocket.app, self.device.key, write=True, op=run_op)
        result: dict[str, Any] = out.model_dump(mode="json")
        return result

    async def read_loop(self) -> None:
        while True:
            raw = await receive_frame(self.websocket)
            self._heard = asyncio.get_running_loop().time()
            if not await self.handle(raw):
                return

    async def push_loop(self) -> None:
        topic = f"station:{self.device.station_id}"
        async with self.database.hub.subscribe([topic]) as subscription:
            while True:
                event: Event = await subscription.next()
                if event.type == stations.DEVICE_REVOKED:
                    if event.data.get("device_id") == self.device.id:
                        await self.close_revoked()
                        return
                    continue  # another key of the station: nothing the robot needs to know
                if event.type in stations.CONSOLE_ONLY:
                    continue
                try:
                    state = await self.state()
                except NotAuthenticated:
                    await self.close_revoked()
                    return
                # ``site`` only routes the event to staff pages
                # (app.services.privacy.sites.reaches).
                data = {key: value for key, value in event.data.items() if key != "site"}
                await self.send(
                    {"type": "event", "event": event.type, "data": data, "state": state}
                )

    async def heartbeat_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(self.heartbeat)
            if loop.time() - self._heard > self.heartbeat * MISSED_HEARTBEATS:
                await self.websocket.close(CLOSE_HEARTBEAT_TIMEOUT, "no heartbeat from the client")
                return
            if not await self.key_still_valid():
                await self.close_revoked()
                return
            await self.record_socket(stations.socket_alive)
            await self.send({"type": "ping"})

    async def serve(self) -> None:
        await self.send(
            {
                "type": "hello",
                "station": self.device.station,
                "heartbeat_seconds": self.heartbeat,
                "state": await self.state(),
            }
        )
        tasks = [
            asyncio.create_task(self.read_loop()),
            asyncio.create_task(self.push_loop()),
            asyncio.create_task(self.heartbeat_loop()),
        ]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
                    await task


class Unauthenticated(Exception):
    """Why a socket is closed before it authenticated (the close frame's reason)."""


async def _key_from_first_message(websocket: WebSocket, timeout: float) -> str:
    """The key of an ``auth`` first message, or Unauthenticated saying what was wrong."""
    try:
        raw = await asyncio.wait_for(receive_frame(websocket), timeout)
    except TimeoutError:
        raise Unauthenticated("no auth message in time") from None
    try:
        message = decode_frame(raw)
    except BadFrame as exc:
        raise Unauthenticated(exc.detail) from None
    key = message.get("key") if isinstance(message, dict) else None
    if message.get("type") != "auth" if isinstance(message, dict) else True:
        raise Unauthenticated('the first message must be {"type": "auth", "key": …}')
    if not isinstance(key, str) or not key:
        raise Unauthenticated("the auth message has no key")
    return key


async def accept_device(websocket: WebSocket) -> AuthenticatedDevice | None:
    """Accept a device's socket and authenticate it (the header, else an ``auth`` first
    message); None when it was refused (closed with 4401 and the reason) or left first. The
    station WebSocket and the room's audio socket authenticate alike."""
    database: Database = websocket.app.state.database
    scheme, _, key = websocket.headers.get("authorization", "").partition(" ")
    key = key.strip() if scheme.lower() == "bearer" else ""
    await websocket.accept()
    try:
        if not key:
            key = await _key_from_first_message(
                websocket, websocket.app.state.settings.websocket_auth_seconds
            )
        try:
            return await run_in_threadpool(_authenticate, database, key)
        except NotAuthenticated:
            raise Unauthenticated("unknown or revoked device key") from None
    except Unauthenticated as refused:
        await websocket.close(CLOSE_UNAUTHENTICATED, _close_reason(str(refused)))
        return None
    except WebSocketDisconnect:
        return None  # the client left before authenticating


@router.websocket("/station/ws")
async def station_socket(websocket: WebSocket) -> None:
    """One robot client's connection to its station."""
    database: Database = websocket.app.state.database
    heartbeat: float = websocket.app.state.settings.websocket_heartbeat_seconds
    device = await accept_device(websocket)
    if device is None:
        return
    connection = _Connection(websocket, database, device, heartbeat)
    await connection.record_socket(stations.socket_opened)
    try:
        with contextlib.suppress(WebSocketDisconnect):
            await connection.serve()
    finally:  # shielded: a server shutting down cancels the handler, not this record
        await asyncio.shield(connection.record_socket(stations.socket_closed))


def _close_reason(text: str) -> str:
    """A close frame's reason: at most 123 bytes of UTF-8 (RFC 6455, 5.5)."""
    return text.encode()[:123].decode(errors="ignore")
