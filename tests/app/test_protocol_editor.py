"""Issue 50 item 2's first step: a protocol's text edited in the browser, checked as it is typed
by study creation's rules, and a study started from the text as typed."""

from __future__ import annotations

import html
import re

from sqlalchemy import select

from app.db import Database
from app.protocol import DEFAULT_PROTOCOL, shipped_protocol, shipped_protocol_files
from app.services import studies
from app.tables import AuditEvent, Role
from tests.conftest import UserClientFactory, sqlite_only

SHIPPED = shipped_protocol(DEFAULT_PROTOCOL).source_text


def _textarea(page: str) -> str:
    found = re.search(r'<textarea name="text"[^>]*>(.*?)</textarea>', page, re.S)
    assert found, page
    return html.unescape(found.group(1))


@sqlite_only("checking a text reads nothing stored")
def test_the_text_is_checked_as_typed_with_every_problem_and_its_key(
    user_client: UserClientFactory,
) -> None:
    admin = user_client(Role.ADMIN)
    editor = admin.get("/admin/protocols/edit").text
    assert _textarea(editor) == SHIPPED  # byte for byte, comments and all
    assert 'hx-post="/admin/protocols/check"' in editor
    fine = admin.post("/admin/protocols/check", data={"text": SHIPPED})
    assert "No problems: a study can start from this protocol." in fine.text
    broken = SHIPPED.replace("block_sizes = [2, 4]", "block_sizes = [3]").replace(
        "sessions =", "sesions ="
    )
    checked = html.unescape(admin.post("/admin/protocols/check", data={"text": broken}).text)
    assert "2 problems:" in checked
    assert "<code>allocation.block_sizes[0]</code>: block size 3" in checked
    assert "<code>schedule.sesions</code>: Extra inputs" in checked
    assert "<html" not in checked  # a fragment for htmx
    not_toml = admin.post("/admin/protocols/check", data={"text": "[study\n"}).text
    assert "1 problem:" in not_toml
    assert (
        user_client(Role.EXPERIMENTER, "ada")
        .post("/admin/protocols/check", data={"text": SHIPPED})
        .status_code
        == 403
    )


def test_a_study_starts_from_the_edited_text_and_a_refusal_keeps_it(
    user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN)
    edited = SHIPPED.replace("sessions = 4", "sessions = 3  # our shorter study")
    assert edited != SHIPPED
    broken = edited.replace("block_sizes = [2, 4]", "block_sizes = [3]")
    refused = admin.post(
        "/admin/protocols/edit",
        data={"name": "short", "start": f"shipped:{DEFAULT_PROTOCOL}", "text": broken},
    )
    assert refused.status_code == 422
    assert "the protocol has problems" in refused.text
    assert "block size 3" in html.unescape(refused.text)
    assert _textarea(refused.text) == broken  # nothing typed is lost
    made = admin.post(
        "/admin/protocols/edit",
        data={"name": "short", "start": f"shipped:{DEFAULT_PROTOCOL}", "text": edited},
    )
    assert made.status_code == 200 and "Study created." in made.text
    with database.read_session() as db:
        study = studies.get_study(db, "short")
        assert study.protocol_source == edited
        assert studies.protocol_of(study).schedule.sessions == 3
    copy = admin.get("/admin/protocols/edit?start=study:short").text
    assert _textarea(copy) == edited
    taken = admin.post(
        "/admin/protocols/edit", data={"name": "short", "start": "study:short", "text": edited}
    )
    assert taken.status_code == 422
    assert "already exists" in html.unescape(taken.text) and _textarea(taken.text) == edited
    unchanged = admin.post(
        "/admin/protocols/edit", data={"name": "same", "start": "study:short", "text": edited}
    )
    assert unchanged.status_code == 200
    with database.read_session() as db:
        started = dict(
            db.execute(
                select(AuditEvent.subject, AuditEvent.details).where(
                    AuditEvent.action == "study.created"
                )
            ).all()
        )
    assert started["short"]["started_from"] == f"text edited from shipped {DEFAULT_PROTOCOL}"
    assert started["same"]["started_from"] == "study short"  # not edited: a plain copy
    assert admin.get("/admin/protocols/edit?start=shipped:nope.toml").status_code == 404
    assert admin.get("/admin/protocols/edit?start=study:ghost").status_code == 404
    assert admin.get("/admin/protocols/edit?start=elsewhere").status_code == 404
    new_study = admin.get("/admin/studies/new").text
    assert 'action="/admin/protocols/edit"' in new_study
    assert 'value="study:short"' in new_study


def test_every_shipped_protocol_round_trips_through_the_editor(
    user_client: UserClientFactory, database: Database
) -> None:
    """Issue 50's quality bar: byte for byte in the text view, and a study made from the text
    unchanged holds that protocol, recorded as where it came from."""
    admin = user_client(Role.ADMIN)
    for number, file in enumerate(shipped_protocol_files()):
        shipped = shipped_protocol(file)
        shown = _textarea(admin.get(f"/admin/protocols/edit?start=shipped:{file}").text)
        assert shown == shipped.source_text, file
        name = f"round-{number}"
        made = admin.post(
            "/admin/protocols/edit", data={"name": name, "start": f"shipped:{file}", "text": shown}
        )
        assert made.status_code == 200, made.text
        with database.read_session() as db:
            study = studies.get_study(db, name)
            assert study.protocol_sha256 == shipped.sha256
            assert studies.protocol_of(study) == shipped.protocol
