"""What the server offers a robot bridge: the study's speech settings, a notice line on the
operator console (and the console's live view of connections), and a push when the participant
steps into a trigger zone."""

from __future__ import annotations

import contextlib
import json
import socket
from datetime import datetime, timedelta
from typing import Any

import pytest
from sqlalchemy import delete, select, update
from websockets.sync.client import ClientConnection, connect

from app import events
from app.protocol import ProtocolError, parse_protocol
from app.services import topics
from app.services.sessions import stations
from app.tables import Device, DeviceSocket, utcnow
from tests.conftest import Lab, protocol_text
from tests.robots.harness import BOUND, console_badge, wait_for

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
    assert speech["leds"] == {}  # off by default


def test_led_colours_are_checked_at_study_creation() -> None:
    """A reply level's LED colour is #rrggbb, for a level the protocol has."""
    good = protocol_text(**{"[reward]": '[speech.leds]\nhigh = "#00FF00"\n\n[reward]'})
    assert parse_protocol(good).protocol.speech.leds == {"high": "#00FF00"}
    for leds, where in (
        ('nearly = "#00ff00"', "speech.leds.nearly"),
        ('high = "green"', "speech.leds.high"),
        ('high = "#00ff0"', "speech.leds.high"),
    ):
        text = protocol_text(**{"[reward]": f"[speech.leds]\n{leds}\n\n[reward]"})
        with pytest.raises(ProtocolError) as refused:
            parse_protocol(text)
        assert where in str(refused.value), str(refused.value)


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
    # The pre-study questionnaires' events were committed before the socket opened, but on
    # PostgreSQL their NOTIFY can reach this process after it subscribed: they are not the
    # subject here.
    pushed = [e for e in pushed if e["event"] != "questionnaire_submitted"]
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
        stations.socket_opened(db, device_id=device.id, socket_id="s", lasts=timedelta(minutes=1))
        stations.socket_closed(db, device_id=device.id, socket_id="s")
        queued = db.info[events.PENDING_KEY]
        assert [(e.topic, e.type) for e in queued] == 2 * [
            (topics.station_topic_of(device.station_id), stations.DEVICE_CONNECTION)
        ]
        db.rollback()


def _last_close(lab: Lab) -> datetime | None:
    """When the server last recorded a close of the key's sockets (stamped at each close)."""
    with lab.database.read_session() as db:
        return db.scalar(select(Device.disconnected_at))


def _close(lab: Lab, ws: ClientConnection, *, kill: bool = False) -> None:
    """Close ``ws`` (``kill``: drop its TCP connection without a close frame, as a killed
    process's socket goes) and wait (bounded) until the server has recorded it."""
    before = _last_close(lab)
    if kill:
        ws.socket.shutdown(socket.SHUT_RDWR)
        ws.socket.close()
    else:
        ws.close()
    wait_for(lambda: _last_close(lab) != before)


def _open(lab: Lab, url: str, sockets: contextlib.ExitStack) -> ClientConnection:
    """A station socket over the network, as a bridge opens it."""
    ws = sockets.enter_context(
        connect(
            url.replace("http", "ws", 1) + SOCKET,
            additional_headers={"Authorization": f"Bearer {lab.key}"},
        )
    )
    assert json.loads(ws.recv(timeout=BOUND))["type"] == "hello"
    return ws


def test_overlapping_sockets_of_one_key_are_counted(lab: Lab, url: str) -> None:
    """A bridge that reconnects opens its new socket before its old, half-open one is closed:
    the old one closing later leaves the device connected; so does the newer one closing
    first; only when neither is open (closed, or killed) is it not connected."""
    with contextlib.ExitStack() as sockets:
        old = _open(lab, url, sockets)
        new = _open(lab, url, sockets)
        _close(lab, old, kill=True)  # after the reconnect
        assert console_badge(lab) == "connected"
        _close(lab, new)
        assert console_badge(lab) == "not connected"

        old = _open(lab, url, sockets)
        new = _open(lab, url, sockets)
        _close(lab, new)  # the newest closes while the other is still open
        assert console_badge(lab) == "connected"
        _close(lab, old, kill=True)
        assert console_badge(lab) == "not connected"


