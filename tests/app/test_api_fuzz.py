"""schemathesis against the app's own OpenAPI document, with valid credentials for every operation.

Each operation gets a bounded number of generated requests (valid and invalid bodies, parameters
and headers) sent with the credentials its users hold: the robot's device key for the station API,
the participant's tablet token for the tablet API, and a signed-in admin (cookie + CSRF header)
for the rest. Every response must be free of server errors, carry a documented status code and
content type, and match its documented schema. Runs on SQLite: the contract does not depend on
the engine, and the two-engine behaviour is covered by the rest of the suite.
"""

from __future__ import annotations

from typing import Any

import pytest
import schemathesis
from fastapi import FastAPI
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from app.access import Principal
from app.db import Database
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
def engine_name() -> str:
    return "sqlite"


@pytest.fixture
def world(app: FastAPI, database: Database, exp3_study: str) -> World:
    return build_world(app, database, exp3_study)


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


def test_every_operation_conforms_to_its_schema(world: World) -> None:
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
