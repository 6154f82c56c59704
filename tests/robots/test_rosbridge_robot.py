"""The rosbridge adapter against a rosbridge v2 stand-in on loopback, through roslibpy itself.

Every test opens and closes its own connections in this one process, so the file as a whole also
shows that roslibpy's reactor (started once, never stopped) serves connection after connection.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import pytest

from app.robots.robot import Cue, Heard, RobotError, RobotLost, RobotUnreachable
from app.robots.rosbridge import RosbridgeOptions, RosbridgeRobot, decode_heard, new_listen_id
from tests.robots.harness import wait_for
from tests.robots.standins.rosbridge import CUE, HEARD, SAID, RosbridgeStandIn
from tests.robots.standins.script import Drop, Said, Script, Silence, Words

pytestmark = pytest.mark.timeout(60)

PHRASES = ["yes", "yeah", "no"]


def robot_at(port: int, **options: Any) -> RosbridgeRobot:
    return RosbridgeRobot(replace(RosbridgeOptions(host="127.0.0.1", port=port), **options))


@pytest.fixture
def script() -> Script:
    return Script()


@pytest.fixture
def stand_in(script: Script) -> Iterator[RosbridgeStandIn]:
    with RosbridgeStandIn(script) as robot:
        yield robot


@pytest.fixture
def robot(stand_in: RosbridgeStandIn) -> Iterator[RosbridgeRobot]:
    connected = robot_at(stand_in.port, listen_grace=0.2)
    connected.connect()
    yield connected
    connected.close()


def assert_one_line(error: RobotError, *parts: str) -> None:
    message = str(error)
    assert "\n" not in message and message.startswith("rosbridge at ws://127.0.0.1:")
    for part in parts:
        assert part in message


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def test_says_lines_in_order_with_their_gestures(robot: RosbridgeRobot, script: Script) -> None:
    robot.say("Is the key under the mat?")
    robot.say("Good, that is right.", gesture="nod")
    robot.say("Next one.")

    assert script.said == [
        Said("Is the key under the mat?"),
        Said("Good, that is right.", "nod"),
        Said("Next one."),
    ]


def test_without_a_gesture_topic_gestures_are_not_sent(
    stand_in: RosbridgeStandIn, script: Script
) -> None:
    robot = robot_at(stand_in.port, gesture_topic=None)
    robot.connect()
    robot.say("Hello", gesture="wave")
    robot.close()

    assert script.said == [Said("Hello")]


def test_listen_reports_what_the_recogniser_heard_and_none_on_silence(
    robot: RosbridgeRobot, stand_in: RosbridgeStandIn, script: Script
) -> None:
    script.add(Words("Yeah", 0.75), Silence(), Words("", 0.9), "no")

    assert robot.listen(PHRASES, 0.3) == Heard("Yeah", 0.75)
    assert robot.listen(PHRASES, 0.3) is None
    assert robot.listen(PHRASES, 0.3) is None
    assert robot.listen(["no"], 0.3) == Heard("no", 0.9)

    assert script.vocabularies == [PHRASES, PHRASES, PHRASES, ["no"]]
    first = stand_in.listen_requests[0]
    assert first == {"id": first["id"], "phrases": PHRASES, "language": "en-US", "seconds": 0.3}
    ids = [request["id"] for request in stand_in.listen_requests]
    assert len(set(ids)) == 4
    # only the silent one is given up on, and cancelled, before the next request
    assert stand_in.listen_log == [
        ("listen", ids[0]),
        ("listen", ids[1]),
        ("cancel", ids[1]),
        ("listen", ids[2]),
        ("listen", ids[3]),
    ]


def test_the_late_result_of_a_listen_cut_off_by_a_drop_is_not_taken_after_reconnecting(
    script: Script,
) -> None:
    """The connection drops while the robot listens (request one); the node still hears "yes"
    and publishes it, with request one's id, once the reconnected bridge asks the next question:
    that is not this question's answer (silence), and request one is cancelled first."""
    script.add(Drop(), Silence())
    with RosbridgeStandIn(script, late_after_drop=Words("yes", 0.95)) as stand_in:
        robot = robot_at(stand_in.port, listen_grace=0.2)
        robot.connect()
        with pytest.raises(RobotLost):
            robot.listen(PHRASES, 30)
        robot.connect()
        assert robot.listen(PHRASES, 0.3) is None
        # The give-up's cancel is on its way when listen returns: the stand-in logs it soon after
        # (under load, after the block would have closed it).
        wait_for(lambda: len(stand_in.listen_log) == 4)
        robot.close()
    cut_off, asked = (request["id"] for request in stand_in.listen_requests)
    assert cut_off != asked
    assert stand_in.listen_log == [
        ("listen", cut_off),
        ("cancel", cut_off),  # superseded by the next request, on the new connection
        ("listen", asked),
        ("cancel", asked),  # silence: given up on
    ]


