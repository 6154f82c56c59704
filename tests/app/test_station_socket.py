"""The station WebSocket: authentication, requests by id, pushes, heartbeats, resumption."""

from __future__ import annotations

import json
import uuid
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select
from starlette.websockets import WebSocketDisconnect

from app.api import station_ws
from app.db import Database
from app.security import token_digest
from app.services.audit import Actor
from app.services.sessions.stations import revoke_device
from app.tables import Device, Role
from tests.conftest import Lab, UserClientFactory, postgres_for_some, sqlite_only

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


def test_a_client_away_during_another_answer_finds_its_reply_in_the_state(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    with lab.robot.websocket_connect(SOCKET) as ws:
        hello = ws.receive_json()
        assert hello["state"]["last_reply"] is None  # nothing answered in this run yet
        ws.send_json({"id": 1, "type": "prompt", "category": "affection"})
        step = _receive(ws, "result")["data"]["step_id"]
    # the client is away (a room offline) while the experimenter answers by Wizard-of-Oz
    answered = lab.experimenter.post(
        f"/api/v1/stations/lab-1/steps/{step}/answer",
        json={"answer": "no", "idempotency_key": "woz-away"},
    )
    assert answered.status_code == 200, answered.text
    assert "last_reply" not in lab.experimenter.get("/api/v1/stations/lab-1/state").json()
    with lab.robot.websocket_connect(SOCKET) as ws:
        state = ws.receive_json()["state"]
        assert state["open_prompts"] == []
        assert state["last_reply"] == {
            "step_id": step,
            "category": "affection",
            "reply": answered.json()["reply"],
            "confidence": answered.json()["confidence"],
        }
        ws.send_json({"id": 2, "type": "prompt", "category": "conation"})
        newer = _receive(ws, "result")["data"]["step_id"]
        ws.send_json(
            {"id": 3, "type": "answer", "step_id": newer, "answer": "yes", "idempotency_key": "k"}
        )
        reply = _receive(ws, "result")["data"]["reply"]
        ws.send_json({"id": 4, "type": "state"})
        latest = _receive(ws, "result")["data"]["last_reply"]
        assert (latest["step_id"], latest["reply"]) == (newer, reply)  # the newest answer's


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
        ws.send_json(
            {"id": 4, "type": "answer", "step_id": 2**64, "answer": "yes", "idempotency_key": "k"}
        )
        error = _receive(ws, "error")
        assert error["status"] == 422 and "step_id" in error["detail"]
        ws.send_json({"id": 5, "type": "prompt", "category": "con\u0000ation"})
        error = _receive(ws, "error")  # the socket stays open and says what is wrong
        assert error["id"] == 5 and 400 <= error["status"] < 500 and error["detail"]


UNREADABLE_FRAMES: list[tuple[str, Any, str]] = [
    ("binary", b"\x00\x01", "binary frames are not supported"),
    ("nested", "[" * 100_000, "nested too deeply"),
    ("not json", "{not json", "not JSON"),
]


@pytest.mark.parametrize(("kind", "frame", "detail"), UNREADABLE_FRAMES, ids=lambda v: str(v)[:8])
@sqlite_only("a frame that cannot be read is answered before any query")
def test_an_unreadable_frame_is_answered_and_the_socket_stays_open(
    lab: Lab, kind: str, frame: Any, detail: str
) -> None:
    lab.enrol_and_assign()
    with lab.robot.websocket_connect(SOCKET) as ws:
        ws.receive_json()
        if isinstance(frame, bytes):
            ws.send_bytes(frame)
        else:
            ws.send_text(frame)
        error = _receive(ws, "error")
        assert (error["id"], error["status"]) == (None, 400)
        assert detail in error["detail"], kind
        ws.send_json({"id": "after", "type": "state"})
        assert _receive(ws, "result")["id"] == "after"


@postgres_for_some(
    "json_step_id, path_step_id",
    [
        ("true", "true"),
        ("8.0", "8.0"),
        ('"8.0"', "8.0"),
        ('"+8"', "+8"),
        ('" 8"', "%208"),
        ("0", "0"),
        ("-1", "-1"),
        (str(2**63), str(2**63)),
        ("9" * 5_000, "9" * 5_000),
    ],
    ids=[
        "true",
        "float",
        "float-text",
        "signed",
        "blank",
        "zero",
        "negative",
        "2^63",
        "5000-digits",
    ],
    postgres={"2^63"},  # past a bigint: were it let through, each engine would fail its own way
)
def test_a_step_id_rest_refuses_is_a_422_with_the_request_id(
    lab: Lab, json_step_id: str, path_step_id: str
) -> None:
    """The WebSocket checks fields as REST does: ``true`` used to answer step 1 and ``8.0`` step
    8, and a 5,000-digit number dropped the socket (json.loads' ValueError)."""
    lab.enrol_and_assign()
    lab.start_session()
    with lab.robot.websocket_connect(SOCKET) as ws:
        ws.receive_json()
        ws.send_json({"id": 1, "type": "prompt", "category": "conation"})
        assert _receive(ws, "result")["data"]["step_id"] >= 1
        frame = {"id": 2, "type": "answer", "step_id": 0, "answer": "yes", "idempotency_key": "k"}
        ws.send_text(json.dumps(frame).replace('"step_id": 0', f'"step_id": {json_step_id}'))
        error = _receive(ws, "error")
        assert (error["id"], error["status"]) == (2, 422)
        assert error["detail"].startswith("answer.step_id")
    rest = lab.robot.post(
        f"/api/v1/station/steps/{path_step_id}/answer",
        json={"answer": "yes", "idempotency_key": "k"},
    )
    assert rest.status_code == 422
    assert lab.robot.get("/api/v1/station").json()["open_prompts"], "nothing was answered"


@sqlite_only("an id that cannot be echoed is refused before any query")
def test_an_id_that_cannot_be_echoed_is_dropped_not_fatal(lab: Lab) -> None:
    with lab.robot.websocket_connect(SOCKET) as ws:
        ws.receive_json()
        ws.send_json({"id": {"nested": True}, "type": "state"})
        error = _receive(ws, "error")
        assert (error["id"], error["status"]) == (None, 422)
        ws.send_json({"id": True, "type": "ping"})
        assert _receive(ws, "error")["status"] == 422


@postgres_for_some(
    "frame, reason",
    [
        (b"\x00", "binary frames are not supported"),
        ("[" * 100_000, "nested too deeply"),
        ('{"type": "auth", "key": 1' + "0" * 5_000 + "}", "unknown or revoked device key"),
        ('{"type": "state"}', "the first message must be"),
        ("[]", "the first message must be"),
        ('{"type": "auth", "key": "tlk_wrong"}', "unknown or revoked device key"),
    ],
    ids=["binary", "nested", "long-number", "not-auth", "not-object", "wrong-key"],
    postgres={"long-number", "wrong-key"},  # the two that look a key up; the rest never get there
)
def test_a_bad_first_message_closes_with_4401_and_the_reason(
    app: FastAPI, lab: Lab, frame: Any, reason: str
) -> None:
    with TestClient(app) as anonymous, anonymous.websocket_connect(SOCKET) as ws:
        if isinstance(frame, bytes):
            ws.send_bytes(frame)
        else:
            ws.send_text(frame)
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 4401
        assert reason in (closed.value.reason or "")


def test_no_auth_message_in_time_closes_with_4401(app: FastAPI, lab: Lab) -> None:
    app.state.settings = app.state.settings.model_copy(update={"websocket_auth_seconds": 0.05})
    with TestClient(app) as anonymous, anonymous.websocket_connect(SOCKET) as ws:
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert (closed.value.code, closed.value.reason) == (4401, "no auth message in time")


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


def _device_id(lab: Lab, key: str) -> int:
    with lab.database.writing() as db:
        device_id = db.scalar(select(Device.id).where(Device.key_hash == token_digest(key)))
    assert device_id is not None
    return int(device_id)


def _revoke_from_another_process(lab: Lab) -> None:
    """Revoke the lab's key as ``trustlab device revoke`` does: with a Database of its own (on
    SQLite its events reach no other process; on PostgreSQL they arrive by NOTIFY)."""
    elsewhere = Database(lab.database.url)
    try:
        with elsewhere.writing() as db:
            revoke_device(db, device_id=_device_id(lab, lab.key), actor=Actor.system("tests"))
    finally:
        elsewhere.dispose()


def _closed_code(ws: Any) -> int:
    with pytest.raises(WebSocketDisconnect) as closed:
        _drain(ws)
    return int(closed.value.code)


@pytest.mark.timeout(60)
def test_revoking_a_key_closes_its_open_socket_at_once(
    app: FastAPI, lab: Lab, user_client: UserClientFactory
) -> None:
    """The revocation's event closes the socket (4401); the station's other key stays connected.
    The heartbeat is an hour, so only the event can close it before the test's timeout."""
    app.state.settings = app.state.settings.model_copy(update={"websocket_heartbeat_seconds": 3600})
    admin = user_client(Role.ADMIN)
    spare = admin.post(f"/api/v1/stations/{lab.station}/devices", json={"label": "spare"})
    spare_key = spare.json()["key"]
    with (
        lab.robot.websocket_connect(SOCKET) as ws,
        TestClient(app, headers={"Authorization": f"Bearer {spare_key}"}) as other,
        other.websocket_connect(SOCKET) as other_ws,
    ):
        assert ws.receive_json()["type"] == "hello"
        assert other_ws.receive_json()["type"] == "hello"
        revoked = admin.post(f"/api/v1/devices/{_device_id(lab, lab.key)}/revoke")
        assert revoked.status_code == 200
        assert _closed_code(ws) == 4401
        other_ws.send_json({"id": 1, "type": "state"})
        reply = other_ws.receive_json()
        assert (reply["type"], reply["id"]) == ("result", 1)


@pytest.mark.timeout(60)
def test_a_revocation_that_sends_no_event_closes_the_socket_at_the_next_heartbeat(
    app: FastAPI, lab: Lab, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On SQLite a revocation from another process (``trustlab device revoke``) reaches this
    process as no event: the heartbeat's key check closes the socket (4401), not the timeout.
    The silent client's timeout is put out of reach, so however long the revocation takes on a
    loaded machine, only the key check can close it."""
    monkeypatch.setattr(station_ws, "MISSED_HEARTBEATS", 10**6)
    app.state.settings = app.state.settings.model_copy(update={"websocket_heartbeat_seconds": 0.2})
    with lab.robot.websocket_connect(SOCKET) as ws:
        assert ws.receive_json()["type"] == "hello"
        _revoke_from_another_process(lab)
        assert _closed_code(ws) == 4401


@pytest.mark.timeout(60)
def test_a_request_with_a_revoked_key_closes_the_socket(app: FastAPI, lab: Lab) -> None:
    app.state.settings = app.state.settings.model_copy(update={"websocket_heartbeat_seconds": 30})
    with lab.robot.websocket_connect(SOCKET) as ws:
        assert ws.receive_json()["type"] == "hello"
        _revoke_from_another_process(lab)
        ws.send_json({"id": 1, "type": "state"})
        assert _closed_code(ws) == 4401