def test_a_socket_of_a_dead_worker_lapses(lab: Lab) -> None:
    """A worker process that dies cannot delete its sockets' rows: each lapses at its expiry
    (a few heartbeats on), unless a live socket pushes it on (at its heartbeat)."""
    with lab.database.write_session() as db:
        device = db.scalar(select(Device))
        assert device is not None
        lasts = timedelta(minutes=1)
        stations.socket_opened(db, device_id=device.id, socket_id="dead", lasts=lasts)
        stations.socket_opened(db, device_id=device.id, socket_id="alive", lasts=lasts)
        db.commit()
    assert console_badge(lab) == "connected"
    with lab.database.write_session() as db:
        db.execute(update(DeviceSocket).values(expires_at=utcnow() - timedelta(seconds=1)))
        stations.socket_alive(db, device_id=device.id, socket_id="alive", lasts=lasts)
        db.commit()
    assert console_badge(lab) == "connected"
    with lab.database.write_session() as db:
        db.execute(update(DeviceSocket).values(expires_at=utcnow() - timedelta(seconds=1)))
        db.commit()
    assert console_badge(lab) == "not connected"
    with lab.database.write_session() as db:  # a socket whose row the database lost comes back
        db.execute(delete(DeviceSocket))
        stations.socket_alive(db, device_id=device.id, socket_id="alive", lasts=lasts)
        db.commit()
    assert console_badge(lab) == "connected"


def test_the_stations_list_carries_each_device_s_connection_and_notice(lab: Lab) -> None:
    """``GET /api/v1/stations`` shows what the console's HTML shows of each device key: whether
    it is connected now, and the line its bridge put there (with its highlight)."""

    def device() -> dict[str, Any]:
        listed = lab.experimenter.get("/api/v1/stations")
        assert listed.status_code == 200, listed.text
        [station] = listed.json()
        [pepper] = station["devices"]
        return dict(pepper)

    assert (device()["connected"], device()["notice"]) == (False, None)
    with lab.robot.websocket_connect(SOCKET) as ws:
        assert ws.receive_json()["type"] == "hello"
        assert device()["connected"] is True
        line = "lost the robot (connection refused); reconnecting"
        put = lab.robot.put("/api/v1/station/notice", json={"text": line, "attention": True})
        assert put.status_code == 204, put.text
        notice = device()["notice"]
        assert (notice["text"], notice["attention"]) == (line, True)
        assert datetime.fromisoformat(notice["at"].replace("Z", "+00:00"))
    wait_for(lambda: device()["connected"] is False)
    lab.robot.put("/api/v1/station/notice", json={"text": None})
    assert device()["notice"] is None


@pytest.mark.parametrize("confidence", [85, -0.5, 1.01])
def test_a_confidence_outside_0_to_1_is_refused_in_one_line(lab: Lab, confidence: float) -> None:
    """A recogniser's 85 (per cent) is neither clamped nor stored, on the robot's route and on
    the experimenter's (console) route alike: a 422 whose one line says what a confidence is."""
    lab.enrol_and_assign("P001")
    lab.start_session()
    step = lab.robot.post("/api/v1/station/prompts", json={"category": "conation"}).json()
    body = {
        "answer": "yes",
        "idempotency_key": "k",
        "modality": "speech",
        "transcript": "yes",
        "transcript_confidence": confidence,
    }
    routes = (
        (lab.robot, f"/api/v1/station/steps/{step['step_id']}/answer"),
        (lab.experimenter, f"/api/v1/stations/{lab.station}/steps/{step['step_id']}/answer"),
    )
    for client, path in routes:
        refused = client.post(path, json=body)
        assert refused.status_code == 422, refused.text
        detail = refused.json()["detail"]
        assert detail == (
            "transcript_confidence: the recogniser's confidence is a fraction from 0 to 1 "
            f"(0.85 for 85 %), not {confidence:g}"
        )
    state = lab.experimenter.get(f"/api/v1/stations/{lab.station}/state").json()
    assert [p["step_id"] for p in state["open_prompts"]] == [step["step_id"]]  # not answered
