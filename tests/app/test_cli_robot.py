"""``trustlab robot`` (the console robot) against a scripted station WebSocket."""

from __future__ import annotations

import asyncio
import json
from typing import Any

from typer.testing import CliRunner
from websockets.asyncio.server import ServerConnection

from app.cli import cli
from tests.app.test_client_socket import Script, scripted_server

runner = CliRunner()


def _state(action: str, *, session: int | None = None, categories: list[str] | None = None) -> Any:
    return {
        "station": "lab-1",
        "participant": "P01" if session is not None else None,
        "study": "s" if session is not None else None,
        "session": None if session is None else {"number": session, "status": "running"},
        "run": None if session is None else {"number": 1, "status": "running"},
        "open_prompts": [],
        "expected": {
            "action": action,
            "message": f"do {action}",
            "categories": categories or [],
            "step_id": None,
            "session": session,
        },
    }


def _hello(state: Any) -> str:
    return json.dumps(
        {"type": "hello", "station": "lab-1", "heartbeat_seconds": 15.0, "state": state}
    )


def _robot(script: Script, stdin: str = "") -> tuple[int, str, str, list[int]]:
    async def main() -> tuple[int, str, str, list[int]]:
        async with scripted_server(script) as (url, attempts):
            args = ["robot", "--url", url, "--station", "lab-1", "--key", "tlk_x"]
            result = await asyncio.to_thread(runner.invoke, cli, args, input=stdin)
            return result.exit_code, result.stdout, result.stderr, attempts

    return asyncio.run(main())


def test_a_key_revoked_while_waiting_ends_with_one_error_line() -> None:
    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.send(_hello(_state("wait", session=0)))
        await asyncio.sleep(0.1)
        await connection.close(4401, "device key revoked")

    code, out, err, attempts = _robot(script)
    assert code == 2
    assert err.strip() == (
        "error: the server refused the device key: device key revoked; "
        "ask the experimenter for a new key"
    )
    assert "Traceback" not in out + err
    assert "[lab-1] P01, the familiarisation run (running), run 1 (running)" in out
    assert "session 0" not in out
    assert attempts == [1], "a refused key must not be retried"


def test_a_key_revoked_before_a_prompt_is_not_asked_again() -> None:
    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.send(_hello(_state("prompt", session=2, categories=["conation"])))
        async for _ in connection:
            await connection.close(4401, "device key revoked")

    code, out, err, _ = _robot(script, stdin="1\n1\n1\nq\n")
    assert code == 2
    assert err.strip().startswith("error: the server refused the device key: device key revoked")
    assert "refused:" not in out, "a refused key is not a refused prompt to retry"
    assert "session 2 (running)" in out


def test_an_unknown_key_at_connection_ends_with_one_error_line() -> None:
    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.close(4401, "unknown or revoked device key")

    code, _, err, _ = _robot(script)
    assert code == 2
    assert err.strip() == (
        "error: the server refused the device key: unknown or revoked device key; "
        "ask the experimenter for a new key"
    )
