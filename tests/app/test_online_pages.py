"""An online participant's pages (app/online/pages.py), through HTTP: the public link, the
browser check's verdict, the tablet's pages and the room in one browser, the completion
redirect, and a return."""

from __future__ import annotations

import re
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.db import Database
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.tables import OnlineParticipation, OnlineStatus, Participant, StudySession
from tests.app.test_online_join import online_protocol
from tests.conftest import POST_ANSWERS, PRE_STUDY_ANSWERS, TRUST_ANSWERS, client_of, sqlite_only

DESKTOP = {"webgl": "1", "audio": "1", "width": "1366", "height": "768", "keyboard": "1"}
ANSWERS = {**PRE_STUDY_ANSWERS, "trust": TRUST_ANSWERS, "overall": POST_ANSWERS}
SHORT = {"sessions = 4": "sessions = 2", "runs_per_session = 3": "runs_per_session = 1"}


@pytest.fixture
def web_study(database: Database) -> str:
    loaded = parse_protocol(online_protocol(**SHORT))
    with database.writing() as db:
        studies.create_study(db, name="web", loaded=loaded, actor=Actor.system())
    return "web"


def joined(client: TestClient, pid: str, **check: str) -> Any:
    query = f"PROLIFIC_PID={pid}&STUDY_ID=s1&SESSION_ID=x1"
    page = client.get(f"/join/web?{query}")
    assert page.status_code == 200, page.text
    assert 'id="join-form"' in page.text and f'value="{query}"' in page.text.replace("&amp;", "&")
    return client.post(
        "/join/web",
        data={"query": query, "browser": "browser-of-test-1", **DESKTOP, **check},
        follow_redirects=False,
    )


def _answer_tablet_page(tablet: TestClient) -> None:
    page = tablet.get("/api/v1/tablet").json()
    if page["kind"] == "consent":
        response = tablet.post("/api/v1/tablet/consent", json={"accept": True})
    else:
        assert page["kind"] == "questionnaire", page
        key = page["instrument"]["key"]
        body: dict[str, Any] = {"answers": ANSWERS[key]}
        if page.get("session") is not None:
            body["session"] = page["session"]
        response = tablet.post(f"/api/v1/tablet/questionnaires/{key}", json=body)
    assert response.status_code == 200, response.text


def _run_session(robot: TestClient) -> int:
    steps = 0
    expected = robot.get("/api/v1/station").json()["expected"]
    while expected["action"] == "prompt":
        step = robot.post("/api/v1/station/prompts", json={"category": expected["categories"][0]})
        assert step.status_code in (200, 201), step.text
        reply = robot.post(
            f"/api/v1/station/steps/{step.json()['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": f"k{step.json()['step_id']}"},
        )
        assert reply.status_code == 200, reply.text
        expected = reply.json()["expected"]
        steps += 1
    return steps


def test_a_participant_goes_from_the_link_to_the_platform_with_its_code(
    app: FastAPI, client: TestClient, database: Database, web_study: str
) -> None:
    browser = client_of(client)
    response = joined(browser, "PID-WALK")
    assert (response.status_code, response.headers["location"]) == (303, "/online")
    tablet = client_of(client, headers={"Authorization": f"Bearer {browser.cookies['tl_tablet']}"})
    rooms = steps = 0
    for _ in range(40):
        page = browser.get("/online", follow_redirects=False)
        if page.status_code == 303:
            assert page.headers["location"].startswith("/tablet/")
            assert browser.get(page.headers["location"]).status_code == 200  # the page shows
            _answer_tablet_page(tablet)
            continue
        assert page.status_code == 200, page.text
        if 'data-outcome="completed"' in page.text:
            break
        key = re.search(r'data-key="(tlk_[^"]+)"', page.text)
        assert key and 'data-start="/online/start"' in page.text, page.text
        # the tablet's waiting page sends an online participant to the room, not to wait
        wait = browser.get("/tablet/wait", follow_redirects=False)
        assert wait.headers["location"] == "/online"
        assert browser.post("/online/start").status_code == 204
        assert browser.post("/online/start").status_code == 409  # already running
        steps += _run_session(client_of(client, headers={"Authorization": f"Bearer {key[1]}"}))
        rooms += 1
    else:
        pytest.fail("never reached the completion page")
    assert rooms == 3 and steps == 3 * 3  # the practice run and two sessions of one run each
    assert "Your completion code is C1ABC2." in page.text
    link = "https://app.prolific.com/submissions/complete?cc=C1ABC2"
    assert f'content="3;url={link}"' in page.text and f'href="{link}"' in page.text
    with database.read_session() as db:
        row = db.scalar(select(OnlineParticipation))
        assert row is not None and row.status == OnlineStatus.COMPLETED
        assert row.step == "done" and row.finished_at is not None
        sessions = db.scalars(select(StudySession.started_by)).all()
        assert all(by.endswith("(online)") for by in sessions) and len(sessions) == 3
    # the key stops working; a return with the same ID is told it finished, with its code
    robot = client_of(client, headers={"Authorization": f"Bearer {key[1]}"})
    assert robot.get("/api/v1/station").status_code == 401
    again = joined(client_of(client), "PID-WALK")
    assert again.status_code == 200 and "Your completion code is C1ABC2." in again.text


