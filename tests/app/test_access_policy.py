"""Every route × every principal, against the policy table in app/access.py.

The routes are enumerated from the running app, so a route added without a policy fails here.
Each cell sends one request with that principal's credentials (a fresh client each time) and
checks that it is let through or refused as the table says. Probes are chosen so that the roles
allowed through cannot change anything (unknown names, incomplete bodies, a step already being
answered), except where the check itself needs a real resource (a robot answering its own step).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.access import POLICY, Principal
from app.db import Database
from app.tablet import form_token
from tests.app.lab_world import World, build_world, client_for
from tests.app.routes import served_routes
from tests.conftest import CSRF_INPUT


def app_routes(app: FastAPI) -> set[tuple[str, str]]:
    """(method, path) of every route the app serves (HEAD folded into GET)."""
    found: set[tuple[str, str]] = set()
    for served in served_routes(app):
        if served.websocket:
            found.add(("WS", served.path))
        found.update((method, served.path) for method in served.methods if method != "HEAD")
    return found


@pytest.fixture
def engine_name() -> str:
    """The policy does not depend on the engine; one is enough."""
    return "sqlite"


@pytest.fixture
def world(app: FastAPI, database: Database, exp3_study: str) -> World:
    return build_world(app, database, exp3_study)


def _tablet_form(world: World, principal: Principal) -> dict[str, str]:
    if principal is Principal.PARTICIPANT_OWN:
        return {"csrf_token": form_token(world.secret, world.tokens["P001"])}
    if principal is Principal.PARTICIPANT_OTHER:
        return {"csrf_token": form_token(world.secret, world.tokens["P002"])}
    return {}


def _login_probe(client: TestClient, world: World, principal: Principal) -> Any:
    token = CSRF_INPUT.search(client.get("/login").text)
    assert token
    return client.post(
        "/login",
        data={
            "username": "throwaway",
            "password": "correct horse battery",
            "csrf_token": token.group(1),
        },
        follow_redirects=False,
    )


Probe = Callable[[TestClient, World, Principal], Any]


def get(path: str) -> Probe:
    return lambda client, world, principal: client.get(
        path.format(**_names(world)), follow_redirects=False
    )


def send(method: str, path: str, **kwargs: Any) -> Probe:
    def probe(client: TestClient, world: World, principal: Principal) -> Any:
        extra = dict(kwargs)
        if extra.pop("tablet_form", False):
            extra["data"] = {**extra.get("data", {}), **_tablet_form(world, principal)}
        return client.request(method, path.format(**_names(world)), follow_redirects=False, **extra)

    return probe


def stream(path: str) -> Probe:
    def probe(client: TestClient, world: World, principal: Principal) -> Any:
        with client.stream("GET", path.format(**_names(world)), follow_redirects=False) as response:
            return response

    return probe


def _names(world: World) -> dict[str, Any]:
    return {"token": world.tokens["P001"], "kiosk": world.kiosk, "step": world.step}


ANSWER = {"answer": "yes", "idempotency_key": "policy-probe"}
PROBES: dict[tuple[str, str], Probe] = {
    ("GET", "/healthz"): get("/healthz"),
    ("GET", "/api/v1/ping"): get("/api/v1/ping"),
    ("GET", "/api/v1/openapi.json"): get("/api/v1/openapi.json"),
    ("GET", "/api/v1/docs"): get("/api/v1/docs"),
    ("GET", "/static"): get("/static/css/app.css"),
    ("GET", "/favicon.ico"): get("/favicon.ico"),
    ("GET", "/login"): get("/login"),
    ("POST", "/login"): _login_probe,
    ("POST", "/api/v1/session"): send(
        "POST",
        "/api/v1/session",
        json={"username": "throwaway", "password": "correct horse battery"},
    ),
    ("GET", "/t/{token}"): get("/t/{token}"),
    ("GET", "/k/{token}"): get("/k/{kiosk}"),
    ("POST", "/logout"): send("POST", "/logout"),
    ("GET", "/api/v1/session"): get("/api/v1/session"),
    ("DELETE", "/api/v1/session"): send("DELETE", "/api/v1/session"),
    ("GET", "/"): get("/"),
    ("GET", "/api/v1/studies"): get("/api/v1/studies"),
    ("GET", "/api/v1/studies/{name}"): get("/api/v1/studies/rt"),
    ("GET", "/api/v1/studies/{name}/protocol"): get("/api/v1/studies/rt/protocol"),
    ("GET", "/api/v1/studies/{name}/participants"): get("/api/v1/studies/rt/participants"),
    ("GET", "/api/v1/studies/{name}/participants/{code}"): get(
        "/api/v1/studies/rt/participants/P001"
    ),
    ("GET", "/studies/{name}"): get("/studies/rt"),
    ("GET", "/studies/{name}/dashboard"): get("/studies/rt/dashboard"),
    ("GET", "/studies/{name}/monitor"): get("/studies/rt/monitor"),
    ("GET", "/api/v1/protocols"): get("/api/v1/protocols"),
    ("GET", "/admin/protocols/edit"): get("/admin/protocols/edit"),
    ("POST", "/admin/protocols/edit"): send(
        "POST", "/admin/protocols/edit", data={"name": "probe", "start": "x", "text": "x"}
    ),
    ("POST", "/admin/protocols/check"): send("POST", "/admin/protocols/check", data={"text": ""}),
    ("GET", "/studies/{name}/preview"): get("/studies/rt/preview"),
    ("GET", "/studies/{name}/preview/room/{language}"): get("/studies/rt/preview/room/en"),
    ("GET", "/studies/{name}/preview/room/{language}/api/room"): get(
        "/studies/rt/preview/room/en/api/room"
    ),
    ("GET", "/studies/{name}/preview/room/{language}/api/speech"): get(
        "/studies/rt/preview/room/en/api/speech"
    ),
    ("GET", "/studies/{name}/preview/room/{language}/api/speech/audio"): get(
        "/studies/rt/preview/room/en/api/speech/audio?text=nope"
    ),
    ("GET", "/studies/{name}/protocol.toml"): get("/studies/rt/protocol.toml"),
    ("GET", "/studies/{name}/preview/{language}/{number}"): get("/studies/rt/preview/en/1"),
    ("POST", "/studies/{name}/preview/{language}/{number}"): send(
        "POST", "/studies/rt/preview/en/1", data={"accept": "yes"}
    ),
    ("GET", "/studies/{name}/dashboard.json"): get("/studies/rt/dashboard.json"),
    ("GET", "/studies/{name}/events"): stream("/studies/rt/events"),
    ("GET", "/studies/{name}/participants/{code}"): get("/studies/rt/participants/P001"),
    ("GET", "/api/v1/stations"): get("/api/v1/stations"),
    ("GET", "/api/v1/stations/{name}/state"): get("/api/v1/stations/lab-1/state"),
    ("GET", "/stations/{name}/events"): stream("/stations/lab-1/events"),
    ("POST", "/api/v1/studies/{name}/participants"): send(
        "POST", "/api/v1/studies/ghost/participants", json={}
    ),
    ("POST", "/api/v1/studies/{name}/participants/{code}/withdraw"): send(
        "POST", "/api/v1/studies/rt/participants/NOPE/withdraw", json={}
    ),
    ("POST", "/api/v1/studies/{name}/participants/{code}/erase"): send(
        "POST", "/api/v1/studies/rt/participants/NOPE/erase", json={"confirm": "NOPE"}
    ),
    ("GET", "/api/v1/studies/{name}/participants/{code}/link"): get(
        "/api/v1/studies/rt/participants/NOPE/link"
    ),
    ("POST", "/api/v1/studies/{name}/participants/{code}/link"): send(
        "POST", "/api/v1/studies/rt/participants/NOPE/link"
    ),
    ("DELETE", "/api/v1/studies/{name}/participants/{code}/link"): send(
        "DELETE", "/api/v1/studies/rt/participants/NOPE/link"
    ),
    ("POST", "/api/v1/studies/{name}/participants/{code}/lock"): send(
        "POST", "/api/v1/studies/rt/participants/NOPE/lock"
    ),
    ("POST", "/api/v1/studies/{name}/participants/{code}/unlock"): send(
        "POST", "/api/v1/studies/rt/participants/NOPE/unlock"
    ),
    ("POST", "/studies/{name}/participants"): send(
        "POST", "/studies/ghost/participants", data={"code": "X"}
    ),
    ("GET", "/studies/{name}/participants/{code}/withdraw"): get(
        "/studies/rt/participants/NOPE/withdraw"
    ),
    ("POST", "/studies/{name}/participants/{code}/withdraw"): send(
        "POST", "/studies/rt/participants/NOPE/withdraw", data={}
    ),
    ("POST", "/studies/{name}/participants/{code}/link"): send(
        "POST", "/studies/rt/participants/NOPE/link", data={}
    ),
    ("POST", "/studies/{name}/participants/{code}/link/revoke"): send(
        "POST", "/studies/rt/participants/NOPE/link/revoke", data={}
    ),
    ("POST", "/studies/{name}/participants/{code}/lock"): send(
        "POST", "/studies/rt/participants/NOPE/lock", data={}
    ),
    ("POST", "/studies/{name}/participants/{code}/unlock"): send(
        "POST", "/studies/rt/participants/NOPE/unlock", data={}
    ),
    ("POST", "/studies/{name}/participants/{code}/language"): send(
        "POST", "/studies/rt/participants/NOPE/language", data={"language": "en"}
    ),
    ("PUT", "/api/v1/stations/{name}/participant"): send(
        "PUT", "/api/v1/stations/ghost/participant", json={"study": "rt", "code": "P001"}
    ),
    ("DELETE", "/api/v1/stations/{name}/participant"): send(
        "DELETE", "/api/v1/stations/ghost/participant"
    ),
    ("POST", "/api/v1/stations/{name}/sessions"): send("POST", "/api/v1/stations/ghost/sessions"),
    ("POST", "/api/v1/stations/{name}/sessions/current/end"): send(
        "POST", "/api/v1/stations/ghost/sessions/current/end"
    ),
    ("POST", "/api/v1/stations/{name}/runs"): send("POST", "/api/v1/stations/ghost/runs"),
    ("POST", "/api/v1/stations/{name}/runs/current/end"): send(
        "POST", "/api/v1/stations/ghost/runs/current/end"
    ),
    ("POST", "/api/v1/stations/{name}/prompts"): send(
        "POST", "/api/v1/stations/ghost/prompts", json={"category": "conation"}
    ),
    ("POST", "/api/v1/stations/{name}/steps/{step_id}/answer"): send(
        "POST", "/api/v1/stations/ghost/steps/{step}/answer", json=ANSWER
    ),
    ("GET", "/stations"): get("/stations"),
    ("GET", "/stations/{name}"): get("/stations/lab-1"),
    ("GET", "/stations/{name}/room-panel"): get("/stations/lab-1/room-panel"),
    ("GET", "/stations/{name}/room"): get("/stations/lab-1/room"),
    ("GET", "/api/v1/languages/{language}/words"): get("/api/v1/languages/sv/words"),
    **{
        ("POST", f"/stations/{{name}}/{action}"): send(
            "POST", f"/stations/ghost/{action}", data=data
        )
        for action, data in {
            "assign": {"study": "rt", "code": "P001"},
            "study": {"study": "rt"},
            "unassign": {},
            "session/start": {},
            "session/end": {},
            "run/start": {},
            "run/end": {},
            "woz/prompt": {"category": "conation"},
            "woz/answer": {"step_id": "1", "answer": "yes", "idempotency_key": "k"},
        }.items()
    },
    ("GET", "/studies/{name}/analysis"): get("/studies/ghost/analysis"),
    ("GET", "/studies/{name}/analysis/mixed"): get("/studies/ghost/analysis/mixed"),
    ("GET", "/studies/{name}/analysis/power"): get("/studies/ghost/analysis/power"),
    ("GET", "/studies/{name}/exports/{export}"): get("/studies/rt/exports/nope"),
    ("POST", "/api/v1/studies"): send("POST", "/api/v1/studies", json={}),
    ("POST", "/api/v1/studies/{name}/status"): send(
        "POST", "/api/v1/studies/ghost/status", json={"status": "open"}
    ),
    ("POST", "/api/v1/studies/{name}/unblind"): send("POST", "/api/v1/studies/ghost/unblind"),
    ("POST", "/api/v1/studies/{name}/phase"): send(
        "POST", "/api/v1/studies/ghost/phase", json={"phase": "live"}
    ),
    ("POST", "/api/v1/studies/{name}/pilot/reset"): send(
        "POST", "/api/v1/studies/ghost/pilot/reset"
    ),
    ("POST", "/api/v1/stations"): send("POST", "/api/v1/stations", json={}),
    ("PATCH", "/api/v1/stations/{name}"): send(
        "PATCH", "/api/v1/stations/ghost", json={"site": None}
    ),
    ("POST", "/api/v1/stations/{name}/devices"): send(
        "POST", "/api/v1/stations/ghost/devices", json={}
    ),
    ("POST", "/api/v1/stations/{name}/kiosk"): send("POST", "/api/v1/stations/ghost/kiosk"),
    ("POST", "/api/v1/devices/{device_id}/revoke"): send("POST", "/api/v1/devices/999999/revoke"),
    ("GET", "/admin/users"): get("/admin/users"),
    ("POST", "/admin/users"): send("POST", "/admin/users", data={}),
    ("GET", "/admin/users/{username}"): get("/admin/users/ghost"),
    ("GET", "/admin/users/{username}/disable"): get("/admin/users/ghost/disable"),
    ("GET", "/admin/users/{username}/password"): get("/admin/users/ghost/password"),
    **{
        ("POST", f"/admin/users/{{username}}/{change}"): send(
            "POST", f"/admin/users/ghost/{change}", data=data
        )
        for change, data in (
            ("disable", {}),
            ("enable", {}),
            ("role", {"role": "analyst"}),
            ("password", {"password": "ghost password", "confirm": "ghost password"}),
            ("unlock", {}),
            ("sites", {"every": "true"}),
        )
    },
    ("GET", "/account"): get("/account"),
    ("POST", "/account/password"): send("POST", "/account/password", data={}),
    ("GET", "/admin/studies/new"): get("/admin/studies/new"),
    ("POST", "/admin/studies"): send("POST", "/admin/studies", data={}),
    ("POST", "/admin/studies/{name}/status"): send(
        "POST", "/admin/studies/ghost/status", data={"status": "open"}
    ),
    ("POST", "/admin/studies/{name}/archive"): send(
        "POST", "/admin/studies/ghost/archive", data={"archived": "true"}
    ),
    ("GET", "/admin/studies/{name}/unblind"): get("/admin/studies/ghost/unblind"),
    ("POST", "/admin/studies/{name}/unblind"): send(
        "POST", "/admin/studies/ghost/unblind", data={}
    ),
    ("GET", "/admin/studies/{name}/protocol"): get("/admin/studies/ghost/protocol"),
    ("POST", "/admin/studies/{name}/protocol"): send(
        "POST", "/admin/studies/ghost/protocol", data={"base": "0" * 64, "text": "x = 1"}
    ),
    ("POST", "/admin/studies/{name}/protocol/undo"): send(
        "POST", "/admin/studies/ghost/protocol/undo", data={"base": "0" * 64}
    ),
    ("POST", "/admin/studies/{name}/protocol/check"): send(
        "POST", "/admin/studies/ghost/protocol/check", data={"text": "x = 1"}
    ),
    ("POST", "/admin/studies/{name}/split"): send(
        "POST", "/admin/studies/ghost/split", data={"text": "x = 1", "new_name": "ghost-2"}
    ),
    ("GET", "/admin/studies/{name}/design/{slug}"): get("/admin/studies/ghost/design/study"),
    ("POST", "/admin/studies/{name}/design/{slug}"): send(
        "POST", "/admin/studies/ghost/design/study", data={"base": "0" * 64}
    ),
    ("POST", "/admin/studies/{name}/design/{slug}/check"): send(
        "POST", "/admin/studies/ghost/design/study/check", data={"base": "0" * 64}
    ),
    ("GET", "/admin/studies/{name}/phase"): get("/admin/studies/ghost/phase?to=live"),
    ("POST", "/admin/studies/{name}/phase"): send(
        "POST", "/admin/studies/ghost/phase", data={"phase": "live"}
    ),
    ("GET", "/admin/studies/{name}/pilot/reset"): get("/admin/studies/ghost/pilot/reset"),
    ("POST", "/admin/studies/{name}/pilot/reset"): send(
        "POST", "/admin/studies/ghost/pilot/reset", data={}
    ),
    ("POST", "/admin/studies/{name}/consent"): send(
        "POST", "/admin/studies/ghost/consent", data={"confirm": "yes"}
    ),
    ("GET", "/admin/audit"): get("/admin/audit"),
    ("GET", "/admin/audit.csv"): get("/admin/audit.csv?action=none"),
    ("POST", "/stations"): send("POST", "/stations", data={}),
    ("POST", "/stations/{name}/devices"): send("POST", "/stations/ghost/devices", data={}),
    ("GET", "/stations/{name}/devices/{device_id}"): get("/stations/ghost/devices/1"),
    ("POST", "/stations/{name}/kiosk"): send("POST", "/stations/ghost/kiosk", data={}),
    ("POST", "/stations/{name}/archive"): send(
        "POST", "/stations/ghost/archive", data={"archived": "true"}
    ),
    ("POST", "/devices/{device_id}/revoke"): send("POST", "/devices/999999/revoke", data={}),
    ("GET", "/api/v1/station"): get("/api/v1/station"),
    ("GET", "/api/v1/station/room"): get("/api/v1/station/room"),
    ("GET", "/api/v1/station/speech/audio"): get("/api/v1/station/speech/audio?text=x"),
    ("PUT", "/api/v1/station/presence"): send("PUT", "/api/v1/station/presence", json={}),
    ("GET", "/api/v1/station/speech"): get("/api/v1/station/speech"),
    ("PUT", "/api/v1/station/notice"): send("PUT", "/api/v1/station/notice", json={}),
    ("POST", "/api/v1/station/prompts"): send("POST", "/api/v1/station/prompts", json={}),
    ("POST", "/api/v1/station/runs"): send("POST", "/api/v1/station/runs"),
    ("POST", "/api/v1/station/steps/{step_id}/answer"): send(
        "POST", "/api/v1/station/steps/{step}/answer", json=ANSWER
    ),
    ("GET", "/api/v1/tablet"): get("/api/v1/tablet"),
    ("POST", "/api/v1/tablet/consent"): send("POST", "/api/v1/tablet/consent", json={}),
    ("POST", "/api/v1/tablet/language"): send("POST", "/api/v1/tablet/language", json={}),
    ("POST", "/api/v1/tablet/questionnaires/{instrument}"): send(
        "POST", "/api/v1/tablet/questionnaires/nope", json={"answers": {}}
    ),
    ("GET", "/tablet"): get("/tablet"),
    ("GET", "/tablet/language"): get("/tablet/language"),
    ("POST", "/tablet/language"): send("POST", "/tablet/language", tablet_form=True),
    ("GET", "/tablet/consent"): get("/tablet/consent"),
    ("POST", "/tablet/consent"): send("POST", "/tablet/consent", tablet_form=True),
    ("GET", "/tablet/q/{instrument}"): get("/tablet/q/nope"),
    ("POST", "/tablet/q/{instrument}"): send("POST", "/tablet/q/nope", tablet_form=True),
    ("GET", "/tablet/q/{instrument}/{session}"): get("/tablet/q/nope/1"),
    ("POST", "/tablet/q/{instrument}/{session}"): send(
        "POST", "/tablet/q/nope/1", tablet_form=True
    ),
    ("GET", "/tablet/wait"): get("/tablet/wait"),
    ("GET", "/tablet/done"): get("/tablet/done"),
    ("GET", "/tablet/withdrawn"): get("/tablet/withdrawn"),
    ("GET", "/tablet/left"): get("/tablet/left"),
    ("GET", "/join/{study}"): get("/join/rt"),
    ("POST", "/join/{study}"): send("POST", "/join/rt", data={"query": "PROLIFIC_PID=probe"}),
    ("GET", "/online"): get("/online"),
    ("POST", "/online/start"): send("POST", "/online/start"),
    ("POST", "/online/away"): send("POST", "/online/away", data={"seconds": "2.5"}),
    ("GET", "/tablet/events"): stream("/tablet/events"),
}
OWNERSHIP_CHECKED = {("POST", "/api/v1/station/steps/{step_id}/answer")}
"""Routes that refuse another station's robot with 404 (the step is not its to see)."""


