"""The room's live state: a room client reports where the participant is and what was said
(REST and WebSocket), and the operator console's room panel shows it, on both engines."""

from __future__ import annotations

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.tables import Role, RoomPresence
from tests.conftest import Lab, UserClientFactory, client_of, sqlite_only

HERE = {"x": 1.9, "z": 4.8, "heading": 370.0, "zone": "conation"}


def _presence(lab: Lab) -> RoomPresence | None:
    with lab.database.read_session() as db:
        return db.scalar(select(RoomPresence))


def test_a_report_is_stored_and_the_console_shows_it(lab: Lab) -> None:
    lab.enrol_and_assign("P001")
    empty = lab.experimenter.get(f"/stations/{lab.station}/room-panel")
    assert "No room client has reported yet" in empty.text
    assert f"/stations/{lab.station}/room" in empty.text

    said = {"kind": "question", "text": "Do you want to escape the room?"}
    stored = lab.robot.put("/api/v1/station/presence", json={**HERE, "utterance": said})
    assert stored.status_code == 204, stored.text
    row = _presence(lab)
    assert row is not None
    assert (row.x, row.z, row.heading, row.zone) == (1.9, 4.8, 10.0, "conation")
    assert (row.utterance_kind, row.utterance) == ("question", said["text"])

    # A report without a new line moves the participant and keeps the last line said.
    moved = lab.robot.put("/api/v1/station/presence", json={"x": 3.0, "z": 4.0, "heading": -90})
    assert moved.status_code == 204
    row = _presence(lab)
    assert row is not None
    assert (row.x, row.z, row.heading, row.zone, row.utterance) == (
        3.0,
        4.0,
        270.0,
        None,
        said["text"],
    )

    panel = lab.experimenter.get(f"/stations/{lab.station}/room-panel")
    assert panel.status_code == 200
    assert "x 3.00 m, z 4.00 m, facing 270°" in panel.text
    assert "Robot asks:</span> “Do you want to escape the room?”" in panel.text
    assert 'class="participant" transform="translate(3.000 2.000) rotate(270.0)"' in panel.text
    console = lab.experimenter.get(f"/stations/{lab.station}")
    assert 'id="room-panel"' in console.text and "facing 270°" in console.text
    # Within the console the panel fetches itself once it is in the page (the console's refresh
    # may predate the room's last report); alone it does not, or it would fetch itself forever.
    assert 'hx-trigger="load, sse:room' in console.text
    assert 'hx-trigger="sse:room' in panel.text and "load," not in panel.text


def test_the_socket_takes_reports_and_answers_each(lab: Lab) -> None:
    lab.enrol_and_assign("P001")
    with lab.robot.websocket_connect("/api/v1/station/ws") as socket:
        assert socket.receive_json()["type"] == "hello"
        socket.send_json({"type": "presence", "id": 7, **HERE, "utterance": None})
        # Stepping into the zone is pushed too, before or after the reply (match replies by id).
        first, second = socket.receive_json(), socket.receive_json()
        result, pushed = (first, second) if first["type"] == "result" else (second, first)
        assert result == {"type": "result", "id": 7, "op": "presence", "data": None}
        assert (pushed["event"], pushed["data"]) == ("zone_entered", {"zone": "conation"})
        socket.send_json({"type": "presence", "id": 8, **HERE, "zone": "no zone!"})
        refused = socket.receive_json()
        assert refused["type"] == "error" and refused["status"] == 422 and refused["id"] == 8
        assert "zone" in refused["detail"]
    row = _presence(lab)
    assert row is not None and row.zone == "conation"


@pytest.mark.parametrize(
    ("body", "problem"),
    [
        ({**HERE, "x": 5000}, "x"),
        ({**HERE, "heading": 1e9}, "heading"),
        ({"z": 1.0, "heading": 0}, "x"),
        ({**HERE, "speed": 1}, "speed"),
        ({**HERE, "utterance": {"kind": "robot"}}, "text"),
        ({**HERE, "utterance": {"kind": "narrator", "text": "hi"}}, "kind"),
        ({**HERE, "utterance": {"kind": "robot", "text": "x" * 301}}, "text"),
    ],
)
@sqlite_only("a bad report is refused by its schema, before any query")
def test_a_bad_report_is_refused_and_nothing_is_stored(
    lab: Lab, body: dict[str, object], problem: str
) -> None:
    refused = lab.robot.put("/api/v1/station/presence", json=body)
    assert refused.status_code == 422
    assert problem in refused.text
    assert _presence(lab) is None


def test_a_station_without_a_study_says_so(lab: Lab) -> None:
    panel = lab.experimenter.get(f"/stations/{lab.station}/room-panel")
    assert "This station runs no study yet" in panel.text


@pytest.fixture
def sealed_lab(
    app: FastAPI,
    client: TestClient,
    lab: Lab,
    sealed_study: str,
    user_client: UserClientFactory,
) -> Lab:
    """Station 'lab-s' running a blinded study, with a participant seated."""
    owner = user_client(Role.ADMIN)
    assert owner.post("/api/v1/stations", json={"name": "lab-s"}).status_code == 201
    key = owner.post("/api/v1/stations/lab-s/devices", json={"label": "room"}).json()["key"]
    robot = client_of(client, headers={"Authorization": f"Bearer {key}"})
    sealed = Lab(app, lab.database, sealed_study, "lab-s", key, lab.experimenter, robot, {})
    sealed.enrol_and_assign("S001")
    return sealed


def test_a_sealed_study_hides_the_reply_but_not_the_question(sealed_lab: Lab) -> None:
    reply = {"kind": "reply", "text": "Awesome, I knew you would say so."}
    sealed_lab.robot.put("/api/v1/station/presence", json={**HERE, "utterance": reply})
    panel = sealed_lab.experimenter.get("/stations/lab-s/room-panel").text
    assert "Awesome" not in panel and "hidden: this study is blinded" in panel
    question = {"kind": "question", "text": "Do you want to escape the room?"}
    sealed_lab.robot.put("/api/v1/station/presence", json={**HERE, "utterance": question})
    assert (
        "Do you want to escape the room?"
        in sealed_lab.experimenter.get("/stations/lab-s/room-panel").text
    )


def test_the_panel_shows_only_the_seated_participants_reports(lab: Lab) -> None:
    lab.enrol_and_assign("P001")
    said = {"kind": "participant", "text": "yes"}
    assert lab.robot.put("/api/v1/station/presence", json={**HERE, "utterance": said}).status_code
    freed = lab.experimenter.delete(f"/api/v1/stations/{lab.station}/participant")
    assert freed.status_code in (200, 204), freed.text
    panel = lab.experimenter.get(f"/stations/{lab.station}/room-panel").text
    assert "Nobody is seated" in panel and "facing" not in panel
    lab.enrol_and_assign("P002")  # the next participant: P001's place and words are not theirs
    panel = lab.experimenter.get(f"/stations/{lab.station}/room-panel").text
    assert "The room has not reported since P002 was seated" in panel and "facing" not in panel
    assert lab.robot.put("/api/v1/station/presence", json=HERE).status_code == 204
    panel = lab.experimenter.get(f"/stations/{lab.station}/room-panel").text
    assert "facing 10°" in panel
    # P002's place, but not P001's last words: the row keeps a line until a new one is said.
    assert "“yes”" not in panel and "nothing said yet" in panel
