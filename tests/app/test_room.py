"""The escape room's floor plan (app/room.py, the protocol's ``[room]``) and what the room client
stores through the robot API: the zone a prompt was triggered in, how an answer was given."""

from __future__ import annotations

import uuid

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.protocol import ProtocolError, default_protocol, parse_protocol
from app.room import check_room, default_room
from app.tables import Answer, Prompt, Role
from tests.conftest import Lab, UserClientFactory, protocol_text, sqlite_only

ZONES = """zones = [
    { category = "conation", x = 1.92, z = 5.0, radius = 0.7 },
    { category = "affection", x = 4.0, z = 3.0, radius = 0.7 },
    { category = "cognition", x = 6.08, z = 1.0, radius = 0.7 },
]"""


def _refusal(zones: str) -> str:
    with pytest.raises(ProtocolError) as refused:
        parse_protocol(protocol_text(**{ZONES: zones}), source="lab.toml")
    return str(refused.value)


def test_the_shipped_room_is_the_default_layout_and_valid() -> None:
    protocol = default_protocol().protocol
    assert protocol.room is not None
    assert protocol.room == default_room(["conation", "affection", "cognition"])
    assert [zone.category for zone in protocol.room.zones] == ["conation", "affection", "cognition"]


@pytest.mark.parametrize("count", [1, 2, 3, 4, 6, 10, 15])
def test_the_default_layout_fits_any_number_of_categories(count: int) -> None:
    names = [f"c{index}" for index in range(count)]
    room = default_room(names)
    assert check_room(room, names) == []
    assert [zone.category for zone in room.zones] == names


def test_a_protocol_without_a_room_gets_the_default_for_its_categories() -> None:
    text = default_protocol().source_text
    without = text[: text.index("[room]")] + text[text.index("[questionnaires.consent]") :]
    protocol = parse_protocol(without).protocol
    assert protocol.room is None
    assert protocol.room_layout() == default_room([c.name for c in protocol.categories])


@pytest.mark.parametrize(
    ("zones", "expected"),
    [
        (
            ZONES.replace("x = 6.08, z = 1.0", "x = 7.6, z = 1.0"),
            "lab.toml: room.zones[2]: the zone lies outside the maze "
            "(x 7.6 + radius 0.7 > width 8)",
        ),
        (
            ZONES.replace("x = 4.0, z = 3.0", "x = 2.3, z = 4.6"),
            "lab.toml: room.zones[1]: overlaps room.zones[0] ('conation'): centres 0.55 m apart, "
            "radii 0.7 + 0.7",
        ),
        (
            ZONES.replace('{ category = "cognition", x = 6.08, z = 1.0, radius = 0.7 },\n', ""),
            "lab.toml: room.zones: no zone for category 'cognition'",
        ),
        (
            ZONES.replace('category = "cognition"', 'category = "curiosity"'),
            "lab.toml: room.zones[2].category: no category 'curiosity' in this protocol "
            "(categories: conation, affection, cognition)",
        ),
        (
            ZONES.replace('category = "cognition"', 'category = "conation"'),
            "lab.toml: room.zones[2].category: a second zone for 'conation' (room.zones[0]); "
            "each category has one zone",
        ),
        (
            ZONES.replace("x = 1.92, z = 5.0", "x = 1.35, z = 1.5"),
            "lab.toml: room.zones[0]: overlaps the start circle (centres 0.60 m apart)",
        ),
    ],
)
def test_a_bad_room_is_refused_with_its_key_path(zones: str, expected: str) -> None:
    assert expected in _refusal(zones).splitlines()


def test_a_room_point_outside_the_maze_and_a_bad_number_are_refused() -> None:
    text = protocol_text(
        **{"red_button = { x = 7.85, z = 4.2 }": "red_button = { x = 9.0, z = 4.2 }"}
    )
    with pytest.raises(ProtocolError, match=r"room\.red_button: red_button lies outside the maze"):
        parse_protocol(text)
    with pytest.raises(ProtocolError, match=r"room\.width"):
        parse_protocol(protocol_text(**{"width = 8.0": "width = nan"}))


