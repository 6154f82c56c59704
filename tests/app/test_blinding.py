"""Blinding holds: while a blinded study is sealed, nothing staff can fetch carries the learners'
probabilities, confidence levels or reply history (the robot still gets them), and unblinding is
an admin's audited, one-way act (app/services/blinding.py)."""

from __future__ import annotations

import asyncio
import json
import re
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.access import POLICY, Principal
from app.db import Database
from app.events import Event, EventHub
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.privacy.sites import Scope
from app.tables import Answer, AuditEvent, Prompt, Role, StudyStatus
from app.web.streams import event_stream
from tests.conftest import (
    BLINDED,
    EXP3_ONLY,
    Lab,
    UserClientFactory,
    client_of,
    create_blinded_study,
    protocol_text,
)

LEARNER_KEYS = frozenset({"probabilities", "probability", "confidence", "confidence_level"})
LEVELS = ("low", "medium_low", "medium", "high")
REPLIES = (
    "I do not believe it but fine.",
    "Is that really so? I am not sure.",
    "I understand now.",
    "Awesome, I knew you would say so.",
)


@pytest.fixture
def blind(
    app: FastAPI, client: TestClient, database: Database, user_client: UserClientFactory
) -> Lab:
    """A blinded study 'blind' (Exp3 in both conditions: fast) with one participant seated at
    'lab-b' in session 1: several answers learned and a prompt open, so that the learners'
    probabilities are no longer uniform and the console has a last step and bars to show."""
    create_blinded_study(database, "blind")
    admin = user_client(Role.ADMIN)
    assert admin.post("/api/v1/stations", json={"name": "lab-b"}).status_code == 201
    key = admin.post("/api/v1/stations/lab-b/devices", json={"label": "pepper"}).json()["key"]
    robot = client_of(client, headers={"Authorization": f"Bearer {key}"})
    lab = Lab(app, database, "blind", "lab-b", key, user_client(Role.EXPERIMENTER), robot, {})
    lab.enrol_and_assign("P001")
    lab.start_session()  # the familiarisation run
    lab.run_session()
    lab.start_session()
    for category in ("conation", "affection"):
        step = lab.prompt(category)
        lab.answer(step["step_id"], "yes")
    lab.prompt("cognition")  # open: the console waits for its answer
    return lab


def _stored_probabilities(database: Database) -> set[float]:
    """Every learner figure the database holds, except the uniform start (1/K is no secret)."""
    values: set[float] = set()
    with database.read_session() as db:
        for probabilities in db.scalars(select(Prompt.probabilities)):
            values.update(probabilities)
        for answer in db.scalars(select(Answer)):
            values.update([answer.probability, *answer.probabilities_after])
    return {v for v in values if abs(v - 0.25) > 1e-9}


def _json_leaks(value: Any, where: str = "") -> list[str]:
    """Learner keys with a value, anywhere in a JSON document."""
    found = []
    if isinstance(value, dict):
        for key, item in value.items():
            # a "confidence" of 0.95 is a figure's interval, not a reply level
            interval = key == "confidence" and isinstance(item, float)
            if key in LEARNER_KEYS and item is not None and not interval:
                found.append(f"{where}.{key}")
            found += _json_leaks(item, f"{where}.{key}")
    elif isinstance(value, list):
        for n, item in enumerate(value):
            found += _json_leaks(item, f"{where}[{n}]")
    return found


