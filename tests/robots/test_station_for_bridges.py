"""What the server offers a robot bridge: the study's speech settings, a notice line on the
operator console (and the console's live view of connections), and a push when the participant
steps into a trigger zone."""

from __future__ import annotations

from typing import Any

from sqlalchemy import select

from app import events
from app.services import stations
from app.tables import Device
from tests.conftest import Lab

SOCKET = "/api/v1/station/ws"
ZONE = {"x": 1.9, "z": 4.8, "heading": 0.0}


def test_the_speech_settings_are_the_study_s(lab: Lab) -> None:
    none_yet = lab.robot.get("/api/v1/station/speech")
    assert none_yet.status_code == 409
    assert "runs no study yet" in none_yet.json()["detail"]
    lab.enrol_and_assign("P001")
    speech = lab.robot.get("/api/v1/station/speech").json()
    assert speech["study"] == lab.study
    assert speech["yes"] == ["yes", "yeah", "yep", "sure"]
    assert speech["no"] == ["no", "nope", "no way"]
    assert (speech["attempts"], speech["min_confidence"], speech["gestures"]) == (3, 0.4, {})


def test_a_notice_shows_on_the_console_until_cleared(lab: Lab) -> None:
    console = lab.experimenter.get(f"/stations/{lab.station}").text
    assert "device-notice" not in console
    said = lab.robot.put(
        "/api/v1/station/notice",
        json={
            "text": "P001's answer stayed unclear: give a Wizard-of-Oz answer",
            "attention": True,
        },
    )
    assert said.status_code == 204, said.text
    console = lab.experimenter.get(f"/stations/{lab.station}").text
    assert 'class="attention device-notice" role="alert"><strong>pepper</strong>' in console
    assert "P001&#39;s answer stayed unclear: give a Wizard-of-Oz answer" in console

    lab.robot.put("/api/v1/station/notice", json={"text": "lost the robot; reconnecting"})
    console = lab.experimenter.get(f"/stations/{lab.station}").text
    assert 'class="notice device-notice"><strong>pepper</strong>' in console
    assert "unclear" not in console

    assert lab.robot.put("/api/v1/station/notice", json={"text": None}).status_code == 204
    assert "device-notice" not in lab.experimenter.get(f"/stations/{lab.station}").text
    with lab.database.read_session() as db:
        device = db.scalar(select(Device))
        assert device is not None
        assert (device.notice, device.notice_attention, device.notice_at) == (None, False, None)


def test_a_bad_notice_is_refused_and_the_old_one_stays(lab: Lab) -> None:
    lab.robot.put("/api/v1/station/notice", json={"text": "bridge ready"})
    for body in ({"text": "x" * 301}, {"text": "   "}, {"attention": True}, {"text": 5}):
        refused = lab.robot.put("/api/v1/station/notice", json=body)
        assert refused.status_code == 422, body
    assert "bridge ready" in lab.experimenter.get(f"/stations/{lab.station}").text


def _events_until(ws: Any, last: dict[str, Any]) -> list[dict[str, Any]]:
    """Pushes received up to and including one whose data is ``last`` (events reach the socket
    in commit order, through NOTIFY on PostgreSQL, so ``last`` comes after all earlier ones)."""
    seen = []
    while not seen or seen[-1]["data"] != last:
        message = ws.receive_json()
        if message["type"] == "event":
            seen.append(message)
    return seen


def test_entering_a_zone_is_pushed_once_and_console_events_are_not(lab: Lab) -> None:
    lab.enrol_and_assign("P001")
    with lab.robot.websocket_connect(SOCKET) as ws:
        assert ws.receive_json()["type"] == "hello"
        put = lab.robot.put
        put("/api/v1/station/presence", json={**ZONE, "zone": "conation"})
        put("/api/v1/station/presence", json={**ZONE, "x": 2.0, "zone": "conation"})
        put("/api/v1/station/presence", json={**ZONE, "zone": None})
        put("/api/v1/station/presence", json={**ZONE, "zone": "affection"})
        put("/api/v1/station/notice", json={"text": "a line for the console only"})
        put("/api/v1/station/presence", json={**ZONE, "zone": "cognition"})  # the last one
        pushed = _events_until(ws, {"zone": "cognition"})
    assert [(e["event"], e["data"]) for e in pushed] == [
        ("zone_entered", {"zone": "conation"}),
        ("zone_entered", {"zone": "affection"}),
        ("zone_entered", {"zone": "cognition"}),
    ]


def test_connecting_wakes_the_console_and_shows_there(lab: Lab) -> None:
    assert (
        'pepper: <span class="badge">not connected</span>'
        in lab.experimenter.get(f"/stations/{lab.station}").text
    )
    with lab.robot.websocket_connect(SOCKET) as ws:
        assert ws.receive_json()["type"] == "hello"
        console = lab.experimenter.get(f"/stations/{lab.station}").text
        assert 'pepper: <span class="badge open">connected</span>' in console


def test_a_connection_change_is_an_event_for_the_station_topic(lab: Lab) -> None:
    with lab.database.write_session() as db:
        device = db.scalar(select(Device))
        assert device is not None
        stations.mark_connection(db, device_id=device.id, connected=True)
        queued = db.info[events.PENDING_KEY]
        assert [(e.topic, e.type) for e in queued] == [
            (stations.station_topic_of(device.station_id), stations.DEVICE_CONNECTION)
        ]
        db.rollback()
