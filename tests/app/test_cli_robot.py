"""``trustlab robot`` (the console robot) against a scripted station WebSocket."""

from __future__ import annotations

import asyncio
import functools
import json
import socket
from typing import Any

import pytest
from typer.testing import CliRunner
from websockets.asyncio.server import ServerConnection

from app import client
from app.cli import cli
from app.client import StationSocket
from tests.app.test_client_socket import Script, scripted_server

runner = CliRunner()


def _state(action: str, *, session: int | None = None, categories: list[str] | None = None) -> Any:
    return {
        "station": "lab-1",
        "participant": "P01" if session is not None else None,
        "study": "s" if session is not None else None,
        "session": None
        if session is None
        else {"number": session, "status": "running", "runs": 4, "familiarisation": session == 0},
        "run": None
        if session is None
        else {"number": 1, "status": "running", "answered": [], "pending": categories or []},
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


def _prompt(step_id: int = 7) -> Any:
    return {
        "step_id": step_id,
        "category": "conation",
        "action": 0,
        "question": "Do you want to go on?",
        "probabilities": [0.5, 0.5],
        "adapts": True,
        "session": 2,
        "run": 1,
        "created": True,
    }


def _answered(state: Any, step_id: int = 7) -> Any:
    return {
        "step_id": step_id,
        "category": "conation",
        "answer": "yes",
        "reply": "Great.",
        "confidence_level": 2,
        "confidence": "sure",
        "probability": 0.75,
        "probabilities": [0.75, 0.25],
        "replayed": False,
        "run_completed": False,
        "session_completed": False,
        "expected": state["expected"],
    }


Reply = tuple[str, Any]  # ("result", data) or ("error", (status, detail))


def _serving(replies: dict[str, list[Reply]], seen: list[dict[str, Any]]) -> Script:
    """Greet with a prompt state, then answer each request with the next scripted reply; a
    ``state`` request beyond the scripted ones gets the station's latest state."""
    prompting = _state("prompt", session=2, categories=["conation"])
    latest = {"state": prompting}

    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.send(_hello(prompting))
        async for raw in connection:
            message = json.loads(raw)
            if message["type"] == "pong":
                continue
            seen.append(message)
            scripted = replies.get(message["type"]) or []
            if not scripted and message["type"] == "state":
                scripted.append(("result", latest["state"]))
            kind, body = scripted.pop(0)
            if kind == "error":
                status, detail = body
                reply = {"type": "error", "id": message["id"], "status": status, "detail": detail}
            else:
                reply = {"type": "result", "id": message["id"], "data": body}
            await connection.send(json.dumps(reply))
            if message["type"] == "state" and body["expected"]["action"] == "wait":
                # the experimenter starts the next session: the robot prompts again
                latest["state"] = prompting
                event = {
                    "type": "event",
                    "event": "session_started",
                    "data": {},
                    "state": prompting,
                }
                await connection.send(json.dumps(event))

    return script


def test_a_refused_answer_is_shown_and_the_robot_carries_on() -> None:
    prompting = _state("prompt", session=2, categories=["conation"])
    seen: list[dict[str, Any]] = []
    replies: dict[str, list[Reply]] = {
        "prompt": [("result", _prompt()), ("result", _prompt(8))],
        "answer": [
            ("error", (409, "step 7 was already answered 'no'; a different answer is refused")),
            ("result", _answered(prompting, 8)),
        ],
        "state": [("result", prompting), ("result", prompting)],
    }
    code, out, err, _ = _robot(_serving(replies, seen), stdin="1\ny\n1\ny\nq\n")
    assert code == 0, err
    assert "Traceback" not in out + err
    assert "  refused: step 7 was already answered 'no'; a different answer is refused" in out
    after = out.split("refused:", 1)[1]
    assert "category?" in after, "the loop goes on after a refused answer"
    assert "robot: Great." in after, "the next prompt and answer work"
    assert [m["type"] for m in seen] == ["prompt", "answer", "state", "prompt", "answer", "state"]


def test_a_busy_server_asks_for_the_answer_again_and_resends_it_with_the_same_key() -> None:
    prompting = _state("prompt", session=2, categories=["conation"])
    seen: list[dict[str, Any]] = []
    replies: dict[str, list[Reply]] = {
        "prompt": [("result", _prompt())],
        "answer": [
            ("error", (503, "the database is unavailable right now; please retry")),
            ("result", _answered(prompting)),
        ],
        "state": [("result", prompting)],
    }
    code, out, err, _ = _robot(_serving(replies, seen), stdin="1\ny\ny\nq\n")
    assert code == 0, err
    assert "Traceback" not in out + err
    assert (
        "  server unavailable: the database is unavailable right now; please retry; "
        "type the answer again to retry"
    ) in out
    assert "robot: Great." in out
    answers = [m for m in seen if m["type"] == "answer"]
    assert len(answers) == 2
    assert answers[0]["idempotency_key"] == answers[1]["idempotency_key"]


def test_a_session_ended_meanwhile_is_shown_and_the_robot_waits() -> None:
    waiting = _state("wait", session=2)
    seen: list[dict[str, Any]] = []
    replies: dict[str, list[Reply]] = {
        "prompt": [("result", _prompt())],
        "answer": [("error", (409, "session 2 has ended; no more answers are taken"))],
        "state": [("result", waiting)],
    }
    code, out, err, _ = _robot(_serving(replies, seen), stdin="1\nn\nq\n")
    assert code == 0, err
    assert "Traceback" not in out + err
    assert "  refused: session 2 has ended; no more answers are taken" in out
    after = out.split("refused:", 1)[1]
    assert "waiting for the experimenter" in after
    assert "event: session_started" in after and "category?" in after


def test_a_refused_prompt_is_shown_and_the_menu_comes_back() -> None:
    prompting = _state("prompt", session=2, categories=["conation"])
    seen: list[dict[str, Any]] = []
    replies: dict[str, list[Reply]] = {
        "prompt": [("error", (503, "the database is unavailable right now; please retry"))],
        "state": [("result", prompting)],
    }
    code, out, err, _ = _robot(_serving(replies, seen), stdin="1\nq\n")
    assert code == 0, err
    assert "  server unavailable: the database is unavailable right now; please retry" in out
    assert out.count("category?") == 2
    assert [m["type"] for m in seen] == ["prompt", "state"]


def test_a_refused_prompt_rereads_the_state_and_waits_when_nothing_is_expected() -> None:
    seen: list[dict[str, Any]] = []
    replies: dict[str, list[Reply]] = {
        "prompt": [("error", (409, "no running session at station lab-1"))],
        "state": [("result", _state("wait", session=2))],
    }
    code, out, err, _ = _robot(_serving(replies, seen), stdin="1\nq\n")
    assert code == 0, err
    assert "  refused: no running session at station lab-1" in out
    after = out.split("refused:", 1)[1]
    assert after.index("waiting for the experimenter") < after.index("category?")
    assert "event: session_started" in after, "the menu comes back once a session is running"
    assert out.count("category?") == 2


QUESTION = "Do you want to escape the room?"


def _answering(step_id: int, *, open_steps: tuple[int, ...] | None = None) -> Any:
    state = _state("answer", session=4, categories=["conation"])
    state["open_prompts"] = [
        {**_prompt(n), "question": f"question {n}" if n != 7 else QUESTION}
        for n in open_steps or (step_id,)
    ]
    state["expected"]["step_id"] = step_id
    return state


def _finished() -> Any:
    state = _state("done", session=4)
    state["expected"]["message"] = "P01 has finished every session"
    return state


def _last_answer_station(seen: list[str]) -> Script:
    """A station in the session's last run with one category left, pushing an event with the
    state of the moment after each change, as the server does; once the robot has read the
    finished state, the experimenter seats the next participant."""
    prompting = _state("prompt", session=4, categories=["conation"])
    current = {"state": prompting}

    async def script(attempt: int, connection: ServerConnection) -> None:
        async def push(event: str, state: Any) -> None:
            current["state"] = state
            await connection.send(
                json.dumps({"type": "event", "event": event, "data": {}, "state": state})
            )

        async def reply(message: Any, data: Any) -> None:
            await connection.send(json.dumps({"type": "result", "id": message["id"], "data": data}))

        await connection.send(_hello(prompting))
        async for raw in connection:
            message = json.loads(raw)
            if message["type"] == "pong":
                continue
            seen.append(message["type"])
            if message["type"] == "prompt":
                await reply(message, {**_prompt(), "question": QUESTION})
                await push("prompt_opened", _answering(7))
            elif message["type"] == "answer":
                await reply(message, {**_answered(_finished()), "session_completed": True})
                await push("answer_recorded", _finished())
                await push("session_ended", _finished())
            elif message["type"] == "state":
                await reply(message, current["state"])
                if current["state"]["expected"]["action"] == "done":
                    seated = _state("prompt", session=1, categories=["conation", "cognition"])
                    await push("participant_assigned", seated)

    return script


def test_after_the_last_answer_the_robot_waits_and_never_asks_again() -> None:
    seen: list[str] = []
    code, out, err, _ = _robot(_last_answer_station(seen), stdin="1\ny\n")
    assert code == 0, err
    assert "Traceback" not in out + err
    assert out.count(f"robot: {QUESTION}") == 1, out
    assert "next: P01 has finished every session" in out
    after = out.split("finished every session", 1)[1]
    assert "(y/n)?" not in after, "nothing is to be answered after the last answer"
    assert "waiting for the experimenter" in after
    # the next participant is seated: the robot follows the server to the new menu
    assert "category? 1) conation  2) cognition" in after
    assert seen[:3] == ["prompt", "answer", "state"]


def test_the_robot_asks_the_step_the_server_expects() -> None:
    seen: list[str] = []

    async def script(attempt: int, connection: ServerConnection) -> None:
        await connection.send(_hello(_answering(9, open_steps=(8, 9))))
        async for raw in connection:
            message = json.loads(raw)
            if message["type"] == "pong":
                continue
            seen.append(f"{message['type']} {message.get('step_id', '')}".strip())
            data = _answered(_finished(), 9) if message["type"] == "answer" else _finished()
            await connection.send(json.dumps({"type": "result", "id": message["id"], "data": data}))
            if message["type"] == "state":
                await connection.close(4401, "device key revoked")

    code, out, err, _ = _robot(script, stdin="n\n")
    assert code == 2, err  # ended by the revoked key, once the robot waits
    assert "robot: question 9" in out and "question 8" not in out
    assert seen == ["answer 9", "state"]


def test_a_lost_connection_ends_with_one_error_line(monkeypatch: pytest.MonkeyPatch) -> None:
    fast = functools.partial(
        StationSocket, request_timeout=0.3, retry_delay=0.01, max_retry_delay=0.05
    )
    monkeypatch.setattr(client, "StationSocket", fast)  # the command imports it when it runs

    async def script(attempt: int, connection: ServerConnection) -> None:
        if attempt > 1:  # the server is gone: every reconnection is dropped at once
            await connection.close(1011, "going away")
            return
        await connection.send(_hello(_state("prompt", session=2, categories=["conation"])))
        async for raw in connection:
            message = json.loads(raw)
            if message["type"] == "prompt":
                reply = {"type": "result", "id": message["id"], "data": _prompt()}
                await connection.send(json.dumps(reply))
            elif message["type"] == "answer":
                await connection.close(1011, "server shutting down")
                return

    code, out, err, attempts = _robot(script, stdin="1\ny\n")
    assert code == 1
    assert "Traceback" not in out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: lost the connection to http://127.0.0.1:")
    assert lines[0].endswith("start the robot again once the server is back")
    assert len(attempts) > 1, "the client tried to reconnect before giving up"


def test_no_server_at_the_url_ends_with_one_error_line() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    args = ["robot", "--url", f"http://127.0.0.1:{port}", "--station", "lab-1", "--key", "tlk_x"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 2
    assert "Traceback" not in result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: cannot reach http://127.0.0.1:{port}")