def _leaks(
    text: str, probabilities: set[float], *, replies: bool = True, words: bool = True
) -> list[str]:
    """What in a response body gives the learners away: a stored probability (as the pages and
    JSON write them), a learner figure in JSON, and unless told otherwise a reply's words
    (``replies``) and a confidence level or probability meter as the pages write them
    (``words``: off for the protocol, which defines the levels, and for the report, whose
    embedded Plotly code has such words of its own)."""
    found = []
    try:
        document = json.loads(text)
    except ValueError:
        document = None
    if document is not None:
        found += _json_leaks(document)
        if isinstance(document, dict) and document.get("adaptation") is not None:
            found.append("adaptation curves")
    for value in probabilities:
        for written in {repr(value), f"{value:.3f}", f"{value:.2f}"}:
            if re.search(rf"(?<![\d.]){re.escape(written)}(?!\d)", text):
                found.append(f"probability {written}")
    for level in LEVELS if words else ():
        if f"({level.replace('_', ' ')}," in text or f'"{level}"' in text:
            found.append(f"level {level}")
    if words and ('role="meter"' in text or "p = " in text):
        found.append("a probability meter")
    if replies:
        found += [f"reply {reply!r}" for reply in REPLIES if reply in text]
    return found


def _experimenter_pages() -> list[str]:
    """Every page and read the access policy lets an experimenter fetch (a new route is swept
    without changing this test), with the blinded study's names filled in; event streams are
    checked below (they carry event types only)."""
    paths = []
    for (method, path), allowed in sorted(POLICY.items()):
        if method != "GET" or Principal.EXPERIMENTER not in allowed:
            continue
        if path.endswith(("/events", "/speech/audio")) or "{token}" in path:
            continue  # streams carry types only (below); tablet links need a participant's
            # token; a preview's spoken line is a protocol line (its text is required)
        if path in {"/static", "/api/v1/docs", "/api/v1/openapi.json"}:
            continue
        if path.startswith("/join/"):
            continue  # an online study's public link: a participant's page, of no study here
        name = "lab-b" if "station" in path else "blind"
        filled = path.replace("{name}", name).replace("{code}", "P001")
        filled = filled.replace("{language}/{number}", "en/1")  # a preview page
        filled = filled.replace("{slug}", "study")  # a designer section
        filled = filled.replace("/preview/room/{language}", "/preview/room/en")
        paths.append(filled.replace("{language}", "sv"))
    return paths


def test_no_page_fragment_or_response_for_an_experimenter_carries_the_learners(
    blind: Lab,
) -> None:
    secret = _stored_probabilities(blind.database)
    assert secret, "the fixture should have moved the learners off the uniform start"
    experimenter = blind.experimenter
    wrong: dict[str, list[str]] = {}

    def check(label: str, response: Any, *, replies: bool = True, words: bool = True) -> None:
        assert response.status_code < 400, f"{label}: {response.status_code} {response.text}"
        found = _leaks(response.text, secret, replies=replies, words=words)
        if found:
            wrong[label] = found

    pages = _experimenter_pages()
    assert "/stations/lab-b" in pages and "/studies/blind/participants/P001" in pages
    for path in pages:
        # the console shows the reply the robot has just said aloud (a wizard must be able to
        # voice it); every other page shows no reply at all; the protocol defines the levels
        protocol = path.endswith("/protocol")
        check(
            path,
            experimenter.get(path),
            replies=path != "/stations/lab-b" and not protocol,
            words=not protocol,
        )

    htmx = {"HX-Request": "true"}
    check(
        "console: Wizard-of-Oz answer fragment",
        experimenter.post(
            "/stations/lab-b/woz/answer",
            data={"step_id": _open_step(blind), "answer": "no", "idempotency_key": "woz-1"},
            headers=htmx,
        ),
        replies=False,
    )
    check(
        "console: Wizard-of-Oz prompt fragment",
        experimenter.post("/stations/lab-b/woz/prompt", data={"category": "conation"}),
        replies=False,
    )
    api = "/api/v1/stations/lab-b"
    check("REST: state", experimenter.get(f"{api}/state"))
    prompt = experimenter.post(f"{api}/prompts", json={"category": "conation"})
    check("REST: prompt", prompt)
    answered = experimenter.post(
        f"{api}/steps/{prompt.json()['step_id']}/answer",
        json={"answer": "yes", "idempotency_key": "woz-2"},
    )
    check("REST: answer", answered, replies=False)
    assert answered.json()["reply"] in REPLIES  # the words the robot says aloud, nothing more
    check("REST: end the run", experimenter.post(f"{api}/runs/current/end"))
    check("REST: next run", experimenter.post(f"{api}/runs"))
    check("REST: end the session", experimenter.post(f"{api}/sessions/current/end"))
    assert wrong == {}, json.dumps(wrong, indent=1)


