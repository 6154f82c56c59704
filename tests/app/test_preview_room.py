"""The room previewed by staff (issue 50, item 3): a whole session walked over the preview's
socket, in either language and either condition, with the study's questions and replies, and
not a row stored; each reply line spoken on request; what a room client cannot ask refused."""

from __future__ import annotations

from typing import Any

import pytest
from starlette.testclient import WebSocketTestSession

from app.api.runtime_schemas import AnswerOut, PromptOut, StationStateOut
from app.db import Database
from app.errors import Conflict, NotFound
from app.protocol import Protocol, shipped_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.design.preview_room import PreviewRoom
from app.tables import Role
from tests.app.test_preview import _rows
from tests.conftest import UserClientFactory, sqlite_only

SV = "fast_adaptation_trust_sv.toml"


@pytest.fixture
def bilingual(database: Database) -> Protocol:
    loaded = shipped_protocol(SV)
    with database.writing() as db:
        studies.create_study(db, name="sv", loaded=loaded, actor=Actor.system())
    return loaded.protocol


def _ask(ws: WebSocketTestSession, number: int, kind: str, **fields: Any) -> dict[str, Any]:
    ws.send_json({"type": kind, "id": number, **fields})
    while True:
        message = ws.receive_json()
        if message.get("id") == number:
            return dict(message)


@sqlite_only("the preview lives in memory; the database is only read")
@pytest.mark.parametrize(("language", "condition"), [("sv", "C2"), ("en", "C1")])
def test_a_whole_session_is_walked_in_the_preview_and_nothing_is_stored(
    user_client: UserClientFactory,
    database: Database,
    bilingual: Protocol,
    language: str,
    condition: str,
) -> None:
    staff = user_client(Role.ADMIN)
    spoken = bilingual.in_language(language)
    lines = {level.line(said) for level in spoken.replies.levels for said in (True, False)}
    page = staff.get(f"/studies/sv/preview/room/{language}?condition={condition}")
    assert page.status_code == 200 and 'data-preview="true"' in page.text
    assert f'data-socket-query="?condition={condition}"' in page.text
    plan = staff.get(f"/studies/sv/preview/room/{language}/api/room").json()
    assert plan["rules"] == list(spoken.study.rules)
    before = _rows(database)
    url = f"/studies/sv/preview/room/{language}/api/ws?condition={condition}"
    with staff.websocket_connect(url) as ws:
        ws.send_json({"type": "auth", "key": "ignored"})
        hello = ws.receive_json()
        assert hello["type"] == "hello" and hello["station"] == f"preview-sv-{language}"
        assert StationStateOut.model_validate(hello["state"]).expected.action == "prompt"
        number = 0
        for _ in range(spoken.schedule.runs_per_session):
            for category in spoken.categories:
                number += 1
                asked = _ask(ws, number, "prompt", category=category.name, zone=category.name)
                prompt = PromptOut.model_validate(asked["data"])
                assert prompt.question in category.questions  # in the preview's language
                number += 1
                said = _ask(ws, number, "answer", step_id=prompt.step_id, answer="yes")
                reply = AnswerOut.model_validate(said["data"])
                assert reply.reply in lines
        assert reply.session_completed
        state = StationStateOut.model_validate(_ask(ws, number + 1, "state")["data"])
        assert state.expected.action == "done"
        refused = _ask(ws, number + 2, "prompt", category="conation")
        assert refused["type"] == "error" and refused["status"] == 409
    assert _rows(database) == before  # no participant, step, answer or audit entry


@sqlite_only("the preview lives in memory; the database is only read")
def test_every_reply_line_is_spoken_on_request_and_nothing_else(
    user_client: UserClientFactory, bilingual: Protocol
) -> None:
    staff = user_client(Role.EXPERIMENTER)
    page = staff.get("/studies/sv/preview/room/sv").text
    line = bilingual.in_language("sv").replies.levels[0].line(True)
    assert "Every reply, by level" in page and line in page
    spoken = staff.get("/studies/sv/preview/room/sv/api/speech/audio", params={"text": line})
    assert spoken.status_code in (200, 503)  # 503: espeak-ng is missing (said in one line)
    if spoken.status_code == 200:
        assert spoken.content[:4] == b"RIFF"
    other = staff.get("/studies/sv/preview/room/sv/api/speech/audio", params={"text": "Hi"})
    assert other.status_code == 404
    assert staff.get("/studies/sv/preview/room/de").status_code == 404  # not a language of it
    speech = staff.get("/studies/sv/preview/room/sv/api/speech").json()
    assert speech["offline_recognition"] is False and speech["cloud_recognizer"] is False


def test_the_preview_refuses_what_a_room_cannot_ask() -> None:
    protocol = shipped_protocol(SV).protocol
    room = PreviewRoom(study="sv", station="preview-sv-en", protocol=protocol, condition="C1")
    with pytest.raises(NotFound):
        room.prompt("nowhere")
    step = room.prompt("conation")
    assert room.prompt("conation") == {**step, "created": False}  # the open one again
    room.answer(step["step_id"], said_yes=False)
    with pytest.raises(Conflict):
        room.answer(step["step_id"], said_yes=True)
    with pytest.raises(Conflict):
        room.prompt("conation")  # answered in this run
    with pytest.raises(Exception, match="choose one of C1, C2"):
        PreviewRoom(study="sv", station="x", protocol=protocol, condition="C9")
