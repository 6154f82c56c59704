"""Integers and names a request carries (app/inputs.py): bounded in one place, matched in full."""

from __future__ import annotations

import types
import typing
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.routing import APIRoute, APIWebSocketRoute
from pydantic import BaseModel, BeforeValidator

from app import inputs
from app.api.station_ws import AnswerMessage
from app.errors import InvalidInput
from app.protocol import default_protocol
from app.tables import Role
from tests.app.routes import api_routes
from tests.conftest import Lab, UserClientFactory, postgres_for_some, sqlite_only

TOO_BIG = "1" + "0" * 29
"""A 30-digit id: SQLite's driver raised OverflowError on it (a 500 and a reset connection)."""


def _int_metadata(annotation: Any, metadata: list[Any]) -> list[Any] | None:
    """The constraints of an integer field (an optional one too: they sit inside its
    ``Annotated``), or None when the field is no integer (booleans are not)."""
    if annotation is int:
        return list(metadata)
    if typing.get_origin(annotation) is typing.Annotated:
        inner, *extra = typing.get_args(annotation)
        return _int_metadata(inner, [*metadata, *_flatten(extra)])
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            found = _int_metadata(arg, metadata)
            if found is not None:
                return found
    return None


def _flatten(extra: list[Any]) -> list[Any]:
    """Annotated extras with pydantic's FieldInfo opened up into its own constraints."""
    out: list[Any] = []
    for item in extra:
        out.extend(getattr(item, "metadata", [item]) if hasattr(item, "metadata") else [item])
    return out


def _is_bounded(metadata: list[Any]) -> bool:
    """Whether a field went through app/inputs.py: its canonical check and an upper bound."""
    canonical = any(
        isinstance(m, BeforeValidator) and m.func is inputs.canonical_int for m in metadata
    )
    upper = any(getattr(m, "le", None) is not None for m in metadata)
    return canonical and upper


def _field_ints(annotation: Any, metadata: list[Any], where: str) -> Iterator[tuple[str, bool]]:
    found = _int_metadata(annotation, metadata)
    if found is not None:
        yield where, _is_bounded(found)
    for arg in (annotation, *typing.get_args(annotation)):
        if isinstance(arg, type) and issubclass(arg, BaseModel):
            for name, field in arg.model_fields.items():
                yield from _field_ints(field.annotation, field.metadata, f"{where}.{name}")


def _route_ints(app: FastAPI) -> Iterator[tuple[str, bool]]:
    """Every integer a route takes (path, query, header, cookie, form or JSON body, through its
    dependencies too), with whether it is bounded."""
    for served in api_routes(app):
        route = served.route
        assert isinstance(route, APIRoute | APIWebSocketRoute)
        pending = [route.dependant]
        while pending:
            dependant = pending.pop()
            pending.extend(dependant.dependencies)
            params = (
                dependant.path_params
                + dependant.query_params
                + dependant.header_params
                + dependant.cookie_params
                + dependant.body_params
            )
            for param in params:
                info = param.field_info
                yield from _field_ints(
                    info.annotation, info.metadata, f"{served.path} {param.name}"
                )


@sqlite_only("a walk over the routes' declarations")
def test_the_walk_finds_the_routes_integers(app: FastAPI) -> None:
    """The walk below sees path, query, form and body integers (so its silence means something)."""
    found = dict(_route_ints(app))
    for where in (
        "/admin/audit page",
        "/api/v1/devices/{device_id}/revoke device_id",
        "/devices/{device_id}/revoke device_id",
        "/stations/{name}/woz/answer step_id",
        "/api/v1/tablet/questionnaires/{instrument} body.session",
    ):
        assert any(key.startswith(where.split()[0]) and where.split()[1] in key for key in found), (
            where,
            sorted(found),
        )


@sqlite_only("a walk over the routes' declarations")
def test_every_integer_a_route_takes_is_bounded_in_one_place(app: FastAPI) -> None:
    unbounded = sorted(where for where, bounded in _route_ints(app) if not bounded)
    assert unbounded == [], "use a type from app/inputs.py for: " + ", ".join(unbounded)


def test_the_websockets_integers_are_bounded_too() -> None:
    found = dict(_field_ints(AnswerMessage, [], "answer"))
    assert found == {"answer.id": True, "answer.step_id": True}


