"""StationSocket against a scripted WebSocket server: which closes end it, which it retries."""

from __future__ import annotations

import asyncio
import json
import random
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from http import HTTPStatus
from typing import Any

import pytest
from websockets.asyncio.server import Request, Response, ServerConnection, serve
from websockets.datastructures import Headers

from app import client
from app.client import ApiError, DeviceKeyRefused, StationSocket

Script = Callable[[int, ServerConnection], Awaitable[None]]
HELLO = {"type": "hello", "station": "lab-1", "heartbeat_seconds": 15.0, "state": {"n": 0}}


@asynccontextmanager
async def scripted_server(
    script: Script, *, busy: frozenset[int] = frozenset()
) -> AsyncIterator[tuple[str, list[int]]]:
    """A server that runs ``script(attempt, connection)`` per connection; handshakes whose
    number is in ``busy`` are answered with HTTP 503. Yields its URL and the attempts seen."""
    attempts: list[int] = []

    def process_request(connection: ServerConnection, request: Request) -> Response | None:
        attempts.append(len(attempts) + 1)
        if attempts[-1] in busy:
            return Response(
                HTTPStatus.SERVICE_UNAVAILABLE, "Service Unavailable", Headers(), b"busy"
            )
        return None

    async def handler(connection: ServerConnection) -> None:
        await script(attempts[-1], connection)

    async with serve(handler, "127.0.0.1", 0, process_request=process_request) as server:
        port = server.sockets[0].getsockname()[1]
        yield f"http://127.0.0.1:{port}", attempts


async def serve_requests(connection: ServerConnection) -> None:
    await connection.send(json.dumps(HELLO))
    async for raw in connection:
        message = json.loads(raw)
        await connection.send(json.dumps({"type": "result", "id": message["id"], "data": {}}))


def _fast(**overrides: Any) -> dict[str, Any]:
    return {"request_timeout": 2.0, "retry_delay": 0.01, "max_retry_delay": 0.05, **overrides}


def test_an_unknown_key_is_refused_at_once_with_the_reason() -> None:
    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.close(4401, "unknown or revoked device key")

    async def main() -> list[int]:
        async with scripted_server(script) as (url, attempts):
            socket = StationSocket(url, "tlk_wrong", **_fast())
            with pytest.raises(DeviceKeyRefused) as refused:
                await socket.open()
            assert isinstance(refused.value, ApiError) and refused.value.status == 401
            assert "4401" in str(refused.value)
            assert "unknown or revoked device key" in str(refused.value)
            await asyncio.sleep(0.2)
            await socket.close()
            return attempts

    assert asyncio.run(main()) == [1], "a refused key must not be retried"


def test_try_again_later_is_retried_until_the_server_answers() -> None:
    async def script(attempt: int, connection: ServerConnection) -> None:
        if attempt == 1:
            await connection.close(1013, "try again later")
            return
        await serve_requests(connection)

    async def main() -> list[int]:
        async with scripted_server(script, busy=frozenset({2, 3})) as (url, attempts):
            async with StationSocket(url, "tlk_key", **_fast()) as socket:
                assert socket.state == {"n": 0}
                assert await socket.request("state") == {}
            return attempts

    assert asyncio.run(main()) == [1, 2, 3, 4]


def test_try_again_later_gives_up_after_the_bounded_attempts() -> None:
    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.close(1013, "try again later")

    async def main() -> list[int]:
        async with scripted_server(script) as (url, attempts):
            socket = StationSocket(url, "tlk_key", **_fast(connect_attempts=3))
            with pytest.raises(ConnectionError, match="1013"):
                await socket.open()
            return attempts

    assert asyncio.run(main()) == [1, 2, 3]


def test_a_key_revoked_while_connected_stops_reconnection() -> None:
    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.send(json.dumps(HELLO))
        await connection.recv()  # the client's first request
        await connection.close(4401, "device key revoked")

    async def main() -> list[int]:
        async with scripted_server(script) as (url, attempts):
            socket = StationSocket(url, "tlk_key", **_fast())
            await socket.open()
            with pytest.raises(DeviceKeyRefused, match="device key revoked"):
                await socket.request("state")
            await asyncio.sleep(0.3)  # many back-off intervals: a retry would have happened
            with pytest.raises(DeviceKeyRefused, match="device key revoked"):
                await socket.request("state")
            with pytest.raises(DeviceKeyRefused, match="device key revoked"):
                await socket.next_event(timeout=1.0)
            await socket.close()
            return attempts

    assert asyncio.run(main()) == [1]


def test_a_dropped_connection_is_still_resumed() -> None:
    async def script(attempt: int, connection: ServerConnection) -> None:
        if attempt == 1:
            await connection.send(json.dumps(HELLO))
            await connection.close(1011, "server restarting")
            return
        await serve_requests(connection)

    async def main() -> tuple[list[int], dict[str, Any]]:
        async with scripted_server(script) as (url, attempts):
            async with StationSocket(url, "tlk_key", **_fast()) as socket:
                event = await socket.next_event(
                    timeout=30.0
                )  # bounds a wait that ends at the reconnect
                assert await socket.request("state") == {}
            return attempts, event

    attempts, event = asyncio.run(main())
    assert attempts == [1, 2] and event["type"] == "reconnected"


def test_backoff_is_jittered_and_bounded() -> None:
    delays = list(client.backoff_delays(0.2, 5.0, random.Random(3), attempts=12))
    assert len(delays) == 12
    assert all(0.1 <= d <= 5.0 for d in delays)
    assert delays[0] <= 0.2 and max(delays) > 2.0, "grows towards the cap"
    again = list(client.backoff_delays(0.2, 5.0, random.Random(4), attempts=12))
    assert delays != again, "two clients do not retry in lockstep"


def test_socket_state_is_the_newest_state_received() -> None:
    def station(action: str) -> dict[str, Any]:
        expected = {"action": action, "message": action, "categories": [], "step_id": None}
        return {
            "station": "lab-1",
            "participant": None,
            "study": None,
            "session": None,
            "run": None,
            "open_prompts": [],
            "expected": {**expected, "session": None},
        }

    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.send(json.dumps({**HELLO, "state": station("answer")}))
        pushed = {"type": "event", "event": "prompt_opened", "data": {}, "state": station("answer")}
        await connection.send(json.dumps(pushed))
        async for raw in connection:
            message = json.loads(raw)
            reply = {"type": "result", "id": message["id"], "data": station("done")}
            await connection.send(json.dumps(reply))

    async def main() -> None:
        async with (
            scripted_server(script) as (url, _),
            StationSocket(url, "k", **_fast()) as socket,
        ):
            queued = await socket.next_event()
            assert (await socket.current_state()).expected.action == "done"
            assert socket.state is not None and socket.state["expected"]["action"] == "done"
            assert queued["state"]["expected"]["action"] == "answer"  # as old as the event

    asyncio.run(main())
