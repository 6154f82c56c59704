"""The Furhat adapter, through the vendor's own client, against a stand-in Remote API skill."""

from __future__ import annotations

import http.server
import logging
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from app.robots.furhat import RECOGNISED_CONFIDENCE, FurhatOptions, FurhatRobot
from app.robots.robot import Cue, Heard, RobotLost, RobotUnreachable
from tests.robots.standins.furhat import FurhatStandIn
from tests.robots.standins.script import Drop, Said, Script, Silence, Words

pytestmark = pytest.mark.timeout(60)

PHRASES = ["yes", "no"]


@contextmanager
def connected(
    script: Script, stand_in_options: dict[str, Any] | None = None, **robot_options: Any
) -> Iterator[tuple[FurhatRobot, FurhatStandIn]]:
    """A connected adapter and its stand-in, closed after."""
    with FurhatStandIn(script, **(stand_in_options or {})) as stand_in:
        options = FurhatOptions(host=stand_in.host, port=stand_in.port, **robot_options)
        robot = FurhatRobot(options)
        robot.connect()
        try:
            yield robot, stand_in
        finally:
            robot.close()


def free_port() -> int:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def assert_one_line(error: pytest.ExceptionInfo[Exception], *parts: str) -> None:
    message = str(error.value)
    assert "\n" not in message
    for part in parts:
        assert part in message


