"""The NAOqi adapter against a stand-in Pepper that speaks real qi messaging."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from app.robots.naoqi import (
    LoginFactory,
    NaoqiOptions,
    NaoqiRobot,
    annotate,
    heard_from_event,
)
from app.robots.robot import Cue, Heard, RobotLost, RobotUnreachable
from app.speech.vocabulary import Vocabulary
from tests.robots.standins.naoqi import NaoqiStandIn
from tests.robots.standins.script import Drop, Said, Script, Silence, Words

pytestmark = pytest.mark.timeout(60)

LISTEN = 0.3
"""Seconds of listening: words arrive at once, so only silence waits this long."""

LONGER_THAN_THE_TEST = 600.0
"""A wait only a dropped connection can end: past the test's timeout, so a wait that ignores
the drop fails the test instead of passing late."""

PHRASES = Vocabulary().phrases


def options_for(stand_in: NaoqiStandIn, **changes: Any) -> NaoqiOptions:
    return NaoqiOptions(host=stand_in.host, port=stand_in.port, call_seconds=5.0, **changes)


@pytest.fixture
def pepper() -> Iterator[NaoqiStandIn]:
    with NaoqiStandIn(Script()) as stand_in:
        yield stand_in


@pytest.fixture
def robot(pepper: NaoqiStandIn) -> Iterator[NaoqiRobot]:
    robot = NaoqiRobot(options_for(pepper))
    robot.connect()
    yield robot
    robot.close()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def test_says_each_line_in_order_with_the_robots_text_to_speech(
    pepper: NaoqiStandIn, robot: NaoqiRobot
) -> None:
    robot.say("Do you want to escape the room?")
    robot.say("I understand now.")

    assert pepper.script.said == [
        Said("Do you want to escape the room?"),
        Said("I understand now."),
    ]
    assert len(pepper.called("ALTextToSpeech.say")) == 2


def test_sets_language_voice_and_volume_on_connect(pepper: NaoqiStandIn) -> None:
    robot = NaoqiRobot(options_for(pepper, language="German", voice="naoenu", volume=0.6))
    robot.connect()
    robot.close()

    assert pepper.called("ALTextToSpeech.setLanguage") == [("German",)]
    assert pepper.called("ALSpeechRecognition.setLanguage") == [("German",)]
    assert pepper.called("ALTextToSpeech.setVoice") == [("naoenu",)]
    assert pepper.called("ALTextToSpeech.setVolume") == [(0.6,)]


def test_keeps_the_robots_own_voice_and_volume_by_default(
    pepper: NaoqiStandIn, robot: NaoqiRobot
) -> None:
    assert pepper.called("ALTextToSpeech.setLanguage") == [("English",)]
    assert pepper.called("ALTextToSpeech.setVoice") == []
    assert pepper.called("ALTextToSpeech.setVolume") == []


def test_a_gesture_goes_to_animated_speech_with_body_language_off(
    pepper: NaoqiStandIn, robot: NaoqiRobot
) -> None:
    robot.say("Awesome, I knew you would say so.", gesture="animations/Stand/Gestures/Yes_1")

    animation = "animations/Stand/Gestures/Yes_1"
    assert pepper.script.said == [
        Said("Awesome, I knew you would say so.", f"^start({animation}) ^wait({animation})")
    ]
    [(_text, configuration)] = pepper.called("ALAnimatedSpeech.say")
    assert configuration == {"bodyLanguageMode": "disabled"}
    assert pepper.called("ALTextToSpeech.say") == []


def test_with_animation_off_a_gesture_is_left_out(pepper: NaoqiStandIn) -> None:
    robot = NaoqiRobot(options_for(pepper, animated=False))
    robot.connect()
    robot.say("I understand now.", gesture="affirmative")
    robot.close()

    assert pepper.script.said == [Said("I understand now.")]
    assert pepper.called("ALAnimatedSpeech.say") == []


@pytest.mark.parametrize(
    ("gesture", "annotated"),
    [
        ("^start(animations/Stand/Gestures/Yes_1)", "^start(animations/Stand/Gestures/Yes_1) Yes"),
        (
            "animations/Stand/Gestures/No_3",
            "^start(animations/Stand/Gestures/No_3) Yes ^wait(animations/Stand/Gestures/No_3)",
        ),
        ("affirmative", "^startTag(affirmative) Yes ^waitTag(affirmative)"),
    ],
)
def test_a_gesture_is_an_annotation_an_animation_or_a_tag(gesture: str, annotated: str) -> None:
    assert annotate("Yes", gesture) == annotated


def test_listen_restricts_the_recogniser_to_the_phrases_and_returns_what_it_heard(
    pepper: NaoqiStandIn, robot: NaoqiRobot
) -> None:
    pepper.script.add(Words("yes", 0.71))

    heard = robot.listen(PHRASES, LISTEN)

    assert heard == Heard("yes", 0.71)
    assert pepper.script.vocabularies == [PHRASES]
    assert pepper.called("ALSpeechRecognition.setVocabulary") == [(PHRASES, False)]
    recogniser = [call[0] for call in pepper.calls if call[0].startswith("ALSpeechRecognition")]
    assert recogniser[-5:] == [
        "ALSpeechRecognition.pause",
        "ALSpeechRecognition.setVocabulary",
        "ALSpeechRecognition.pause",
        "ALSpeechRecognition.subscribe",
        "ALSpeechRecognition.unsubscribe",
    ]


def test_silence_is_none_and_the_recogniser_is_released(
    pepper: NaoqiStandIn, robot: NaoqiRobot
) -> None:
    pepper.script.add(Silence(), "no")

    assert robot.listen(PHRASES, LISTEN) is None
    assert pepper.called("ALSpeechRecognition.unsubscribe") == [("trustlab",)]
    assert robot.listen(PHRASES, LISTEN) == Heard("no", 0.9)


def test_a_doubtful_recognition_is_passed_on_for_the_vocabulary_to_judge(
    pepper: NaoqiStandIn, robot: NaoqiRobot
) -> None:
    pepper.script.add(Words("yes", -1.0))

    heard = robot.listen(PHRASES, LISTEN)

    assert heard == Heard("yes", -1.0)
    assert Vocabulary().classify(heard) is None


@pytest.mark.parametrize(
    ("value", "heard"),
    [
        ("garbage", Heard("garbage", 0.0)),
        ([], Heard("[]", 0.0)),
        (["yes"], Heard("yes", 0.0)),
        (["yes", "high"], Heard("yes", 0.0)),
        ([3, 0.5], Heard("3", 0.5)),
        (None, Heard("", 0.0)),
    ],
)
def test_a_malformed_recognition_does_not_crash_the_listener(
    pepper: NaoqiStandIn, robot: NaoqiRobot, value: object, heard: Heard
) -> None:
    pepper.raw_events.append(value)

    assert robot.listen(PHRASES, LISTEN) == heard


def test_best_guess_first_of_several(pepper: NaoqiStandIn) -> None:
    assert heard_from_event(["no", 0.6, "yes", 0.3]) == Heard("no", 0.6)
    assert heard_from_event(("yes", 1)) == Heard("yes", 1.0)


def test_a_drop_while_listening_is_robot_lost(pepper: NaoqiStandIn, robot: NaoqiRobot) -> None:
    pepper.script.add(Drop())

    with pytest.raises(RobotLost) as lost:
        robot.listen(PHRASES, LONGER_THAN_THE_TEST)

    assert "\n" not in str(lost.value)
    with pytest.raises(RobotLost):
        robot.say("Are you there?")


def test_after_a_drop_the_robot_reconnects(pepper: NaoqiStandIn, robot: NaoqiRobot) -> None:
    pepper.script.add(Drop(), "yes")
    with pytest.raises(RobotLost):
        robot.listen(PHRASES, LONGER_THAN_THE_TEST)

    pepper.start()
    robot.connect()

    assert robot.listen(PHRASES, LISTEN) == Heard("yes", 0.9)


def test_a_failed_reconnection_is_robot_lost(pepper: NaoqiStandIn, robot: NaoqiRobot) -> None:
    pepper.drop()

    with pytest.raises(RobotLost, match=r"cannot reach NAOqi at tcp://127\.0\.0\.1:\d+"):
        robot.connect()


def test_wrong_port_is_unreachable_in_one_line_naming_the_address() -> None:
    port = free_port()
    robot = NaoqiRobot(NaoqiOptions(port=port, call_seconds=5.0))

    with pytest.raises(RobotUnreachable) as unreachable:
        robot.connect()

    message = str(unreachable.value)
    assert f"tcp://127.0.0.1:{port}" in message
    assert "refused" in message.lower()
    assert "NAOqi 2.9 wants its password" in message
    assert "\n" not in message


def test_a_robot_without_speech_recognition_is_unreachable_naming_the_service() -> None:
    services = ("ALMemory", "ALTextToSpeech", "ALAnimatedSpeech")
    with NaoqiStandIn(Script(), services=services) as virtual:
        robot = NaoqiRobot(options_for(virtual))
        with pytest.raises(RobotUnreachable, match="has no ALSpeechRecognition service"):
            robot.connect()


def test_a_robot_without_animated_speech_needs_animation_off() -> None:
    services = ("ALMemory", "ALTextToSpeech", "ALSpeechRecognition")
    with NaoqiStandIn(Script(), services=services) as nao:
        with pytest.raises(RobotUnreachable, match="has no ALAnimatedSpeech service"):
            NaoqiRobot(options_for(nao)).connect()
        robot = NaoqiRobot(options_for(nao, animated=False))
        robot.connect()
        robot.say("Hello", gesture="hello")
        robot.close()
        assert nao.script.said == [Said("Hello")]


def test_a_login_against_a_robot_without_one_asks_to_check_the_credentials(
    pepper: NaoqiStandIn,
) -> None:
    robot = NaoqiRobot(options_for(pepper, password="wrong"))

    with pytest.raises(RobotUnreachable) as unreachable:
        robot.connect()

    message = str(unreachable.value)
    assert message.startswith(f"NAOqi at tcps://127.0.0.1:{pepper.port} ")
    assert "check NAOqi 2.9 credentials" in message
    assert "\n" not in message


def test_naoqi_2_9_is_reached_over_tls_with_a_login() -> None:
    secure = NaoqiOptions(host="10.0.0.5", password="secret")
    assert secure.url == "tcps://10.0.0.5:9503"
    assert NaoqiOptions(host="10.0.0.5").url == "tcp://10.0.0.5:9559"
    login = LoginFactory("nao", "secret").newAuthenticator()
    assert login.initialAuthData() == {"user": "nao", "token": "secret"}


def test_options_refuse_impossible_values() -> None:
    with pytest.raises(ValueError, match="volume"):
        NaoqiOptions(volume=1.5)
    with pytest.raises(ValueError, match="port"):
        NaoqiOptions(port=70000)


def test_a_head_touch_is_the_cue(pepper: NaoqiStandIn, robot: NaoqiRobot) -> None:
    cues: list[Cue | None] = []
    waiting = threading.Thread(target=lambda: cues.append(robot.wait_cue(30.0)))
    waiting.start()
    # A touch counts only while the robot waits; press until the waiting thread has seen one.
    while waiting.is_alive():
        pepper.touch_head("MiddleTactilTouched")
        waiting.join(0.05)

    assert cues == [Cue(category=None, source="head touched")]


def test_a_release_is_no_cue(pepper: NaoqiStandIn, robot: NaoqiRobot) -> None:
    cues: list[Cue | None] = []
    waiting = threading.Thread(target=lambda: cues.append(robot.wait_cue(LISTEN)))
    waiting.start()
    while waiting.is_alive():
        pepper.memory.raiseEvent("FrontTactilTouched", 0.0)
        waiting.join(0.05)

    assert cues == [None]


def test_a_drop_while_waiting_for_a_cue_is_robot_lost(
    pepper: NaoqiStandIn, robot: NaoqiRobot
) -> None:
    errors: list[BaseException] = []

    def wait() -> None:
        try:
            robot.wait_cue(LONGER_THAN_THE_TEST)
        except RobotLost as error:
            errors.append(error)

    waiting = threading.Thread(target=wait)
    waiting.start()
    pepper.drop()
    waiting.join()

    assert len(errors) == 1


def test_close_is_idempotent(robot: NaoqiRobot) -> None:
    robot.close()
    robot.close()

    with pytest.raises(RobotLost):
        robot.say("Hello")
