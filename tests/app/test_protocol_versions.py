"""A draft's protocol edited in the browser (issue 50, item 2): each save a version, checked as
study creation checks; a second editor's stale save refused with what changed, their text kept;
the last change undone; a pilot's or live study's protocol frozen."""

from __future__ import annotations

import html
import re

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.db import Database
from app.protocol import parse_protocol, shipped_protocol, shipped_protocol_files
from app.services import studies
from app.services.audit import Actor
from app.tables import AuditEvent, ProtocolVersion, Role, StudyPhase
from tests.conftest import EXP3_ONLY, UserClientFactory, protocol_text, sqlite_only

NAME = "drafted"


def _draft(database: Database, text: str, name: str = NAME) -> None:
    with database.writing() as db:
        studies.create_study(
            db,
            name=name,
            loaded=parse_protocol(text),
            actor=Actor.system(),
            phase=StudyPhase.DRAFT,
        )


def _textarea(page: str) -> str:
    found = re.search(r'<textarea name="text"[^>]*>(.*?)</textarea>', page, re.S)
    assert found is not None, page
    return html.unescape(found.group(1))


def _base(page: str) -> str:
    found = re.search(r'name="base" value="([0-9a-f]{64})"', page)
    assert found is not None
    return found.group(1)


@pytest.fixture
def admin(user_client: UserClientFactory) -> TestClient:
    return user_client(Role.ADMIN)


@sqlite_only("pages and checks; the version check under a row lock is tested on both engines")
def test_a_draft_is_saved_as_versions_and_the_last_change_undone(
    database: Database, admin: TestClient
) -> None:
    original = protocol_text(**EXP3_ONLY)
    _draft(database, original)
    page = admin.get(f"/admin/studies/{NAME}/protocol")
    assert page.status_code == 200 and _textarea(page.text) == original
    assert "Undo the last change" not in page.text
    edited = original.replace("sessions = 4", "sessions = 3")
    saved = admin.post(
        f"/admin/studies/{NAME}/protocol",
        data={"base": _base(page.text), "text": edited, "reason": "three sessions fit a day"},
    )
    assert saved.status_code == 200 and "Saved as version 2." in saved.text
    assert _textarea(saved.text) == edited
    with database.read_session() as db:
        study = studies.get_study(db, NAME)
        assert studies.protocol_of(study).schedule.sessions == 3
        assert study.protocol_source == edited
        event = db.scalar(select(AuditEvent).where(AuditEvent.action == "study.protocol_saved"))
        assert event is not None and event.details["reason"] == "three sessions fit a day"
        assert event.details["version"] == 2
    undone = admin.post(f"/admin/studies/{NAME}/protocol/undo", data={"base": _base(saved.text)})
    assert "Undone: saved as version 3." in undone.text
    assert _textarea(undone.text) == original
    with database.read_session() as db:
        study = studies.get_study(db, NAME)
        assert study.protocol_source == original
        rows = db.scalars(select(ProtocolVersion).order_by(ProtocolVersion.number)).all()
        assert [(v.number, v.source) for v in rows if v.study_id == study.id] == [
            (1, original),
            (2, edited),
            (3, original),
        ]
    same = admin.post(
        f"/admin/studies/{NAME}/protocol", data={"base": _base(undone.text), "text": original}
    )
    assert "Nothing changed." in same.text and "Saved as version" not in same.text