def refused(route: tuple[str, str], response: Any) -> bool:
    """Whether the response is a refusal of the caller (not of the request's content).

    A browser page refuses an anonymous caller with a redirect to ``/login?next=…``; signing out
    succeeds with a plain redirect to ``/login``, which is therefore not a refusal.
    """
    if response.status_code in (401, 403):
        return True
    if response.status_code == 303 and response.headers["location"].startswith("/login?next="):
        return True
    return route in OWNERSHIP_CHECKED and response.status_code == 404


def test_every_route_has_a_policy_and_a_probe(app: FastAPI) -> None:
    routes = app_routes(app)
    assert routes - set(POLICY) == set(), "routes without a policy in app/access.py"
    assert set(POLICY) - routes == set(), "policies of routes that no longer exist"
    assert set(PROBES) | set(SOCKETS) == set(POLICY)


def _cells() -> Iterator[tuple[tuple[str, str], Principal]]:
    for route in sorted(PROBES):
        for principal in Principal:
            yield route, principal


def test_every_cell(world: World) -> None:
    wrong = []
    for route, principal in _cells():
        client = client_for(world, principal)
        response = PROBES[route](client, world, principal)
        allowed = principal in POLICY[route]
        if allowed == refused(route, response):
            wrong.append(
                f"{route[0]} {route[1]} as {principal}: {response.status_code} "
                f"(policy: {'allow' if allowed else 'deny'})"
            )
    assert wrong == [], "\n".join(wrong)


