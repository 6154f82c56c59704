"""A typed asyncio client for trustlab's API, for robot integrators, the bots and the console robot.

- :class:`RobotClient` speaks for one station with a device key over REST;
- :class:`StationSocket` does the same over the station WebSocket, answers heartbeats, receives
  pushes, and reconnects by itself (requests are idempotent, so a retried prompt or answer never
  creates a second step), except after close code 4401: a refused key raises
  :class:`DeviceKeyRefused` instead;
- :class:`ExperimenterClient` signs in like a person and drives enrolment and sessions.

Responses are parsed into the same pydantic models the server validates against
(app/api/runtime_schemas.py), so a field the server renames breaks loudly here too.

Example::

    async with RobotClient("http://127.0.0.1:8000", key) as robot:
        step = await robot.prompt("conation")
        reply = await robot.answer(step.step_id, "yes")
        print(reply.reply)
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import random
import uuid
from collections.abc import AsyncIterator, Iterator
from types import TracebackType
from typing import Any, Literal, Self, TypeVar

import httpx
from pydantic import BaseModel
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from app.api.runtime_schemas import (
    AnswerOut,
    DeviceOut,
    IssuedDeviceOut,
    PromptOut,
    SpeechOut,
    StaffStationStateOut,
    StationStateOut,
)

Model = TypeVar("Model", bound=BaseModel)
Answer = Literal["yes", "no"]

RETRYABLE_STATUS = {502, 503, 504}
IDLE_CONNECTION_SECONDS = 30.0
"""A client closes a connection idle this long, well before the server would
(app.settings.KEEP_ALIVE_SECONDS): a request is never sent on a connection the server is closing
at that moment, which fails without an answer."""


def http_client(base_url: str, **options: Any) -> httpx.AsyncClient:
    """An httpx client for trustlab's server (``options`` as httpx takes them)."""
    limits = httpx.Limits(keepalive_expiry=IDLE_CONNECTION_SECONDS)
    return httpx.AsyncClient(base_url=base_url.rstrip("/"), limits=limits, **options)


CLOSE_KEY_REFUSED = 4401
"""The station WebSocket's close code for an unknown or revoked device key: never retried."""
CLOSE_TRY_AGAIN_LATER = 1013
"""The standard close code for "try again later" (overload, restart): retried with back-off."""