@postgres_for_some(
    "value",
    [TOO_BIG, "9" * 5_000, "-1", "0", "1.0", "+1", "1_0", " 1"],
    ids=["too-big", "5000-digits", "-1", "0", "1.0", "+1", "1_0", "blank-1"],
    postgres={"too-big"},  # past a bigint: were it let through, each engine would fail its own way
)
def test_oversized_or_malformed_ids_are_4xx_never_500(
    lab: Lab, user_client: UserClientFactory, value: str
) -> None:
    admin = user_client(Role.ADMIN)
    responses = {
        "audit page": admin.get(f"/admin/audit?page={value}"),
        "api revoke": admin.post(f"/api/v1/devices/{value}/revoke"),
        "web revoke": admin.post(f"/devices/{value}/revoke", follow_redirects=False),
        "woz answer": lab.experimenter.post(
            f"/stations/{lab.station}/woz/answer",
            data={"step_id": value, "answer": "yes", "idempotency_key": "k"},
            follow_redirects=False,
        ),
        "tablet page": lab.experimenter.get(f"/tablet/q/post_session/{value}"),
    }
    statuses = {name: response.status_code for name, response in responses.items()}
    assert all(400 <= status < 500 for status in statuses.values()), statuses
    assert admin.get("/admin/audit").status_code == 200, "the connection still serves"


def test_a_far_page_of_the_audit_log_within_bounds_is_empty_not_an_error(
    user_client: UserClientFactory,
) -> None:
    admin = user_client(Role.ADMIN)
    response = admin.get("/admin/audit?page=1000000000")
    assert response.status_code == 200


@pytest.mark.parametrize(
    ("value", "expected"),
    [(8, 8), ("8", 8), ("0012", 12), (2**63 - 1, 2**63 - 1)],
)
def test_canonical_ints_pass(value: Any, expected: int) -> None:
    assert inputs.canonical_int(value) == expected


@pytest.mark.parametrize("value", [True, False, 8.0, "8.0", "+8", " 8", "8 ", "1_000", "٣", 10**19])
def test_everything_else_is_refused(value: Any) -> None:
    with pytest.raises(ValueError):
        inputs.canonical_int(value)


RULES = [inputs.STUDY_NAME, inputs.STATION_NAME, inputs.PARTICIPANT_CODE, inputs.USERNAME]


@pytest.mark.parametrize("rule", RULES, ids=lambda rule: rule.what)
@pytest.mark.parametrize("suffix", ["\n", "\r\n", " ", "\t", "\x00"], ids=repr)
def test_a_name_with_a_trailing_newline_or_blank_is_refused(
    rule: inputs.NameRule, suffix: str
) -> None:
    assert rule.matches("lab-1")
    assert not rule.matches("lab-1" + suffix)
    with pytest.raises(InvalidInput, match=rule.what):
        rule.check("lab-1" + suffix)


def test_stratum_values_refuse_control_characters_anywhere() -> None:
    assert inputs.STRATUM_VALUE.matches("18-25 years")
    for bad in ["a\nb", "a\x00", "a;b", "a=b", " a"]:
        assert not inputs.STRATUM_VALUE.matches(bad), bad


def test_look_alike_studies_and_stations_cannot_be_created(
    lab: Lab, user_client: UserClientFactory
) -> None:
    """``"default\\n"`` and ``"lab-1\\n"`` used to create second, look-alike rows."""
    admin = user_client(Role.ADMIN)
    station = admin.post("/api/v1/stations", json={"name": f"{lab.station}\n"})
    assert station.status_code == 422 and "station name" in station.json()["detail"]
    source = default_protocol().source_text
    study = admin.post("/api/v1/studies", json={"name": f"{lab.study}\n", "protocol_toml": source})
    assert study.status_code == 422 and "study name" in study.json()["detail"]
    listed = admin.get("/api/v1/studies").json()
    assert all("\n" not in item["name"] for item in listed)
    enrolled = admin.post(f"/api/v1/studies/{lab.study}/participants", json={"code": "P9\n"})
    assert enrolled.status_code in (201, 422)
    if enrolled.status_code == 201:  # codes are stripped before the check: the same code
        assert enrolled.json()["code"] == "P9"
