"""Issue 50 item 3: a study's tablet pages previewed by staff, in each language, checked as the
tablet checks them, with nothing stored."""

from __future__ import annotations

import html
import re

from fastapi.testclient import TestClient
from sqlalchemy import func, select

from app.db import Database
from app.protocol import InstrumentSpec, ItemKind, Protocol, shipped_protocol
from app.services import studies
from app.services.audit import Actor
from app.tables import Base, Role
from tests.conftest import UserClientFactory, sqlite_only

SWEDISH = "fast_adaptation_trust_sv.toml"


def _bilingual_study(database: Database) -> Protocol:
    with database.writing() as db:
        study = studies.create_study(
            db, name="sv", loaded=shipped_protocol(SWEDISH), actor=Actor.system("test")
        )
        return studies.protocol_of(study)


def _valid_answers(instrument: InstrumentSpec, protocol: Protocol) -> dict[str, str]:
    """An answer every item accepts (the lowest point, the first option, a number in range)."""
    scales = {scale.name: scale for scale in protocol.questionnaires.scales}
    answers = {}
    for item in instrument.items:
        if item.kind == ItemKind.LIKERT:
            answers[item.key] = str(scales[str(item.scale)].minimum)
        elif item.kind == ItemKind.NUMBER:
            answers[item.key] = str(item.minimum if item.minimum is not None else 1)
        elif item.kind == ItemKind.CHOICE:
            option = item.options[0]
            answers[item.key] = option.value
            if option.describe:
                answers[item.key + "_description"] = "as I am"
        else:
            answers[item.key] = "fine"
    return answers


def _rows(database: Database) -> dict[str, int]:
    with database.read_session() as db:
        return {
            table.name: db.scalar(select(func.count()).select_from(table)) or 0
            for table in Base.metadata.sorted_tables
        }


def _form(page: str) -> tuple[str, str]:
    """The page's form action and CSRF token."""
    action = re.search(r'<form method="post" action="([^"]+)"', page)
    token = re.search(r'name="csrf_token" value="([^"]+)"', page)
    assert action and token, page
    return html.unescape(action.group(1)), token.group(1)


def _walk(client: TestClient, start: str, protocol: Protocol) -> list[str]:
    """Go through every page from ``start`` as a participant who first sends each page empty
    (and is told what is missing), then fills it in; the paths visited."""
    visited, path = [], start
    instruments = {i.title: i for i in protocol.questionnaires.instruments}
    while "/preview/" in path:
        visited.append(path)
        page = client.get(path)
        assert page.status_code == 200, page.text
        assert "nothing entered here is stored" in page.text
        assert "data-draft-key" not in page.text  # not even the browser keeps a draft
        action, token = _form(page.text)
        assert action == path
        empty = client.post(action, data={"csrf_token": token}, follow_redirects=False)
        assert empty.status_code == 422 and 'role="alert"' in empty.text
        title = re.search(r"<h1>([^<]+)", page.text)
        assert title
        instrument = instruments.get(html.unescape(title.group(1)).strip())
        consent = {"accept": "yes"}
        filled = consent if instrument is None else _valid_answers(instrument, protocol)
        sent = client.post(action, data={"csrf_token": token, **filled}, follow_redirects=False)
        assert sent.status_code == 303, sent.text
        path = sent.headers["location"]
    assert path.endswith("finished=true")
    return visited


def test_a_preview_walks_every_page_in_each_language_and_stores_nothing(
    user_client: UserClientFactory, database: Database
) -> None:
    protocol = _bilingual_study(database)
    client = user_client(Role.EXPERIMENTER)
    study_page = client.get("/studies/sv").text
    assert 'href="/studies/sv/preview"' in study_page
    before = _rows(database)

    index = client.get("/studies/sv/preview").text
    pages = protocol.instruments_at("pre") + protocol.instruments_at("session")
    pages += protocol.instruments_at("post")
    listed = re.findall(r'<li><a href="(/studies/sv/preview/en/\d+)">([^<]+)</a>', index)
    assert [html.unescape(title) for _, title in listed] == ["Consent"] + [i.title for i in pages]
    assert f"after each of the {protocol.schedule.sessions} sessions" in index
    assert 'href="/studies/sv/preview?language=sv"' in index
    assert _walk(client, listed[0][0], protocol) == [path for path, _ in listed]

    swedish = protocol.in_language("sv")
    consent = client.get("/studies/sv/preview/sv/1").text
    assert '<html lang="sv"' in consent
    first_paragraph = swedish.questionnaires.consent.text.split("\n\n")[0].strip()
    assert html.escape(first_paragraph, quote=False) in consent
    refused = client.post("/studies/sv/preview/sv/1", data={"csrf_token": _form(consent)[1]})
    assert refused.status_code == 422
    assert "Please tick the box to take part." not in refused.text  # said in Swedish
    assert len(_walk(client, "/studies/sv/preview/sv/1", swedish)) == len(listed)

    assert _rows(database) == before  # no participant, answer, consent or audit entry


def test_a_wrong_answer_is_said_beside_its_item_and_what_was_chosen_stays(
    user_client: UserClientFactory, database: Database
) -> None:
    protocol = _bilingual_study(database)
    client = user_client(Role.ANALYST)  # every staff role may look
    instrument = protocol.instruments_at("pre")[0]
    number = 2  # the consent page comes first
    page = client.get(f"/studies/sv/preview/en/{number}").text
    answers = _valid_answers(instrument, protocol)
    wrong_key = next(
        item.key for item in instrument.items if item.kind in (ItemKind.LIKERT, ItemKind.NUMBER)
    )
    kept_key = next(key for key in answers if key != wrong_key)
    answers[wrong_key] = "999"
    refused = client.post(
        f"/studies/sv/preview/en/{number}", data={"csrf_token": _form(page)[1], **answers}
    )
    assert refused.status_code == 422
    assert f'id="err-{wrong_key}"' in refused.text
    assert f'id="err-{kept_key}"' not in refused.text
    assert f'value="{answers[kept_key]}"' in refused.text


@sqlite_only("refused before any query of the preview's own")
def test_a_preview_refuses_what_the_study_does_not_have(
    user_client: UserClientFactory, database: Database, client: TestClient
) -> None:
    _bilingual_study(database)
    staff = user_client(Role.EXPERIMENTER)
    assert staff.get("/studies/sv/preview/de/1").status_code == 404
    said = html.unescape(staff.get("/studies/sv/preview?language=de").text)
    assert "study 'sv' is not offered in 'de' (it is in en, sv)" in said
    assert staff.get("/studies/sv/preview/en/0").status_code == 422  # pages count from 1
    assert staff.get("/studies/sv/preview/en/99").status_code == 404
    assert staff.get("/studies/ghost/preview").status_code == 404
    signed_out = TestClient(client.app).get("/studies/sv/preview", follow_redirects=False)
    assert signed_out.status_code in (303, 401)
    forged = staff.post(
        "/studies/sv/preview/en/1", data={"accept": "yes"}, headers={"X-CSRF-Token": "forged"}
    )
    assert forged.status_code == 403  # as every staff form