def _open_step(lab: Lab) -> int:
    expected = lab.robot.get("/api/v1/station").json()["expected"]
    assert expected["action"] == "answer", expected
    return int(expected["step_id"])


def test_the_robot_still_gets_everything_it_needs(blind: Lab) -> None:
    reply = blind.answer(_open_step(blind), "yes")
    assert len(reply["probabilities"]) == 4 and reply["confidence"] in LEVELS
    assert 0 <= reply["probability"] <= 1 and reply["reply"] in REPLIES
    assert all(
        p["probabilities"] for p in blind.robot.get("/api/v1/station").json()["open_prompts"]
    )


def test_a_pages_event_stream_carries_only_the_types_of_change() -> None:
    async def first_message() -> str:
        hub = EventHub()
        body = event_stream(hub, ["study:1"], scope=Scope.every_site()).body_iterator
        await anext(body)  # the retry hint: subscribed
        hub.deliver([Event(topic="study:1", type="answer", data={"probabilities": [0.7, 0.1]})])
        message = str(await asyncio.wait_for(anext(body), 5))
        await body.aclose()  # type: ignore[attr-defined]
        return message

    assert asyncio.run(first_message()) == 'event: changed\ndata: {"types": ["answer"]}\n\n'


def test_analysts_see_no_learners_until_the_study_is_unblinded(
    blind: Lab, user_client: UserClientFactory
) -> None:
    secret = _stored_probabilities(blind.database)
    analyst = user_client(Role.ANALYST)
    page = analyst.get("/studies/blind/analysis")
    assert page.status_code == 200
    assert "No adaptation curves: this study is blinded" in page.text
    assert 'data-figure="figure-adaptation"' not in page.text
    assert 'href="/studies/blind/exports/steps-csv"' not in page.text
    refused = analyst.get("/studies/blind/exports/steps-csv")
    assert refused.status_code == 409 and "until an admin unblinds it" in refused.text
    assert 'href="/studies/blind/exports/adaptation-csv"' not in page.text
    joined = analyst.get("/studies/blind/exports/adaptation-csv")
    assert joined.status_code == 409 and "until an admin unblinds it" in joined.text
    mixed = analyst.get("/studies/blind/exports/mixed-json")
    assert mixed.status_code == 200 and "this study is blinded" in mixed.text
    assert _leaks(mixed.text, secret, replies=False, words=False) == []
    report = analyst.get("/studies/blind/exports/html")
    assert report.status_code == 200 and "this study is blinded" in report.text
    assert _leaks(report.text, secret, replies=False, words=False) == []
    assert not any(reply in report.text for reply in REPLIES)
    for path in ("/studies/blind/dashboard.json", "/studies/blind/participants/P001"):
        assert _leaks(analyst.get(path).text, secret) == [], path
    # the analyst still sees the real conditions (they analyse them), only not the learners
    assert {p["condition"] for p in analyst.get("/api/v1/studies/blind/participants").json()} <= {
        "C1",
        "C2",
    }