@sqlite_only("the protocol is refused before anything is stored")
def test_study_creation_refuses_a_bad_room(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    bad = protocol_text(**{ZONES: ZONES.replace('category = "cognition"', 'category = "x"')})
    refused = admin.post("/api/v1/studies", json={"name": "maze", "protocol_toml": bad})
    assert refused.status_code == 422
    assert "room.zones[2].category: no category 'x'" in refused.json()["detail"]
    assert admin.get("/api/v1/studies/maze").status_code == 404


def test_the_station_serves_the_room_of_its_study(lab: Lab) -> None:
    nobody = lab.robot.get("/api/v1/station/room")
    assert nobody.status_code == 409
    assert "runs no study yet" in nobody.json()["detail"]
    lab.enrol_and_assign("P001")
    room = lab.robot.get("/api/v1/station/room")
    assert room.status_code == 200, room.text
    body = room.json()
    assert body["study"] == lab.study
    assert "title" not in body  # the staff's title of the study: not for a participant's screen
    assert [c["name"] for c in body["categories"]] == ["conation", "affection", "cognition"]
    assert body["layout"]["zones"][1] == {
        "category": "affection",
        "x": 4.0,
        "z": 3.0,
        "radius": 0.7,
    }
    assert body["rules"][0] == "Your goal is to escape the room."
    # Freed, the station still runs its study: the room stays up for the next participant.
    assert lab.experimenter.delete(f"/api/v1/stations/{lab.station}/participant").status_code in (
        200,
        204,
    )
    assert lab.robot.get("/api/v1/station/room").json()["layout"] == body["layout"]


def test_zone_and_how_answered_are_stored_once(lab: Lab) -> None:
    lab.enrol_and_assign("P001")
    lab.start_session()
    asked = lab.robot.post(
        "/api/v1/station/prompts", json={"category": "conation", "zone": "conation"}
    )
    assert asked.status_code == 201, asked.text
    again = lab.robot.post(
        "/api/v1/station/prompts", json={"category": "conation", "zone": "other"}
    )
    assert again.status_code == 200 and again.json()["step_id"] == asked.json()["step_id"]
    step = asked.json()["step_id"]
    key = uuid.uuid4().hex
    spoken = {
        "answer": "yes",
        "idempotency_key": key,
        "modality": "speech",
        "transcript": "yes please",
        "transcript_confidence": 0.82,
    }
    first = lab.robot.post(f"/api/v1/station/steps/{step}/answer", json=spoken)
    assert first.status_code == 200, first.text
    retried = lab.robot.post(
        f"/api/v1/station/steps/{step}/answer",
        json={"answer": "yes", "idempotency_key": key, "modality": "button"},
    )
    assert retried.status_code == 200 and retried.json()["replayed"] is True
    with lab.database.read_session() as db:
        prompts = db.scalars(select(Prompt)).all()
        answers = db.scalars(select(Answer)).all()
    assert [(p.category, p.zone) for p in prompts] == [("conation", "conation")]
    assert [(a.modality, a.transcript, a.transcript_confidence) for a in answers] == [
        ("speech", "yes please", 0.82)
    ]


@pytest.mark.parametrize(
    ("body", "problem"),
    [
        ({"answer": "yes", "transcript": "yes"}, "come with modality 'speech'"),
        ({"answer": "no", "modality": "voice"}, "modality"),
        (
            {"answer": "no", "modality": "speech", "transcript_confidence": 1.5},
            "a fraction from 0 to 1 (0.85 for 85 %), not 1.5",
        ),
    ],
)
@sqlite_only("the answer's body is refused by its schema, before any query")
def test_an_answer_with_a_bad_account_of_itself_is_refused(
    lab: Lab, body: dict[str, object], problem: str
) -> None:
    lab.enrol_and_assign("P001")
    lab.start_session()
    step = lab.robot.post("/api/v1/station/prompts", json={"category": "affection"}).json()
    refused = lab.robot.post(
        f"/api/v1/station/steps/{step['step_id']}/answer",
        json={**body, "idempotency_key": uuid.uuid4().hex},
    )
    assert refused.status_code == 422
    assert problem in refused.text
    with lab.database.read_session() as db:
        assert db.scalars(select(Answer)).all() == []


@sqlite_only("the zone's name is refused by its schema, before any query")
def test_a_bad_zone_name_is_refused(lab: Lab) -> None:
    lab.enrol_and_assign("P001")
    lab.start_session()
    refused = lab.robot.post(
        "/api/v1/station/prompts", json={"category": "conation", "zone": "<script>"}
    )
    assert refused.status_code == 422
    with lab.database.read_session() as db:
        assert db.scalars(select(Prompt)).all() == []


def test_the_socket_carries_zone_and_modality(lab: Lab) -> None:
    lab.enrol_and_assign("P001")
    lab.start_session()
    client: TestClient = lab.robot
    with client.websocket_connect("/api/v1/station/ws") as socket:
        assert socket.receive_json()["type"] == "hello"
        socket.send_json({"type": "prompt", "id": 1, "category": "cognition", "zone": "cognition"})
        reply = socket.receive_json()
        while reply["type"] != "result":
            reply = socket.receive_json()
        step = reply["data"]["step_id"]
        socket.send_json(
            {
                "type": "answer",
                "id": 2,
                "step_id": step,
                "answer": "no",
                "idempotency_key": uuid.uuid4().hex,
                "modality": "key",
            }
        )
        reply = socket.receive_json()
        while reply["type"] != "result":
            reply = socket.receive_json()
        assert reply["data"]["answer"] == "no"
    with lab.database.read_session() as db:
        prompt = db.scalars(select(Prompt)).one()
        answer = db.scalars(select(Answer)).one()
    assert (prompt.zone, answer.modality, answer.transcript) == ("cognition", "key", None)
