"""schemathesis against the app's own OpenAPI document, with valid credentials for every operation.

Each operation gets a bounded number of generated requests (valid and invalid bodies, parameters
and headers) sent with the credentials its users hold: the robot's device key for the station API,
the participant's tablet token for the tablet API, and a signed-in admin (cookie + CSRF header)
for the rest. Every response must be free of server errors, carry a documented status code and
content type, and match its documented schema. The station WebSocket gets generated frames of
every shape (valid and broken messages, arbitrary JSON, text that is not JSON, binary frames): each
is answered and the connection stays open. Both fuzz runs end with ``trustlab verify``'s checks,
which must find nothing, on both engines.
"""

from __future__ import annotations

import json
from typing import Any

import pytest
import schemathesis
from fastapi import FastAPI
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from app.access import Principal
from app.db import Database
from app.services.sessions import verify
from tests.app.lab_world import World, build_world, client_for

EXAMPLES_PER_OPERATION = 25
"""Bounded so the whole fuzz run stays near a minute in CI; raise it locally to dig deeper."""

CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
]


@pytest.fixture
def world(app: FastAPI, database: Database, exp3_study: str) -> World:
    return build_world(app, database, exp3_study)


def assert_verify_finds_nothing(database: Database, study: str) -> None:
    """What ``trustlab verify`` checks (replayed learners, steps, timelines, allocation) holds."""
    with database.read_session() as db:
        report = verify.verify_study(db, study_name=study)
    assert report.participants == 2
    assert report.findings == []


def principal_for(path: str) -> Principal:
    """Who really calls an operation: the robot, the participant's tablet, or a signed-in admin."""
    if path.startswith("/api/v1/station"):
        return Principal.DEVICE_OWN
    if path.startswith("/api/v1/tablet"):
        return Principal.PARTICIPANT_OWN
    if path == "/api/v1/session":
        return Principal.ANONYMOUS
    return Principal.ADMIN


def fuzz_order(path: str) -> int:
    """Robot and tablet operations first, while their keys are certainly valid (the admin's
    operations may revoke a key); sign-in last, since its failures throttle the address."""
    return {Principal.DEVICE_OWN: 0, Principal.PARTICIPANT_OWN: 1, Principal.ADMIN: 2}.get(
        principal_for(path), 3
    )


def fuzzer(
    operation: Any, headers: dict[str, str], cookies: dict[str, str], sent: list[int]
) -> Any:
    """A Hypothesis test that sends generated requests for one operation with fixed credentials."""

    @settings(
        max_examples=EXAMPLES_PER_OPERATION,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(case=operation.as_strategy())
    def exercise(case: Any) -> None:
        sent.append(1)
        case.call_and_validate(
            headers={**headers, **(case.headers or {})}, cookies=cookies, checks=CHECKS
        )

    return exercise


def test_every_operation_conforms_to_its_schema(world: World, exp3_study: str) -> None:
    schema = schemathesis.openapi.from_asgi("/api/v1/openapi.json", world.app)
    credentials = {}
    for principal in {principal_for(path) for path in schema.raw_schema["paths"]}:
        client = client_for(world, principal)  # signed in before any sign-in is fuzzed
        credentials[principal] = (dict(client.headers), dict(client.cookies))
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) > 10, "the OpenAPI document lists too few operations"
    failures: list[str] = []
    sent: list[int] = []
    for operation in sorted(operations, key=lambda op: fuzz_order(op.path)):
        headers, cookies = credentials[principal_for(operation.path)]

        exercise = fuzzer(operation, headers, cookies, sent)
        try:
            exercise()
        except Exception as failure:
            failures.append(f"{operation.label}: {str(failure).strip()[:2000]}")
    assert failures == [], "\n\n".join(failures)
    assert len(sent) >= 5 * len(operations), f"only {len(sent)} requests were generated"
    assert_verify_finds_nothing(world.app.state.database, exp3_study)


SOCKET_FRAMES = 150
"""Frames per run: enough to reach every message type with broken and valid fields."""

_scalars = st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20)
_json = st.recursive(
    _scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=12,
)
_field = _json | st.integers(min_value=-(2**70), max_value=2**70) | st.sampled_from(["yes", "no"])
_message = st.fixed_dictionaries(
    {"type": st.sampled_from(["state", "prompt", "answer", "start_run", "ping", "auth", "x"])},
    optional={
        "id": _field,
        "category": st.sampled_from(["conation", "affection", "cognition"]) | _field,
        "step_id": _field,
        "answer": _field,
        "idempotency_key": st.text(max_size=120) | _field,
        "extra": _field,
    },
)
_frame = (
    _message.map(json.dumps)
    | _json.map(json.dumps)
    | st.text(max_size=40)
    | st.binary(max_size=40)
    | st.integers(min_value=1, max_value=30).map(lambda depth: "[" * depth * 1000)
)


def test_every_websocket_frame_is_answered_and_the_connection_stays_open(
    world: World, exp3_study: str
) -> None:
    """After each generated frame a ping must still come back: nothing the robot sends closes
    its authenticated connection or goes unanswered without the connection noticing."""
    robot = client_for(world, Principal.DEVICE_OWN)
    sent: list[int] = []
    with robot, robot.websocket_connect("/api/v1/station/ws") as ws:
        assert ws.receive_json()["type"] == "hello"

        @settings(
            max_examples=SOCKET_FRAMES,
            deadline=None,
            derandomize=True,
            database=None,
            suppress_health_check=list(HealthCheck),
        )
        @given(frame=_frame)
        def exercise(frame: str | bytes) -> None:
            sent.append(1)
            if isinstance(frame, bytes):
                ws.send_bytes(frame)
            else:
                ws.send_text(frame)
            probe = f"probe-{len(sent)}"
            ws.send_json({"id": probe, "type": "ping"})
            for _ in range(20):  # replies, events and heartbeats may come first
                message = ws.receive_json()
                assert message.get("status") != 500, (frame, message)
                if message.get("type") == "pong" and message.get("id") == probe:
                    return
            raise AssertionError(f"no pong after {frame!r}")

        exercise()
    assert len(sent) >= SOCKET_FRAMES // 2
    assert_verify_finds_nothing(world.app.state.database, exp3_study)