@contextmanager
def http_server(status: int, body: bytes) -> Iterator[int]:
    """Some other HTTP server, answering every request with ``status`` and ``body``."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self._answer()

        def do_POST(self) -> None:
            self._answer()

        def _answer(self) -> None:
            self.send_response(status)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, args=(0.02,), daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()


# Saying.


def test_says_lines_in_order_with_the_gesture_started_first() -> None:
    script = Script()
    with connected(script) as (robot, stand_in):
        robot.say("Is the red box heavier?")
        robot.say("Well done.", gesture="Nod")
        assert script.said == [Said("Is the red box heavier?"), Said("Well done.", "Nod")]
        calls = [(m, p, q.get("blocking")) for m, p, q in stand_in.requests if p != "/furhat/users"]
        assert calls[-3:] == [
            ("POST", "/furhat/say", "True"),
            ("POST", "/furhat/gesture", "False"),
            ("POST", "/furhat/say", "True"),
        ]


def test_a_gesture_the_robot_refuses_is_logged_and_the_line_still_said(
    caplog: pytest.LogCaptureFixture,
) -> None:
    script = Script()
    with connected(script) as (robot, stand_in), caplog.at_level(logging.WARNING):
        robot.say("Thank you.", gesture="Cartwheel")
        assert script.said == [Said("Thank you.")]
        assert stand_in.gestures == []
    assert "did not do gesture 'Cartwheel'" in caplog.text


def test_a_voice_is_set_on_connect() -> None:
    with connected(Script(), voice="Joanna") as (_, stand_in):
        assert stand_in.voice == "Joanna"


def test_a_voice_the_robot_lacks_is_unreachable_with_its_voices() -> None:
    with FurhatStandIn(Script()) as stand_in:
        robot = FurhatRobot(FurhatOptions(host=stand_in.host, port=stand_in.port, voice="Hal"))
        with pytest.raises(RobotUnreachable) as error:
            robot.connect()
        assert_one_line(error, "no voice 'Hal'", "Matthew, Joanna")
        assert stand_in.voice is None


# Listening.


def test_heard_words_come_back_with_the_recognised_confidence_in_the_configured_language() -> None:
    script = Script()
    script.add(Words("yes", confidence=0.1), "no way")
    with connected(script, language="sv-SE") as (robot, stand_in):
        assert robot.listen(PHRASES, 5) == Heard("yes", RECOGNISED_CONFIDENCE)
        assert robot.listen(PHRASES, 5) == Heard("no way", RECOGNISED_CONFIDENCE)
        assert [q["language"] for q in stand_in.queries("/furhat/listen")] == ["sv-SE", "sv-SE"]


@pytest.mark.parametrize("silence_message", ["SILENCE", ""])
def test_silence_is_nothing_heard(silence_message: str) -> None:
    script = Script()
    script.add(Silence(), "yes")
    with connected(script, {"silence_message": silence_message}) as (robot, _):
        assert robot.listen(PHRASES, 5) is None
        assert robot.listen(PHRASES, 5) == Heard("yes", RECOGNISED_CONFIDENCE)


def test_a_failed_recognition_is_nothing_heard_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    script = Script()
    script.add("FAILED")
    with connected(script) as (robot, _), caplog.at_level(logging.WARNING):
        assert robot.listen(PHRASES, 5) is None
    assert "could not listen: FAILED" in caplog.text


def test_the_robot_is_told_to_stop_listening_when_the_time_is_up() -> None:
    with connected(Script(), {"listen_until_stopped": True}) as (robot, stand_in):
        assert robot.listen(PHRASES, 0.05) is None
        assert stand_in.listen_stops == 1


def test_a_dropped_listen_is_the_robot_lost_and_a_reconnection_carries_on() -> None:
    script = Script()
    script.add(Drop(), "yes")
    with connected(script) as (robot, _):
        with pytest.raises(RobotLost) as error:
            robot.listen(PHRASES, 5)
        assert_one_line(error, robot.description, "while listening")
        robot.connect()
        assert robot.listen(PHRASES, 5) == Heard("yes", RECOGNISED_CONFIDENCE)


def test_a_robot_gone_while_saying_is_lost_and_so_is_its_reconnection() -> None:
    with connected(Script()) as (robot, stand_in):
        stand_in.stop()
        with pytest.raises(RobotLost) as error:
            robot.say("Hello?")
        assert_one_line(error, robot.description, "connection refused", "while saying")
        with pytest.raises(RobotLost) as error:
            robot.connect()
        assert_one_line(error, "connection refused")


def test_a_robot_that_was_never_connected_is_lost() -> None:
    robot = FurhatRobot(FurhatOptions(port=free_port()))
    with pytest.raises(RobotLost) as error:
        robot.say("Hello?")
    assert_one_line(error, "not connected")
    with pytest.raises(RobotLost) as error:
        robot.wait_cue(30)
    assert_one_line(error, "not connected")


# Reaching the robot.


def test_a_wrong_port_is_unreachable_in_one_line() -> None:
    port = free_port()
    robot = FurhatRobot(FurhatOptions(host="127.0.0.1", port=port))
    with pytest.raises(RobotUnreachable) as error:
        robot.connect()
    assert_one_line(error, f"Furhat at 127.0.0.1:{port}", "connection refused", "Remote API skill")


@pytest.mark.parametrize(
    ("status", "body", "evidence"),
    [
        (404, b"<html>Not Found</html>", "HTTP 404 on /furhat/voices"),
        (200, b"<html>Welcome</html>", "/furhat/voices is not a list of names"),
    ],
)
def test_an_http_server_that_is_not_furhat_is_unreachable(
    status: int, body: bytes, evidence: str
) -> None:
    with http_server(status, body) as port:
        robot = FurhatRobot(FurhatOptions(host="127.0.0.1", port=port))
        with pytest.raises(RobotUnreachable) as error:
            robot.connect()
    assert_one_line(error, "not as Furhat's Remote API", evidence, "Remote API skill", "54321")


def test_a_server_that_never_answers_is_unreachable_within_the_request_time() -> None:
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        port = silent.getsockname()[1]
        robot = FurhatRobot(FurhatOptions(host="127.0.0.1", port=port, request_seconds=0.2))
        with pytest.raises(RobotUnreachable) as error:
            robot.connect()
    assert_one_line(error, "no answer within 0.2 s")


# The robot's cue.


def test_a_user_entering_is_a_cue() -> None:
    with connected(Script()) as (robot, stand_in):
        stand_in.enter_user()
        assert robot.wait_cue(30) == Cue(source="user entered")


def test_users_already_there_are_no_cue_but_a_new_one_is() -> None:
    script = Script()
    with FurhatStandIn(script) as stand_in:
        first = stand_in.enter_user()
        robot = FurhatRobot(
            FurhatOptions(host=stand_in.host, port=stand_in.port, poll_seconds=0.01)
        )
        robot.connect()
        try:
            assert robot.wait_cue(0.05) is None
            stand_in.leave_user(first)
            assert robot.wait_cue(0.05) is None
            stand_in.enter_user()
            assert robot.wait_cue(30) == Cue(source="user entered")
        finally:
            robot.close()


def test_a_robot_gone_while_waiting_for_a_cue_is_lost() -> None:
    with connected(Script()) as (robot, stand_in):
        stand_in.stop()
        with pytest.raises(RobotLost) as error:
            robot.wait_cue(30)
        assert_one_line(error, robot.description, "while looking for users")


def test_closing_ends_a_wait_for_a_cue() -> None:
    with connected(Script()) as (robot, _):
        result: list[Cue | None] = []
        waiter = threading.Thread(target=lambda: result.append(robot.wait_cue(30)))
        waiter.start()
        robot.close()
        waiter.join(30)
        assert result == [None]