def test_unblinding_is_an_admins_audited_one_way_act(
    blind: Lab, database: Database, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN, "boss")
    experimenter, analyst = blind.experimenter, user_client(Role.ANALYST)
    assert experimenter.post("/api/v1/studies/blind/unblind").status_code == 403
    assert analyst.post("/api/v1/studies/blind/unblind").status_code == 403
    still_open = admin.post("/api/v1/studies/blind/unblind")
    assert still_open.status_code == 409 and "close study 'blind'" in still_open.json()["detail"]
    assert admin.get("/api/v1/studies/blind").json()["unblinded_at"] is None

    closed = admin.post("/api/v1/studies/blind/status", json={"status": "closed"})
    assert closed.status_code == 200
    done = admin.post("/api/v1/studies/blind/unblind")
    assert done.status_code == 200 and done.json()["unblinded_at"] is not None
    again = admin.post("/api/v1/studies/blind/unblind")
    assert again.status_code == 409 and "was unblinded on" in again.json()["detail"]
    reopen = admin.post("/api/v1/studies/blind/status", json={"status": "open"})
    assert reopen.status_code == 409 and "has been unblinded" in reopen.json()["detail"]
    with database.read_session() as db:
        events = db.scalars(select(AuditEvent).where(AuditEvent.action == "study.unblinded")).all()
        labels = studies.get_study(db, "blind").neutral_labels
        assert [(e.actor, e.subject, e.details) for e in events] == [
            ("boss", "blind", {"active_participants": 1, "neutral_labels": labels})
        ]
        assert studies.get_study(db, "blind").status == StudyStatus.CLOSED

    # from now on staff see the learners and the real conditions
    state = experimenter.get("/api/v1/stations/lab-b/state").json()
    assert all(p["probabilities"] for p in state["open_prompts"])
    console = experimenter.get("/stations/lab-b").text
    assert 'role="meter"' in console
    groups = {c["label"] for c in experimenter.get("/api/v1/studies/blind").json()["enrolment"]}
    assert groups == {"C1", "C2"}
    assert experimenter.get("/studies/blind/dashboard.json").json()["adaptation"] is not None
    assert analyst.get("/studies/blind/exports/steps-csv").status_code == 200
    assert "No adaptation curves" not in analyst.get("/studies/blind/analysis").text


def test_each_blinded_study_draws_which_condition_gets_which_label() -> None:
    """The protocol (which experimenters read) gives the set of labels, never the assignment
    (issue 35, item 10: C1 was always Group A)."""
    protocol = parse_protocol(protocol_text(**EXP3_ONLY, **BLINDED)).protocol
    draws = {tuple(studies.draw_neutral_labels(protocol).items()) for _ in range(64)}  # type: ignore[union-attr]
    # both assignments come up (that one never would has odds 2 × 2⁻⁶⁴)
    assert draws == {(("C1", "Group A"), ("C2", "Group B")), (("C1", "Group B"), ("C2", "Group A"))}
    assert studies.draw_neutral_labels(parse_protocol(protocol_text()).protocol) is None


@pytest.mark.parametrize("engine_name", ["sqlite"])  # what is shown does not depend on the engine
def test_staff_see_the_studys_own_labels_and_the_assignment_only_once_unblinded(
    database: Database, user_client: UserClientFactory
) -> None:
    with database.writing() as db:
        study = studies.create_study(
            db,
            name="drawn",
            loaded=parse_protocol(protocol_text(**EXP3_ONLY, **BLINDED)),
            actor=Actor.system(),
        )
        assert sorted(study.neutral_labels.values()) == ["Group A", "Group B"]  # type: ignore[union-attr]
        study.neutral_labels = {"C1": "Group B", "C2": "Group A"}  # against the protocol's order
        db.commit()
    experimenter, analyst = user_client(Role.EXPERIMENTER), user_client(Role.ANALYST)
    admin = user_client(Role.ADMIN)
    for _ in range(2):
        assert experimenter.post("/api/v1/studies/drawn/participants", json={}).status_code == 201
    truth = {
        p["code"]: p["condition"] for p in analyst.get("/api/v1/studies/drawn/participants").json()
    }
    shown = {
        p["code"]: p["condition"]
        for p in experimenter.get("/api/v1/studies/drawn/participants").json()
    }
    assert shown == {code: {"C1": "Group B", "C2": "Group A"}[c] for code, c in truth.items()}
    page = experimenter.get("/studies/drawn/participants/P001").text
    assert shown["P001"] in page
    summary = experimenter.get("/api/v1/studies/drawn").json()["enrolment"]
    assert [group["label"] for group in summary] == ["Group A", "Group B"]  # by label
    protocol = experimenter.get("/api/v1/studies/drawn/protocol").json()
    assert [c["id"] for c in protocol["conditions"]] == ["Group A", "Group B"]
    assert "Group A; Group B" in experimenter.get("/studies/drawn").text
    assert "while blinded" not in analyst.get("/studies/drawn").text  # sealed: not yet

    admin.post("/api/v1/studies/drawn/status", json={"status": "closed"})
    assert admin.post("/api/v1/studies/drawn/unblind").status_code == 200
    page = experimenter.get("/studies/drawn").text
    assert "(was Group B while blinded)" in page and "(was Group A while blinded)" in page