def test_the_second_editor_is_shown_what_changed_and_keeps_what_they_typed(
    database: Database, user_client: UserClientFactory
) -> None:
    original = protocol_text(**EXP3_ONLY)
    _draft(database, original)
    first, second = user_client(Role.ADMIN, "ada"), user_client(Role.ADMIN, "bo")
    base = _base(first.get(f"/admin/studies/{NAME}/protocol").text)
    assert base == _base(second.get(f"/admin/studies/{NAME}/protocol").text)
    saved = first.post(
        f"/admin/studies/{NAME}/protocol",
        data={"base": base, "text": original.replace("sessions = 4", "sessions = 3")},
    )
    assert "Saved as version 2." in saved.text
    theirs = original.replace("runs_per_session = 3", "runs_per_session = 2")
    assert theirs != original
    refused = second.post(f"/admin/studies/{NAME}/protocol", data={"base": base, "text": theirs})
    assert refused.status_code == 409
    words = " ".join(html.unescape(refused.text).split())
    assert "changed while you edited it: you started from version 1" in words
    assert "saved by ada" in words
    assert "-sessions = 4" in html.unescape(refused.text)
    assert "+sessions = 3" in html.unescape(refused.text)
    assert _textarea(refused.text) == theirs  # nothing typed is lost
    with database.read_session() as db:
        assert studies.protocol_of(studies.get_study(db, NAME)).schedule.sessions == 3
        assert studies.protocol_of(studies.get_study(db, NAME)).schedule.runs_per_session == 3
    # The page now carries the current version: the merge saves.
    assert _base(refused.text) == _base(saved.text)
    merged = theirs.replace("sessions = 4", "sessions = 3")
    again = second.post(
        f"/admin/studies/{NAME}/protocol", data={"base": _base(refused.text), "text": merged}
    )
    assert "Saved as version 3." in again.text


@sqlite_only("pages and checks; the version check under a row lock is tested on both engines")
def test_a_protocol_with_problems_is_not_saved_a_pilot_frozen_and_a_live_one_amended(
    database: Database, admin: TestClient, exp3_study: str
) -> None:
    original = protocol_text(**EXP3_ONLY)
    _draft(database, original)
    base = _base(admin.get(f"/admin/studies/{NAME}/protocol").text)
    broken = admin.post(
        f"/admin/studies/{NAME}/protocol",
        data={"base": base, "text": original.replace("sessions = 4", "sessions = 0")},
    )
    assert broken.status_code == 422 and "schedule.sessions" in broken.text
    live = admin.get(f"/admin/studies/{exp3_study}/protocol")
    assert 'id="protocol-amendment"' in live.text and "<textarea" in live.text
    with database.read_session() as db:
        live_base = studies.get_study(db, exp3_study).protocol_sha256
    amended = original.replace("sessions = 4", "sessions = 3")
    refused = admin.post(
        f"/admin/studies/{exp3_study}/protocol", data={"base": live_base, "text": amended}
    )
    assert refused.status_code == 422 and "an amendment" in refused.text  # no reason given
    assert admin.post(f"/api/v1/studies/{NAME}/phase", json={"phase": "pilot"}).status_code == 200
    pilot = admin.post(f"/admin/studies/{NAME}/protocol", data={"base": base, "text": original})
    assert pilot.status_code == 409 and "Reset the pilot and take it back to draft" in pilot.text
    frozen = admin.get(f"/admin/studies/{NAME}/protocol")
    assert 'id="protocol-frozen"' in frozen.text and "<textarea" not in frozen.text
    with database.read_session() as db:
        assert len(db.scalars(select(ProtocolVersion)).all()) == 2  # the two studies' first


@sqlite_only("pages and checks; the version check under a row lock is tested on both engines")
@pytest.mark.parametrize("file", shipped_protocol_files())
def test_every_shipped_protocol_round_trips_through_the_study_editor(
    database: Database, admin: TestClient, file: str
) -> None:
    shipped = shipped_protocol(file)
    _draft(database, shipped.source_text, name="round-trip")
    page = admin.get("/admin/studies/round-trip/protocol")
    assert _textarea(page.text) == shipped.source_text
    saved = admin.post(
        "/admin/studies/round-trip/protocol",
        data={"base": _base(page.text), "text": _textarea(page.text)},
    )
    assert "Nothing changed." in saved.text
    with database.read_session() as db:
        assert studies.get_study(db, "round-trip").protocol_sha256 == shipped.sha256