def test_a_reload_or_a_second_tab_continues_where_they_were(
    client: TestClient, database: Database, web_study: str
) -> None:
    first = client_of(client)
    assert joined(first, "PID-BACK").status_code == 303
    consent = first.get("/online", follow_redirects=False).headers["location"]
    other_tab = client_of(client)  # a new browser with the same ID (the cookie gone)
    response = joined(other_tab, "PID-BACK")
    assert (response.status_code, response.headers["location"]) == (303, "/online")
    assert other_tab.get("/online", follow_redirects=False).headers["location"] == consent
    with database.read_session() as db:
        assert len(db.scalars(select(Participant)).all()) == 1


@sqlite_only("the pages' words, not the database's")
def test_a_browser_that_cannot_run_the_room_is_sent_back_politely(
    client: TestClient, web_study: str
) -> None:
    response = joined(client_of(client), "PID-NOGL", webgl="0")
    assert response.status_code == 200
    assert "Sorry, this study cannot run here" in response.text
    assert "It needs 3D graphics (WebGL)" in response.text
    assert 'href="https://app.prolific.com/submissions/complete?cc=SCREENED"' in response.text
    small = joined(client_of(client), "PID-SMALL", width="800")
    assert "It needs a window of at least 1024 × 600 pixels." in small.text


@sqlite_only("the pages' words, not the database's")
def test_pages_without_the_join_say_what_to_do(
    client: TestClient, web_study: str, study_name: str
) -> None:
    nobody = client_of(client)
    refused = nobody.get("/online", follow_redirects=False)
    assert refused.status_code == 401
    assert "recruitment platform" in refused.text
    assert nobody.post("/online/start").status_code == 401
    no_id = nobody.get("/join/web?STUDY_ID=s1")
    assert "This link does not say who you are" in no_id.text and "join-form" not in no_id.text
    assert nobody.get(f"/join/{study_name}?PROLIFIC_PID=x").status_code == 404
    bad = nobody.post("/join/web", data={"query": "PROLIFIC_PID=has spaces", **DESKTOP})
    assert bad.status_code == 422 and "PROLIFIC_PID is missing or malformed" in bad.text


@sqlite_only("which visits write, not the database's")
def test_a_visit_that_changes_nothing_writes_nothing(
    app: FastAPI, client: TestClient, web_study: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    database: Database = app.state.database
    writes = []
    write_session = database.write_session

    def counted() -> Any:
        writes.append(1)
        return write_session()

    monkeypatch.setattr(database, "write_session", counted)
    browser = client_of(client)
    assert joined(browser, "PID-QUIET").status_code == 303
    writes.clear()
    assert browser.get("/online", follow_redirects=False).headers["location"] == "/tablet/consent"
    assert len(writes) == 1  # the first sight of the consent page is noted
    for _ in range(3):  # a reload, and another: the same step, seen just now
        assert browser.get("/online", follow_redirects=False).status_code == 303
    assert len(writes) == 1
    tablet = client_of(client, headers={"Authorization": f"Bearer {browser.cookies['tl_tablet']}"})
    _answer_tablet_page(tablet)  # consent given: the next visit notes the new step
    writes.clear()
    assert browser.get("/online", follow_redirects=False).headers["location"] == (
        "/tablet/q/demographics"
    )
    assert len(writes) == 1
    with database.read_session() as db:
        row = db.scalar(select(OnlineParticipation))
        assert row is not None and row.step == "questionnaire:demographics"