class ApiError(Exception):
    """The server refused a request: ``status`` and its one-sentence ``detail``."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"{status}: {detail}")
        self.status = status
        self.detail = detail


class DeviceKeyRefused(ApiError):
    """The server closed the station WebSocket with code 4401: the key is unknown or revoked.

    Retrying cannot help, so :class:`StationSocket` stops reconnecting; ``detail`` is the server's
    reason (``unknown or revoked device key`` or ``device key revoked``).
    """

    def __init__(self, reason: str) -> None:
        reason = reason or "unknown or revoked device key"
        super().__init__(401, f"the server closed the station WebSocket with code 4401: {reason}")
        self.reason = reason


class _TryAgainLater(ConnectionError):
    """The server answered the WebSocket handshake with 503 or closed it with 1013."""


def backoff_delays(
    base: float, cap: float, rng: random.Random, *, attempts: int | None = None
) -> Iterator[float]:
    """Waits between retries: ``base`` doubling up to ``cap``, each drawn from its upper half
    (jitter, so that robots cut off together do not come back in lockstep); endless unless
    ``attempts`` is given."""
    for attempt in itertools.count() if attempts is None else range(attempts):
        ceiling = min(cap, base * 2**attempt)
        yield rng.uniform(ceiling / 2, ceiling)


def _detail(response: httpx.Response) -> str:
    try:
        body = response.json()
    except ValueError:
        return response.text[:200] or response.reason_phrase
    return str(body.get("detail", body)) if isinstance(body, dict) else str(body)


class _Http:
    """An httpx client that retries what is safe to retry and raises :class:`ApiError`."""

    def __init__(
        self, base_url: str, *, headers: dict[str, str], timeout: float, retries: int
    ) -> None:
        self._client = http_client(base_url, headers=headers, timeout=timeout)
        self._retries = retries

    async def request(
        self,
        method: str,
        path: str,
        *,
        json_body: Any = None,
        headers: dict[str, str] | None = None,
    ) -> httpx.Response:
        """Send; retry connection failures and 502/503/504 (callers only send idempotent work)."""
        for attempt in itertools.count():
            try:
                response = await self._client.request(method, path, json=json_body, headers=headers)
            except (httpx.TransportError, httpx.TimeoutException):
                if attempt >= self._retries:
                    raise
            else:
                if response.status_code not in RETRYABLE_STATUS or attempt >= self._retries:
                    if response.status_code >= 400:
                        raise ApiError(response.status_code, _detail(response))
                    return response
            await asyncio.sleep(min(0.2 * 2**attempt, 2.0))
        raise AssertionError("unreachable")  # pragma: no cover

    async def parse(
        self, model: type[Model], method: str, path: str, *, json_body: Any = None
    ) -> Model:
        response = await self.request(method, path, json_body=json_body)
        return model.model_validate(response.json())

    async def aclose(self) -> None:
        await self._client.aclose()


class RobotClient:
    """A robot client for one station, authenticated by its device key (REST)."""

    def __init__(self, base_url: str, key: str, *, timeout: float = 10.0, retries: int = 3) -> None:
        self._http = _Http(
            base_url, headers={"Authorization": f"Bearer {key}"}, timeout=timeout, retries=retries
        )

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Close the connection pool."""
        await self._http.aclose()

    async def state(self) -> StationStateOut:
        """The station's participant, session, run, open prompts and what to do next."""
        return await self._http.parse(StationStateOut, "GET", "/api/v1/station")

    async def speech(self) -> SpeechOut:
        """The ``[speech]`` settings of the study the station runs (409 when it runs none)."""
        return await self._http.parse(SpeechOut, "GET", "/api/v1/station/speech")

    async def prompt(self, category: str) -> PromptOut:
        """The question to ask for ``category`` (the open one again if already prompted)."""
        return await self._http.parse(
            PromptOut, "POST", "/api/v1/station/prompts", json_body={"category": category}
        )

    async def answer(
        self, step_id: int, answer: Answer, *, idempotency_key: str | None = None
    ) -> AnswerOut:
        """Record a yes/no answer; retried with the same key, so it is applied exactly once."""
        key = idempotency_key or uuid.uuid4().hex
        return await self._http.parse(
            AnswerOut,
            "POST",
            f"/api/v1/station/steps/{step_id}/answer",
            json_body={"answer": answer, "idempotency_key": key},
        )

    async def notice(self, text: str | None, *, attention: bool = False) -> None:
        """Show a line on the station's operator console (None clears it)."""
        await self._http.request(
            "PUT", "/api/v1/station/notice", json_body={"text": text, "attention": attention}
        )

    async def start_run(self) -> StationStateOut:
        """Start the next run (prompting after a finished run does this implicitly)."""
        return await self._http.parse(StationStateOut, "POST", "/api/v1/station/runs")


