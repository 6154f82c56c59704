"""Server-rendered pages: content, htmx fragments, forms, confirmations and headers."""

from __future__ import annotations

import html
import json
import re
import threading
import time
from collections.abc import Callable

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from httpx import Response
from sqlalchemy import select

from app.db import Database
from app.events import EventHub
from app.inputs import STUDY_NAME
from app.protocol import default_protocol, shipped_protocol, shipped_protocol_files
from app.services import studies
from app.services.audit import Actor
from app.services.sessions import stations
from app.services.topics import station_topic_of, study_topic
from app.tables import AuditEvent, Role
from tests.conftest import UserClientFactory, protocol_text, sqlite_only


def test_empty_state_says_what_to_do(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    page = admin.get("/").text
    assert "No study yet." in page and "Create one from a protocol file" in page
    experimenter = user_client(Role.EXPERIMENTER)
    assert "Ask an admin to create one." in experimenter.get("/").text


def test_study_list_and_page(user_client: UserClientFactory, study_name: str) -> None:
    client = user_client(Role.EXPERIMENTER)
    listing = client.get("/").text
    assert 'href="/studies/default"' in listing
    page = client.get("/studies/default").text
    assert "Nobody is enrolled yet." in page
    assert "Enrol and randomise" in page
    assert "permuted blocks of 2 or 4" in page


def test_enrol_form_full_page_and_htmx_fragment(
    user_client: UserClientFactory, study_name: str
) -> None:
    client = user_client(Role.EXPERIMENTER)
    response = client.post("/studies/default/participants", data={"code": "K1"})
    assert response.status_code == 200
    assert "Enrolled K1: allocated to C" in response.text  # the notice, shown once
    assert "Enrolled K1" not in client.get("/studies/default").text
    duplicate = client.post(
        "/studies/default/participants", data={"code": "K1"}, headers={"HX-Request": "true"}
    )
    assert duplicate.status_code == 409
    assert duplicate.headers["vary"] == "HX-Request"
    assert duplicate.text.lstrip().startswith('<section id="participants"')
    assert "already used" in duplicate.text
    assert "<html" not in duplicate.text


def test_withdraw_asks_for_confirmation(user_client: UserClientFactory, study_name: str) -> None:
    client = user_client(Role.EXPERIMENTER)
    client.post("/studies/default/participants", data={"code": "W1"})
    confirm = client.get("/studies/default/participants/W1/withdraw")
    assert "Withdraw W1?" in confirm.text and "cannot be undone" in confirm.text
    done = client.post("/studies/default/participants/W1/withdraw", data={"reason": "tired"})
    assert "Withdrew W1." in done.text
    assert 'badge withdrawn">withdrawn' in done.text
    again = client.post("/studies/default/participants/W1/withdraw", data={})
    assert again.status_code == 409
    assert "already withdrawn" in again.text


def test_admin_manages_users(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    form = admin.get("/admin/users").text  # a new account is an experimenter unless chosen
    assert '<option value="experimenter" selected>' in form
    assert '<option value="admin" selected>' not in form
    created = admin.post(
        "/admin/users", data={"username": "Ada", "role": "analyst", "password": "long password 1"}
    )
    assert "Created ada." in created.text
    weak = admin.post("/admin/users", data={"username": "bob", "role": "analyst", "password": "x"})
    assert weak.status_code == 422
    assert "at least 10 characters" in weak.text


def test_admin_uploads_a_protocol(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    bad = protocol_text(**{"block_sizes = [2, 4]": "block_sizes = [3]", "sessions =": "sesions ="})
    refused = admin.post(
        "/admin/studies",
        data={"name": "lab"},
        files={"protocol": ("lab.toml", bad.encode(), "application/toml")},
    )
    assert refused.status_code == 422
    assert "lab.toml: allocation.block_sizes[0]: block size 3" in refused.text
    assert "lab.toml: schedule.sesions: Extra inputs" in refused.text  # both kinds at once
    accepted = admin.post(
        "/admin/studies",
        data={"name": "lab"},
        files={"protocol": ("lab.toml", default_protocol().source_text.encode(), "text/plain")},
    )
    assert accepted.status_code == 200
    assert "Study created." in accepted.text
    closed = admin.post("/admin/studies/lab/status", data={"status": "closed"})
    assert "Study is now closed." in closed.text and "Reopen enrolment" in closed.text


def test_a_study_starts_from_a_shipped_protocol_or_a_copy_of_a_studys(
    user_client: UserClientFactory, database: Database
) -> None:
    """Issue 50 item 1: no TOML file needed to start; each start is audited."""
    admin = user_client(Role.ADMIN)
    form = admin.get("/admin/studies/new").text
    for file in shipped_protocol_files():
        loaded = shipped_protocol(file)
        assert f'value="shipped:{file}"' in form
        assert html.escape(loaded.protocol.study.title) in form
    assert "In English and Svenska" in form  # the two-language one
    assert 'value="shipped:fast_adaptation_trust.toml" checked' in form  # the default

    swedish = "fast_adaptation_trust_sv.toml"
    made = admin.post(
        "/admin/studies", data={"name": "wave-1", "start": f"shipped:{swedish}", "title": "W1"}
    )
    assert made.status_code == 200 and "Study created." in made.text
    copied = admin.post(
        "/admin/studies", data={"name": "wave-2", "start": "study", "from_study": "wave-1"}
    )
    assert copied.status_code == 200 and "Study created." in copied.text
    with database.read_session() as db:
        first, second = (studies.get_study(db, name) for name in ("wave-1", "wave-2"))
        assert first.protocol_source == shipped_protocol(swedish).source_text  # byte for byte
        assert second.protocol_source == first.protocol_source
        assert second.protocol_sha256 == first.protocol_sha256
        assert second.allocation_seed != first.allocation_seed  # a sequence of its own
        started = [
            e.details["started_from"]
            for e in db.scalars(select(AuditEvent).where(AuditEvent.action == "study.created"))
            if "started_from" in e.details
        ]
    assert started == [f"shipped {swedish}", "study wave-1"]

    for data, said in [
        ({"start": "study"}, "choose the study whose protocol the new one copies"),
        ({"start": "study", "from_study": "ghost"}, "no study named"),
        ({"start": "shipped:../../etc/passwd"}, "trustlab ships no protocol of that name"),
        ({"start": "file"}, "choose a protocol file to upload"),
        ({"start": "elsewhere"}, "choose what the study starts from"),
    ]:
        refused = admin.post("/admin/studies", data={"name": "wave-3", **data})
        assert refused.status_code == 422, data
        assert said in html.unescape(refused.text), (data, refused.text)
        assert 'value="wave-3"' in refused.text  # what was typed stays
    both = admin.post(
        "/admin/studies",
        data={"name": "wave-3", "start": f"shipped:{swedish}"},
        files={"protocol": ("mine.toml", b"[study]", "text/plain")},
    )
    assert both.status_code == 422 and "a protocol file was chosen" in both.text
    with database.read_session() as db:
        assert "wave-3" not in [study.name for study in studies.list_studies(db)]
    downloaded = admin.get("/studies/wave-2/protocol.toml")
    assert downloaded.status_code == 200
    assert downloaded.text == shipped_protocol(swedish).source_text  # byte for byte
    assert downloaded.headers["content-disposition"] == (
        'attachment; filename="wave-2-protocol.toml"'
    )
    # Admins download it from the designer; analysts from the study's page.
    assert 'href="/admin/studies/wave-2/design/study"' in admin.get("/studies/wave-2").text
    designer = admin.get("/admin/studies/wave-2/design/study").text
    assert 'href="/studies/wave-2/protocol.toml"' in designer
    experimenter = user_client(Role.EXPERIMENTER, "ada")
    assert experimenter.get("/studies/wave-2/protocol.toml").status_code == 403
    assert "protocol.toml" not in experimenter.get("/studies/wave-2").text
    analyst = user_client(Role.ANALYST, "bea")
    assert 'href="/studies/wave-2/protocol.toml"' in analyst.get("/studies/wave-2").text


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # a form, not storage
def test_the_new_study_form_says_the_name_rule(user_client: UserClientFactory) -> None:
    """The rule is said beside the field, not left to the browser's "match the requested format"
    (issue 35): the server's own words, so the two cannot drift apart."""
    form = user_client(Role.ADMIN).get("/admin/studies/new").text
    field = form.split('<input name="name"', 1)[1].split(">", 1)[0]
    assert 'aria-describedby="study-name-rule"' in field
    rule = STUDY_NAME.rule[0].upper() + STUDY_NAME.rule[1:]
    said = form.split('id="study-name-rule">', 1)[1].split("<", 1)[0]
    assert html.unescape(said) == f"{rule}."
    title = field.split('title="', 1)[1].split('"', 1)[0]
    assert html.unescape(title) == f"{rule}."  # the browser's own message quotes it too


def test_unknown_pages_and_studies_render_html_errors(user_client: UserClientFactory) -> None:
    client = user_client(Role.ANALYST)
    missing = client.get("/studies/ghost", headers={"accept": "text/html"})
    assert missing.status_code == 404
    assert "no study named &#39;ghost&#39;" in missing.text
    nowhere = client.get("/no/such/page", headers={"accept": "text/html"})
    assert nowhere.status_code == 404 and "Not found" in nowhere.text


@sqlite_only("headers, not storage")
def test_security_headers(client: TestClient) -> None:
    headers = client.get("/login").headers
    policy = headers["content-security-policy"]
    assert "script-src 'self';" in policy and "frame-ancestors 'none'" in policy
    assert "unsafe-inline" not in policy.split("script-src")[1].split(";")[0]
    assert headers["x-content-type-options"] == "nosniff"
    assert headers["referrer-policy"] == "same-origin"
    assert headers["x-frame-options"] == "DENY"
    body = client.get("/login").text
    assert "<script>" not in body  # every script is an external file (the CSP forbids inline)


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)
def test_a_new_device_key_has_a_page_of_its_own_and_a_reload_issues_none(
    user_client: UserClientFactory, study_name: str
) -> None:
    """The key shows once on a GET page (no "Method Not Allowed" on reload, no second key),
    with what to do next: open the station's room and paste it."""
    admin = user_client(Role.ADMIN)
    assert admin.post("/stations", data={"name": "lab-1"}).status_code == 200
    issued = admin.post("/stations/lab-1/devices", data={"label": "room"})
    assert issued.status_code == 200
    assert issued.history and issued.history[0].status_code == 303
    assert str(issued.url).startswith("http://testserver/stations/lab-1/devices/")
    key = re.search(r"tlk_[\w-]+", issued.text)
    assert key is not None, issued.text
    assert "http://testserver/stations/lab-1/room" in issued.text
    assert issued.headers["cache-control"] == "no-store"
    with_key = {"Authorization": f"Bearer {key[0]}"}
    assert admin.get("/api/v1/station", headers=with_key).status_code != 401  # a live key
    again = admin.get(str(issued.url))  # a reload: the key is not shown again, none is issued
    assert again.status_code == 200
    assert key[0] not in again.text and "was shown once" in again.text
    listed = admin.get("/api/v1/stations").json()
    assert [len(s["devices"]) for s in listed if s["name"] == "lab-1"] == [1]
    assert admin.get("/stations/lab-1/devices/999999").status_code == 404


WIDE_TEXT = "Schlüssel … 机器人 ✓"
"""Text outside Latin-1 (a cookie header's alphabet): device labels and titles may hold any."""


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # cookies, not storage
def test_notices_carry_any_text(user_client: UserClientFactory, study_name: str) -> None:
    admin = user_client(Role.ADMIN)
    assert admin.post("/stations", data={"name": "lab-1"}).status_code == 200
    issued = admin.post("/stations/lab-1/devices", data={"label": WIDE_TEXT})
    assert issued.status_code == 200
    device_id = str(issued.url).rsplit("/", 1)[1]
    revoked = admin.post(f"/devices/{device_id}/revoke")
    assert revoked.status_code == 200
    assert f"Revoked {WIDE_TEXT} (" in revoked.text and "…) at lab-1." in revoked.text
    source = default_protocol().source_text.encode()
    admin.post(
        "/admin/studies",
        data={"name": "wide", "title": WIDE_TEXT},
        files={"protocol": ("p.toml", source, "text/plain")},
    )
    archived = admin.post("/admin/studies/wide/archive", data={"archived": "true"})
    assert archived.status_code == 200
    assert f"Archived {WIDE_TEXT}: it is hidden" in archived.text


def _stream_path(page: str, attribute: str) -> str:
    found = re.search(rf'{attribute}="([^"]*/events\?since=[0-9.]+)"', page)
    assert found, f"no {attribute} with a since"
    return html.unescape(found.group(1))


def _first_types(client: TestClient, path: str, *, then: Callable[[], None]) -> list[str]:
    """What the first message of the stream at ``path`` is about; ``then`` is called once it is
    open, to make a change of its own (so the stream has something to say either way)."""
    with client.stream("GET", path) as stream:
        lines = stream.iter_lines()
        assert next(lines) == "retry: 3000"  # subscribed
        then()
        data = next(line for line in lines if line.startswith("data:"))
        types: list[str] = json.loads(data.removeprefix("data:"))["types"]
        # On PostgreSQL the event listener's start (just before the pages) says "resync".
        return [kind for kind in types if kind != "resync"]


def _wait_until_heard(hub: EventHub, topic: str, kind: str) -> None:
    """Wait (bounded, not timed) until ``hub`` has received an event ``kind`` on ``topic``."""
    for _ in range(1500):
        if any(event.type == kind for event in hub.since([topic], time.time() - 30) or []):
            return
        threading.Event().wait(0.02)
    raise AssertionError(f"the hub never heard {kind} on {topic}")


def test_a_live_page_hears_a_change_made_between_its_rendering_and_its_stream(
    user_client: UserClientFactory, study_name: str, database: Database, app: FastAPI
) -> None:
    """Its stream opens only after the page is drawn: a change that came in between would
    otherwise leave the page stale until the next one."""
    client = user_client(Role.EXPERIMENTER)
    # As if the server had run for a while: a hub started within the pages' clock margin of
    # their reading cannot tell what came since, and sends "unknown" (a refresh all the same).
    app.state.database.hub.heard_from -= 60
    with database.write_session() as db:
        lab_topic = station_topic_of(
            stations.create_station(db, name="lab-1", actor=Actor.system("test")).id
        )
        study_id = studies.get_study(db, study_name).id
    overview = _stream_path(client.get("/studies/default").text, "sse-connect")
    dashboard = _stream_path(client.get("/studies/default/dashboard").text, "data-events")
    console = _stream_path(client.get("/stations/lab-1").text, "sse-connect")

    def post(path: str, **form: str) -> Callable[[], None]:
        return lambda: assert_ok(client.post(path, data=form))

    def assert_ok(response: Response) -> None:
        assert response.status_code == 200, response.text

    hub = app.state.database.hub
    post("/studies/default/participants", code="K1")()  # after the pages, before their streams
    seat = post("/stations/lab-1/assign", study="default", code="K1")
    unseat = post("/stations/lab-1/unassign")
    # PostgreSQL hands each change to the hub through LISTEN, after its commit: a stream must
    # open once the hub has it, or it comes live instead of in the stream's first message.
    _wait_until_heard(hub, study_topic(study_id), "participant_enrolled")
    assert _first_types(client, overview, then=seat) == ["participant_enrolled"]
    assert "participant_enrolled" in _first_types(client, dashboard, then=unseat)
    _wait_until_heard(hub, lab_topic, "participant_unassigned")
    # The console was drawn before the seating and the unseating, which it is told of first.
    missed = ["participant_assigned", "participant_unassigned"]
    assert _first_types(client, console, then=seat) == missed
    assert client.get("/studies/default/events?since=nan").status_code == 422