PREVIEW_SOCKET = ("WS", "/studies/{name}/preview/room/{language}/api/ws")
SOCKETS = [("WS", "/api/v1/station/ws"), ("WS", "/api/v1/station/audio"), PREVIEW_SOCKET]


def test_the_room_preview_socket_admits_signed_in_staff_only(world: World) -> None:
    for principal in Principal:
        client = client_for(world, principal)
        allowed = principal in POLICY[PREVIEW_SOCKET]
        with client.websocket_connect("/studies/rt/preview/room/en/api/ws") as ws:
            ws.send_json({"type": "auth", "key": "anything"})  # the room client's first words
            if allowed:
                assert ws.receive_json()["type"] == "hello"
            else:
                with pytest.raises(WebSocketDisconnect) as closed:
                    ws.receive_json()
                assert closed.value.code == 4401


@pytest.mark.parametrize("socket", SOCKETS[:2], ids=["station", "audio"])
def test_the_station_sockets_admit_devices_only(world: World, socket: tuple[str, str]) -> None:
    for principal in Principal:
        client = client_for(world, principal)
        allowed = principal in POLICY[socket]
        with client.websocket_connect(socket[1]) as ws:
            if allowed:
                assert ws.receive_json()["type"] == "hello"
            else:  # a browser's cookie is no key: its first request is refused at once
                ws.send_json({"id": 1, "type": "state"})
                with pytest.raises(WebSocketDisconnect) as closed:
                    ws.receive_json()
                assert closed.value.code == 4401