def test_listen_ids_are_unique_across_robots_and_processes() -> None:
    """Each id is the process's random prefix and its count: a second adapter in this process
    and a restarted bridge (another process) never repeat one."""
    here = [new_listen_id() for _ in range(3)]
    program = "from app.robots.rosbridge import new_listen_id; print(new_listen_id())"
    elsewhere = [
        subprocess.run(
            [sys.executable, "-c", program], capture_output=True, text=True, check=True
        ).stdout.strip()
        for _ in range(2)
    ]
    assert len(set(here + elsewhere)) == 5
    assert all(isinstance(request_id, str) and request_id for request_id in here + elsewhere)


def test_no_cancel_is_sent_without_a_cancel_topic(script: Script) -> None:
    script.add(Silence())
    with RosbridgeStandIn(script) as stand_in:
        robot = robot_at(stand_in.port, listen_grace=0.1, cancel_topic=None)
        robot.connect()
        assert robot.listen(PHRASES, 0.1) is None
        robot.close()
    assert [kind for kind, _ in stand_in.listen_log] == ["listen"]


def test_a_late_result_of_an_earlier_listen_is_not_taken_for_this_one(script: Script) -> None:
    script.add("yes", Silence())
    late = '{"id": 0, "words": "no", "confidence": 1}'
    with RosbridgeStandIn(script, stale_heard=late) as stand_in:
        robot = robot_at(stand_in.port, listen_grace=0.2)
        robot.connect()
        assert robot.listen(PHRASES, 30) == Heard("yes", 0.9)
        assert robot.listen(PHRASES, 0.3) is None
        robot.close()


@pytest.mark.parametrize(
    ("data", "request_id", "heard"),
    [
        ('{"id": 3, "words": "yes", "confidence": 0.6}', 3, Heard("yes", 0.6)),
        ('{"words": " no ", "confidence": 2}', None, Heard("no", 2.0)),  # refused by the bridge
        ('{"id": "a-1", "words": "yes", "confidence": 85}', "a-1", Heard("yes", 85.0)),
        ('{"words": "yes", "confidence": -0.5}', None, Heard("yes", -0.5)),
        ('{"words": "no"}', None, Heard("no", 1.0)),
        ('{"words": "yes", "confidence": "high"}', None, Heard("yes", 0.0)),
        ('{"words": "yes", "confidence": NaN}', None, Heard("yes", 0.0)),
        ('{"id": 4, "words": ""}', 4, None),
        ("no way", None, Heard("no way", 1.0)),
        ("42", None, Heard("42", 1.0)),
        ("  ", None, None),
    ],
)
def test_heard_messages_are_json_or_plain_words(
    data: str, request_id: object, heard: Heard | None
) -> None:
    assert decode_heard(data) == (request_id, heard)


def test_a_dropped_connection_while_listening_is_robot_lost_and_connect_recovers(
    robot: RosbridgeRobot, stand_in: RosbridgeStandIn, script: Script
) -> None:
    script.add(Drop(), "yes")

    with pytest.raises(RobotLost) as lost:
        robot.listen(PHRASES, 30)
    assert_one_line(lost.value, "lost while listening")
    with pytest.raises(RobotLost):
        robot.say("Anyone there?")

    robot.connect()
    assert robot.listen(PHRASES, 30) == Heard("yes", 0.9)
    robot.close()
    stand_in.wait_connections(0)


def test_a_robot_that_never_reports_a_line_said_is_lost(script: Script) -> None:
    with RosbridgeStandIn(script, reports_said=False) as stand_in:
        robot = robot_at(stand_in.port, say_timeout=0.2)
        robot.connect()
        with pytest.raises(RobotLost) as lost:
            robot.say("Hello?\nAnyone?")
        robot.close()

    assert_one_line(lost.value, "'Hello? Anyone?'", SAID)