class StationSocket:
    """The station WebSocket: requests by id, pushes on :attr:`events`, automatic reconnection.

    Reconnection waits with jittered, bounded back-off (``retry_delay`` doubling up to
    ``max_retry_delay``). :meth:`open` retries a server that answers 503 or closes with 1013 (try
    again later) up to ``connect_attempts`` connections; after a drop the socket reconnects until
    :meth:`close`. Close code 4401 (unknown or revoked key) is never retried: :meth:`open`,
    :meth:`request` and :meth:`next_event` raise :class:`DeviceKeyRefused` naming the reason.
    """

    def __init__(
        self,
        base_url: str,
        key: str,
        *,
        request_timeout: float = 15.0,
        reconnect: bool = True,
        retry_delay: float = 0.2,
        max_retry_delay: float = 5.0,
        connect_attempts: int = 8,
    ) -> None:
        scheme = "wss" if base_url.startswith("https") else "ws"
        self.url = f"{scheme}://{base_url.split('://', 1)[1].rstrip('/')}/api/v1/station/ws"
        self._key = key
        self._timeout = request_timeout
        self._reconnect = reconnect
        self._retry_delay = retry_delay
        self._max_retry_delay = max_retry_delay
        self._connect_attempts = max(1, connect_attempts)
        self._rng = random.Random()
        self._connection: ClientConnection | None = None
        self._pending: dict[str, asyncio.Future[dict[str, Any]]] = {}
        self._ids = itertools.count(1)
        self._reader: asyncio.Task[None] | None = None
        self._connected = asyncio.Event()
        self._refused: DeviceKeyRefused | None = None
        self._refused_event = asyncio.Event()
        self._closing = False
        self.events: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self.state: dict[str, Any] | None = None
        """The newest state received: from ``hello``, each event as it arrives, and each
        :meth:`current_state` reply. A queued event's own ``state`` is as old as the event."""

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def open(self) -> None:
        """Connect and wait for the server's hello (which carries the current state).

        Raises :class:`DeviceKeyRefused` at once for a refused key; retries 503/1013 with back-off,
        then raises :class:`ConnectionError`.
        """
        delays = backoff_delays(
            self._retry_delay,
            self._max_retry_delay,
            self._rng,
            attempts=self._connect_attempts - 1,
        )
        while True:
            try:
                await self._connect()
                break
            except _TryAgainLater:
                delay = next(delays, None)
                if delay is None:
                    raise
                await asyncio.sleep(delay)
        self._reader = asyncio.create_task(self._read_forever())

    async def _connect(self) -> None:
        try:
            connection = await connect(
                self.url,
                additional_headers={"Authorization": f"Bearer {self._key}"},
                open_timeout=self._timeout,
            )
        except InvalidStatus as exc:
            if exc.response.status_code == 503:
                raise _TryAgainLater(f"the server answered 503: {exc}") from exc
            raise
        try:
            hello = json.loads(await asyncio.wait_for(connection.recv(), self._timeout))
        except ConnectionClosed as exc:
            self._raise_for_close(connection)
            raise ConnectionError(f"closed before the greeting: {exc}") from exc
        except TimeoutError:
            await connection.close()
            raise
        if hello.get("type") != "hello":
            await connection.close()
            raise ApiError(401, f"unexpected greeting {hello!r}")
        self.state = hello.get("state")
        self._connection = connection
        self._connected.set()

    @staticmethod
    def _raise_for_close(connection: ClientConnection) -> None:
        """Raise what a refusing close code means (4401, 1013); return for any other."""
        code, reason = connection.close_code, connection.close_reason or ""
        if code == CLOSE_KEY_REFUSED:
            raise DeviceKeyRefused(reason)
        if code == CLOSE_TRY_AGAIN_LATER:
            raise _TryAgainLater(f"the server closed with code 1013: {reason or 'try again later'}")

    def _refuse(self, refused: DeviceKeyRefused) -> None:
        """The key is refused: stop reconnecting and fail whoever waits, with the reason."""
        self._refused = refused
        self._refused_event.set()
        for future in self._pending.values():
            if not future.done():
                future.set_exception(refused)
        self._pending.clear()

    async def _read_forever(self) -> None:
        while not self._closing:
            connection = self._connection
            assert connection is not None
            try:
                async for raw in connection:
                    await self._dispatch(json.loads(raw))
            except ConnectionClosed:
                pass
            self._connected.clear()
            if connection.close_code == CLOSE_KEY_REFUSED:
                self._refuse(DeviceKeyRefused(connection.close_reason or ""))
                return
            for future in self._pending.values():
                if not future.done():
                    future.set_exception(ConnectionError("connection lost"))
            self._pending.clear()
            if self._closing or not self._reconnect:
                return
            try:
                await self._reconnect_with_backoff()
            except DeviceKeyRefused as refused:
                self._refuse(refused)
                return

    async def _reconnect_with_backoff(self) -> None:
        """Reconnect until it works or :meth:`close`; a refused key raises."""
        for delay in backoff_delays(self._retry_delay, self._max_retry_delay, self._rng):
            if self._closing:
                return
            await asyncio.sleep(delay)
            if self._closing:
                return
            try:
                await self._connect()
            except DeviceKeyRefused:
                raise
            except (OSError, ConnectionClosed, TimeoutError, ApiError, InvalidStatus):
                continue
            await self.events.put({"type": "reconnected", "state": self.state})
            return

    async def _wait_connected(self) -> None:
        """Wait until connected; raise :class:`DeviceKeyRefused` if the key was refused."""
        if self._refused is None and not self._connected.is_set():
            waiters = [
                asyncio.ensure_future(self._connected.wait()),
                asyncio.ensure_future(self._refused_event.wait()),
            ]
            try:
                await asyncio.wait(
                    waiters, timeout=self._timeout * 2, return_when=asyncio.FIRST_COMPLETED
                )
            finally:
                for waiter in waiters:
                    waiter.cancel()
        if self._refused is not None:
            raise self._refused
        if not self._connected.is_set():
            raise TimeoutError("not connected to the station WebSocket")

    async def _dispatch(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        if kind == "ping":
            with contextlib.suppress(ConnectionClosed):
                assert self._connection is not None
                await self._connection.send(json.dumps({"type": "pong"}))
            return
        if kind in ("result", "error", "pong"):
            future = self._pending.pop(str(message.get("id")), None)
            if future is not None and not future.done():
                future.set_result(message)
            return
        if kind == "event":
            self.state = message.get("state", self.state)
        await self.events.put(message)

    async def request(self, op: str, **fields: Any) -> dict[str, Any]:
        """Send one request and return its ``data``; resend after a reconnection (idempotent)."""
        for attempt in range(3):
            await self._wait_connected()
            request_id = f"r{next(self._ids)}"
            future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
            self._pending[request_id] = future
            try:
                assert self._connection is not None
                await self._connection.send(json.dumps({"id": request_id, "type": op, **fields}))
                reply = await asyncio.wait_for(future, self._timeout)
            except (ConnectionError, ConnectionClosed, TimeoutError):
                self._pending.pop(request_id, None)
                if attempt == 2 or not self._reconnect:
                    raise
                continue
            if reply["type"] == "error":
                raise ApiError(int(reply.get("status", 500)), str(reply.get("detail")))
            data: dict[str, Any] = reply.get("data", {})
            return data
        raise AssertionError("unreachable")  # pragma: no cover

    async def prompt(self, category: str) -> PromptOut:
        """The question to ask for ``category``."""
        return PromptOut.model_validate(await self.request("prompt", category=category))

    async def answer(
        self,
        step_id: int,
        answer: Answer,
        *,
        idempotency_key: str | None = None,
        heard: tuple[str | None, float | None] | None = None,
    ) -> AnswerOut:
        """Record a yes/no answer exactly once (the key survives reconnections). ``heard``, the
        recogniser's words and confidence (either may be None), marks the answer as spoken."""
        spoken: dict[str, Any] = {}
        if heard is not None:
            words, confidence = heard
            spoken = {"modality": "speech", "transcript": words}
            spoken["transcript_confidence"] = confidence
        data = await self.request(
            "answer",
            step_id=step_id,
            answer=answer,
            idempotency_key=idempotency_key or uuid.uuid4().hex,
            **spoken,
        )
        return AnswerOut.model_validate(data)

    async def current_state(self) -> StationStateOut:
        """Ask for the station's state (kept in :attr:`state` too: the newest one received)."""
        data = await self.request("state")
        self.state = data
        return StationStateOut.model_validate(data)

    async def next_event(self, timeout: float | None = None) -> dict[str, Any]:
        """The next pushed event (or reconnection notice); raises :class:`DeviceKeyRefused` once
        the queue is empty and the key was refused (no more events can come)."""
        if not self.events.empty() or self._refused is None:
            getter = asyncio.ensure_future(self.events.get())
            refused = asyncio.ensure_future(self._refused_event.wait())
            try:
                done, _ = await asyncio.wait(
                    [getter, refused], timeout=timeout, return_when=asyncio.FIRST_COMPLETED
                )
            finally:
                refused.cancel()
                if not getter.done():
                    getter.cancel()
            if getter in done:
                return getter.result()
            if not done:
                raise TimeoutError("no event")
        assert self._refused is not None
        raise self._refused

    async def close(self) -> None:
        """Close the connection and stop reconnecting."""
        self._closing = True
        if self._connection is not None:
            await self._connection.close()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader


class ExperimenterClient:
    """An experimenter (or admin) signed in over the API."""

    def __init__(self, base_url: str, *, timeout: float = 15.0, retries: int = 2) -> None:
        self._http = _Http(base_url, headers={}, timeout=timeout, retries=retries)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self._http.aclose()

    async def sign_in(self, username: str, password: str) -> None:
        """Sign in and keep the CSRF token for later requests."""
        response = await self._http.request(
            "POST", "/api/v1/session", json_body={"username": username, "password": password}
        )
        self._http._client.headers["X-CSRF-Token"] = response.json()["csrf_token"]

    async def call(self, method: str, path: str, body: Any = None) -> Any:
        """Any API call as JSON (path relative to /api/v1)."""
        response = await self._http.request(method, f"/api/v1{path}", json_body=body)
        return response.json() if response.content else None

    async def protocol(self, study: str) -> dict[str, Any]:
        """The study's protocol (conditions hidden from blinded roles)."""
        value: dict[str, Any] = await self.call("GET", f"/studies/{study}/protocol")
        return value

    async def enroll(
        self,
        study: str,
        *,
        code: str | None = None,
        strata: dict[str, str] | None = None,
        language: str | None = None,
    ) -> dict[str, Any]:
        """Enrol and randomise a participant (``language``: one of the study's)."""
        body: dict[str, Any] = {"code": code, "strata": strata or {}}
        if language is not None:
            body["language"] = language
        value: dict[str, Any] = await self.call("POST", f"/studies/{study}/participants", body)
        return value

    async def station_state(self, station: str) -> dict[str, Any]:
        """Where a station stands, as the experimenter's routes return it."""
        state: dict[str, Any] = await self.call("GET", f"/stations/{station}/state")
        return state

    async def ensure_station(self, name: str) -> None:
        """Create the station unless it exists (admin)."""
        try:
            await self.call("POST", "/stations", {"name": name})
        except ApiError as exc:
            if exc.status != 409:
                raise

    async def issue_key(self, station: str, label: str = "robot") -> IssuedDeviceOut:
        """A new device key for a station (admin)."""
        return IssuedDeviceOut.model_validate(
            await self.call("POST", f"/stations/{station}/devices", {"label": label})
        )

    async def revoke_key(self, device_id: int) -> DeviceOut:
        """Revoke a device key (admin); its robot is refused from then on."""
        return DeviceOut.model_validate(await self.call("POST", f"/devices/{device_id}/revoke"))

    async def assign(self, station: str, study: str, code: str) -> None:
        """Seat a participant at a station."""
        await self.call("PUT", f"/stations/{station}/participant", {"study": study, "code": code})

    async def unassign(self, station: str) -> None:
        """Free a station."""
        await self.call("DELETE", f"/stations/{station}/participant")

    async def start_session(self, station: str) -> StaffStationStateOut:
        """Start the assigned participant's next session."""
        return StaffStationStateOut.model_validate(
            await self.call("POST", f"/stations/{station}/sessions")
        )

    async def end_session(self, station: str) -> StaffStationStateOut:
        """End the running session early."""
        return StaffStationStateOut.model_validate(
            await self.call("POST", f"/stations/{station}/sessions/current/end")
        )


async def iterate_events(socket: StationSocket) -> AsyncIterator[dict[str, Any]]:
    """Pushed events as an async iterator (until the socket closes)."""
    while True:
        yield await socket.events.get()