def test_the_unblind_page_says_what_it_does_and_refuses_clearly(
    blind: Lab, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    study_page = admin.get("/studies/blind").text
    assert 'href="/admin/studies/blind/unblind"' in study_page
    form = admin.get("/admin/studies/blind/unblind")
    assert form.status_code == 200
    assert "This cannot be undone" in form.text and "close it first" in form.text
    refused = admin.post("/admin/studies/blind/unblind", data={})
    assert refused.status_code == 409 and "close study" in refused.text
    admin.post("/admin/studies/blind/status", data={"status": "closed"})
    warned = admin.get("/admin/studies/blind/unblind").text
    assert "1 participant has" in warned and "not finished" in warned
    done = admin.post("/admin/studies/blind/unblind", data={}, follow_redirects=False)
    assert done.status_code == 303 and done.headers["location"] == "/studies/blind"
    page = admin.get("/studies/blind").text
    assert ">unblinded<" in page and 'href="/admin/studies/blind/unblind"' not in page
    assert "was unblinded on" in admin.get("/admin/studies/blind/unblind").text


def test_a_study_that_is_not_blinded_has_nothing_to_unblind(
    lab: Lab, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    lab.enrol_and_assign()
    lab.start_session()
    admin.post("/api/v1/studies/rt/status", json={"status": "closed"})
    refused = admin.post("/api/v1/studies/rt/unblind")
    assert refused.status_code == 409 and "is not blinded" in refused.json()["detail"]
    step = lab.experimenter.post("/api/v1/stations/lab-1/prompts", json={"category": "conation"})
    assert step.json()["probabilities"] == [0.25] * 4  # not blinded: shown as before


def test_the_command_line_unblinds_after_asking(blind: Lab, database_url: str) -> None:
    from tests.app.test_cli import run

    code, _, err = run(database_url, "study", "unblind", "blind")
    assert code != 0 and "cannot be undone: add --yes" in err
    code, _, err = run(database_url, "study", "unblind", "blind", "--yes")
    assert code != 0 and "close study 'blind' for enrolment first" in err
    with blind.database.writing() as db:
        studies.set_study_status(db, name="blind", status=StudyStatus.CLOSED, actor=Actor.system())
    code, out, _ = run(database_url, "study", "unblind", "blind", "--yes")
    assert code == 0 and out.startswith("unblinded study 'blind' at ")
    assert out.splitlines()[1] in {
        "while blinded: C1 was Group A, C2 was Group B",
        "while blinded: C1 was Group B, C2 was Group A",
    }
    with blind.database.read_session() as db:
        event = db.scalars(select(AuditEvent).where(AuditEvent.action == "study.unblinded")).one()
        assert event.actor_kind == "cli" and event.subject == "blind"
    state = blind.experimenter.get("/api/v1/stations/lab-b/state").json()
    assert all(p["probabilities"] for p in state["open_prompts"])