def test_a_wrong_port_is_unreachable_in_one_line() -> None:
    with pytest.raises(RobotUnreachable) as unreachable:
        robot_at(free_port()).connect()

    assert_one_line(unreachable.value, "connection refused")


def test_a_port_that_is_not_rosbridge_is_unreachable() -> None:
    with socket.socket() as silent:  # accepts TCP (the kernel's backlog) but never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        with pytest.raises(RobotUnreachable) as unreachable:
            robot_at(silent.getsockname()[1], connect_timeout=0.3).connect()

    assert_one_line(unreachable.value, "no rosbridge WebSocket within 0.3 s")


def test_losing_rosbridge_for_good_makes_reconnecting_robot_lost(script: Script) -> None:
    with RosbridgeStandIn(script) as stand_in:
        robot = robot_at(stand_in.port)
        robot.connect()

    with pytest.raises(RobotLost) as lost:
        robot.connect()
    assert_one_line(lost.value, "connection refused")


@pytest.mark.parametrize("topic", [SAID, HEARD])
def test_a_missing_robot_topic_is_unreachable_naming_it(script: Script, topic: str) -> None:
    with RosbridgeStandIn(script, missing_topics=[topic]) as stand_in:
        with pytest.raises(RobotUnreachable) as unreachable:
            robot_at(stand_in.port).connect()
        stand_in.wait_connections(0)

    assert_one_line(unreachable.value, f"no topic {topic} ")


def test_the_cue_topic_is_required_only_when_asked(script: Script) -> None:
    with RosbridgeStandIn(script, missing_topics=[CUE]) as stand_in:
        with pytest.raises(RobotUnreachable) as unreachable:
            robot_at(stand_in.port, require_cue_topic=True).connect()
        robot = robot_at(stand_in.port)
        robot.connect()
        robot.close()

    assert_one_line(unreachable.value, f"no topic {CUE} ")


def test_a_robot_topic_of_another_type_is_unreachable(script: Script) -> None:
    image = {HEARD: "sensor_msgs/msg/Image"}
    with (
        RosbridgeStandIn(script, topic_types=image) as stand_in,
        pytest.raises(RobotUnreachable) as unreachable,
    ):
        robot_at(stand_in.port).connect()

    assert_one_line(unreachable.value, HEARD, "sensor_msgs/msg/Image")


def test_a_rosbridge_without_rosapi_is_unreachable(script: Script) -> None:
    with (
        RosbridgeStandIn(script, rosapi=False) as stand_in,
        pytest.raises(RobotUnreachable) as unreachable,
    ):
        robot_at(stand_in.port).connect()

    assert_one_line(unreachable.value, "/rosapi/topics failed", "does not exist")


def test_cues_name_their_category_or_leave_it_to_the_station(
    robot: RosbridgeRobot, stand_in: RosbridgeStandIn
) -> None:
    assert robot.wait_cue(0.05) is None

    stand_in.cue("affection")
    assert robot.wait_cue(30) == Cue("affection", source="ROS topic")
    stand_in.cue()
    assert robot.wait_cue(30) == Cue(None, source="ROS topic")


def test_closing_wakes_a_thread_waiting_for_a_cue(robot: RosbridgeRobot) -> None:
    errors: list[BaseException] = []
    waiting = threading.Event()

    def wait() -> None:
        waiting.set()
        try:
            robot.wait_cue(30)
        except BaseException as error:
            errors.append(error)

    waiter = threading.Thread(target=wait)
    waiter.start()
    waiting.wait(10)
    robot.close()
    waiter.join(30)

    assert not waiter.is_alive()
    assert [type(error) for error in errors] == [RobotLost]
    assert "closed while waiting" in str(errors[0]) or "not connected" in str(errors[0])


def test_connect_and_close_again_and_again_in_one_process(
    stand_in: RosbridgeStandIn, script: Script
) -> None:
    first = robot_at(stand_in.port)
    for line in ("one", "two"):
        first.connect()
        first.say(line)
        first.close()
        stand_in.wait_connections(0)
    second = robot_at(stand_in.port)
    second.connect()
    second.say("three")
    second.close()
    second.close()
    stand_in.wait_connections(0)

    assert [said.text for said in script.said] == ["one", "two", "three"]


def test_a_robot_not_connected_is_lost() -> None:
    with pytest.raises(RobotLost) as lost:
        robot_at(9).say("Hello")

    assert_one_line(lost.value, "not connected")
