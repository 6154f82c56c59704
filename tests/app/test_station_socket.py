"""The station WebSocket: authentication, requests by id, pushes, heartbeats, resumption."""

from __future__ import annotations

import uuid
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from tests.conftest import Lab

SOCKET = "/api/v1/station/ws"


def _receive(ws: Any, type_: str) -> dict[str, Any]:
    """The next message of a type, skipping heartbeats and other pushes."""
    for _ in range(50):
        message = ws.receive_json()
        if message["type"] == type_:
            return dict(message)
    raise AssertionError(f"no {type_} message")


def test_hello_requests_and_pushes(lab: Lab) -> None:
    code = lab.enrol_and_assign()
    with lab.robot.websocket_connect(SOCKET) as ws:
        hello = ws.receive_json()
        assert hello["type"] == "hello"
        assert hello["station"] == "lab-1"
        assert hello["state"]["participant"] == code
        assert hello["state"]["expected"]["action"] == "start_session"
        lab.start_session()
        event = _receive(ws, "event")
        assert event["event"] == "session_started"
        assert event["state"]["expected"]["action"] == "prompt"
        ws.send_json({"id": 1, "type": "prompt", "category": "cognition"})
        result = _receive(ws, "result")
        assert (result["id"], result["op"]) == (1, "prompt")
        step = result["data"]
        assert step["category"] == "cognition" and step["created"] is True
        ws.send_json(
            {
                "id": "a",
                "type": "answer",
                "step_id": step["step_id"],
                "answer": "yes",
                "idempotency_key": "k1",
            }
        )
        answered = _receive(ws, "result")
        assert answered["id"] == "a"
        assert answered["data"]["reply"]
        ws.send_json(
            {
                "id": "b",
                "type": "answer",
                "step_id": step["step_id"],
                "answer": "no",
                "idempotency_key": "k2",
            }
        )
        refused = _receive(ws, "error")
        assert (refused["id"], refused["status"]) == ("b", 409)
        ws.send_json({"id": 9, "type": "ping"})
        assert _receive(ws, "pong")["id"] == 9


def test_reconnecting_client_resumes_without_duplicates(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    with lab.robot.websocket_connect(SOCKET) as ws:
        ws.receive_json()
        ws.send_json({"id": 1, "type": "prompt", "category": "affection"})
        step = _receive(ws, "result")["data"]
    with lab.robot.websocket_connect(SOCKET) as ws:
        hello = ws.receive_json()
        assert [p["step_id"] for p in hello["state"]["open_prompts"]] == [step["step_id"]]
        ws.send_json({"id": 2, "type": "prompt", "category": "affection"})
        again = _receive(ws, "result")["data"]
        assert again["step_id"] == step["step_id"] and again["created"] is False
        key = uuid.uuid4().hex
        for request_id in (3, 4):
            ws.send_json(
                {
                    "id": request_id,
                    "type": "answer",
                    "step_id": step["step_id"],
                    "answer": "no",
                    "idempotency_key": key,
                }
            )
        first, second = _receive(ws, "result"), _receive(ws, "result")
        assert first["data"]["replayed"] is False and second["data"]["replayed"] is True


def test_authentication_by_first_message_and_refusal(app: FastAPI, lab: Lab) -> None:
    with TestClient(app) as anonymous:
        with anonymous.websocket_connect(SOCKET) as ws:
            ws.send_json({"type": "auth", "key": lab.key})
            assert ws.receive_json()["type"] == "hello"
        with anonymous.websocket_connect(SOCKET) as ws:
            ws.send_json({"type": "auth", "key": "tlk_wrong"})
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_json()
            assert closed.value.code == 4401


def test_malformed_messages_get_clear_errors(lab: Lab) -> None:
    lab.enrol_and_assign()
    with lab.robot.websocket_connect(SOCKET) as ws:
        ws.receive_json()
        ws.send_text("{not json")
        error = _receive(ws, "error")
        assert error["status"] == 400 and error["detail"].startswith("not JSON")
        ws.send_json({"id": 1, "type": "dance"})
        error = _receive(ws, "error")
        assert error["status"] == 422 and "'state', 'prompt', 'answer'" in error["detail"]
        ws.send_json({"id": 2, "type": "prompt"})
        error = _receive(ws, "error")
        assert error == {
            "type": "error",
            "id": 2,
            "status": 422,
            "detail": "prompt.category: Field required",
        }
        ws.send_json({"id": 3, "type": "prompt", "category": "conation"})
        error = _receive(ws, "error")
        assert error["status"] == 409 and "no session is running" in error["detail"]


def test_heartbeat_pings_and_times_out(app: FastAPI, lab: Lab) -> None:
    app.state.settings = app.state.settings.model_copy(update={"websocket_heartbeat_seconds": 0.1})
    with lab.robot.websocket_connect(SOCKET) as ws:
        ws.receive_json()
        assert ws.receive_json()["type"] == "ping"
        with pytest.raises(WebSocketDisconnect) as closed:
            _drain(ws)
        assert closed.value.code == 4408


def _drain(ws: Any) -> None:
    """Read until the server closes the connection."""
    for _ in range(50):
        ws.receive_json()
