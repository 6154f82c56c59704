"""The bridge loop with an in-process robot against the test's app served on loopback: what the
robot says and in what order, what is stored (once, with transcript and confidence), the
console's notices, each trigger, losing the robot, and the refusals at start."""

from __future__ import annotations

import asyncio
import json
import threading
from importlib import resources
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from app.api import station_ops
from app.client import RobotClient, StationSocket
from app.protocol import parse_protocol
from app.robots.bridge import BridgeRefused, Trigger
from app.robots.robot import Cue
from app.services import studies
from app.services.audit import Actor
from app.tables import Device, Prompt
from tests.conftest import Lab, fill_pre_study, tablet_client
from tests.robots.fake_robot import FakeRobot
from tests.robots.harness import (
    BOUND,
    RunningBridge,
    ask_now,
    assert_verify_clean,
    served,
    stored_answers,
    wait_for,
)
from tests.robots.standins.script import Drop, Said, Script, Silence, Words
from tests.servers import free_port

SQLITE_ONLY = pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)
pytestmark = pytest.mark.timeout(120)

REPROMPT = "Sorry, I did not catch that. Please answer yes or no."


@SQLITE_ONLY
def test_ask_now_is_said_heard_stored_once_and_replied(seated: Lab, url: str) -> None:
    script = Script()
    script.add(Words("Yeah!", 0.83))
    with RunningBridge(FakeRobot(script), url, seated.station, seated.key):
        step = ask_now(seated)
        said = script.wait_said(2, BOUND)
    assert said[0] == Said(step["question"])
    [answer] = stored_answers(seated)
    assert (answer.prompt_id, answer.answer, answer.modality) == (step["step_id"], True, "speech")
    assert (answer.transcript, answer.transcript_confidence) == ("Yeah!", 0.83)
    assert said[1].text == answer.reply and said[1].gesture is None
    assert script.vocabularies == [["yes", "yeah", "yep", "sure", "no", "nope", "no way"]]
    assert_verify_clean(seated)


def _notice(lab: Lab) -> tuple[str | None, bool]:
    with lab.database.read_session() as db:
        device = db.scalar(select(Device))
        assert device is not None
        return device.notice, device.notice_attention


@SQLITE_ONLY
def test_silence_and_unclear_words_are_asked_again(seated: Lab, url: str) -> None:
    script = Script()
    script.add(Silence(), Words("\x00\ufffd garbage \x1b[2J", 0.99), Words("maybe", 0.9), "no way")
    speech = seated.robot.get("/api/v1/station/speech").json()
    assert speech["attempts"] == 3
    with RunningBridge(FakeRobot(script), url, seated.station, seated.key, trigger=Trigger.CONSOLE):
        ask_now(seated)
        script.wait_said(3, BOUND)
        # three tries: silence, garbage, "maybe" -> the console is asked for an answer
        wait_for(lambda: _notice(seated)[0] is not None)
        notice, attention = _notice(seated)
        assert attention and notice is not None
        assert "stayed unclear after 3 tries (last heard: “maybe” (0.90))" in notice
        assert stored_answers(seated) == []
        step_id = seated.robot.get("/api/v1/station").json()["open_prompts"][0]["step_id"]
        woz = seated.experimenter.post(
            f"/api/v1/stations/{seated.station}/steps/{step_id}/answer",
            json={"answer": "no", "idempotency_key": "woz-1"},
        )
        assert woz.status_code == 200, woz.text
        said = script.wait_said(4, BOUND)
        wait_for(lambda: _notice(seated)[0] is None)
    assert [line.text for line in said[1:]] == [REPROMPT, REPROMPT, woz.json()["reply"]]
    [answer] = stored_answers(seated)
    assert (answer.answer, answer.modality, answer.transcript) == (False, None, None)
    assert _notice(seated) == (None, False)
    assert len(script.said) == 4 and len(script.vocabularies) == 3
    assert list(script.replies) == [Words("no way")]  # never listened a fourth time


@SQLITE_ONLY
def test_stepping_into_a_zone_asks_its_category(seated: Lab, url: str) -> None:
    script = Script()
    script.add("yes")
    with RunningBridge(FakeRobot(script), url, seated.station, seated.key, trigger="presence") as b:
        where = {"x": 1.0, "z": 1.0, "heading": 0.0, "zone": "affection"}
        assert seated.robot.put("/api/v1/station/presence", json=where).status_code == 204
        said = script.wait_said(2, BOUND)
    [answer] = stored_answers(seated)
    with seated.database.read_session() as db:
        category = db.scalar(select(Prompt.category).where(Prompt.id == answer.prompt_id))
    assert category == "affection" and said[1].text == answer.reply
    assert any("stepped into zone affection: asking for affection" in line for line in b.lines)


@SQLITE_ONLY
def test_the_robot_s_cue_asks_the_expected_category(seated: Lab, url: str) -> None:
    script = Script()
    script.add("sure", "nope")
    robot = FakeRobot(script)
    with RunningBridge(robot, url, seated.station, seated.key, trigger=Trigger.ROBOT):
        expected = seated.robot.get("/api/v1/station").json()["expected"]["categories"]
        robot.cues.put(Cue(source="head touched"))
        script.wait_said(2, BOUND)
        robot.cues.put(Cue(category=expected[-1], source="ROS topic"))
        script.wait_said(4, BOUND)
    answers = stored_answers(seated)
    with seated.database.read_session() as db:
        categories = [db.get(Prompt, a.prompt_id).category for a in answers]  # type: ignore[union-attr]
    assert categories == [expected[0], expected[-1]]
    assert [a.answer for a in answers] == [True, False]


def test_a_lost_robot_is_told_to_the_console_and_asked_again(seated: Lab, url: str) -> None:
    script = Script()
    script.add(Drop(), "yep")
    robot = FakeRobot(script)
    robot.away_after_drop = True
    with RunningBridge(robot, url, seated.station, seated.key) as bridge:
        step = ask_now(seated)
        wait_for(lambda: robot.away.is_set() and _notice(seated)[0] is not None)
        away = _notice(seated)  # the bridge keeps trying while the robot stays away
        wait_for(lambda: robot.attempts >= 3)  # at start, then twice refused while away
        assert _notice(seated) == away
        console = seated.experimenter.get(f"/stations/{seated.station}").text
        assert 'class="attention device-notice" role="alert"><strong>pepper</strong>' in console
        assert "lost the robot (the fake robot dropped the connection); reconnecting" in console
        robot.away.clear()
        said = script.wait_said(3, BOUND)
        wait_for(lambda: _notice(seated) == (None, False))
        assert "device-notice" not in seated.experimenter.get(f"/stations/{seated.station}").text
    assert away == (
        "lost the robot (the fake robot dropped the connection); reconnecting",
        True,
    )
    assert [line.text for line in said[:2]] == [step["question"], step["question"]]
    [answer] = stored_answers(seated)
    assert (answer.prompt_id, answer.transcript) == (step["step_id"], "yep")
    assert said[2].text == answer.reply
    assert robot.connects == 2
    assert any(
        "lost the fake robot (the fake robot dropped the connection)" in line
        for line in bridge.lines
    )
    assert _notice(seated) == (None, False)
    assert_verify_clean(seated)


def test_a_reply_cut_off_by_a_lost_robot_is_said_once_it_is_back(seated: Lab, url: str) -> None:
    """The answer is stored, the robot drops while saying the reply: once it is back it says
    the reply (not the question again), and the answer stays stored once."""
    script = Script()
    script.add("yes")
    script.drop_says = {2}  # the question, then the reply: dropped
    robot = FakeRobot(script)
    with RunningBridge(robot, url, seated.station, seated.key) as bridge:
        step = ask_now(seated)
        said = script.wait_said(2, BOUND)
        wait_for(lambda: _notice(seated) == (None, False))
    [answer] = stored_answers(seated)
    assert (answer.prompt_id, answer.transcript) == (step["step_id"], "yes")
    assert [line.text for line in said] == [step["question"], answer.reply]
    assert robot.connects == 2 and len(script.vocabularies) == 1  # not asked or heard again
    assert any("dropped the connection while speaking" in line for line in bridge.lines)
    assert any("saying the reply the robot was cut off in" in line for line in bridge.lines)
    assert_verify_clean(seated)


def test_a_reply_cut_off_after_the_study_moved_on_is_told_to_the_console(
    seated: Lab, url: str
) -> None:
    """The robot drops while saying a reply and stays away while the console asks the next
    question: once back, it does not say the stale reply; the console is told what the
    participant did not hear, until the next reply is said."""
    script = Script()
    script.add("yes")
    script.drop_says = {2}
    robot = FakeRobot(script)
    robot.away_after_drop = True
    with RunningBridge(robot, url, seated.station, seated.key):
        first = ask_now(seated, "conation")
        wait_for(lambda: (_notice(seated)[0] or "").startswith("lost the robot"))
        second = ask_now(seated, "affection")
        robot.hold = True
        robot.away.clear()
        wait_for(lambda: "moved on" in (_notice(seated)[0] or ""))
        notice, attention = _notice(seated)
        [answer] = stored_answers(seated)
        assert attention and notice is not None
        assert f"P001's answer to “{first['question']}”" in notice
        assert f"the reply “{answer.reply}” was recorded but not heard" in notice
        assert robot.listening.wait(BOUND)  # the next question is asked
        script.add("no")
        robot.release.set()
        said = script.wait_said(3, BOUND)
        wait_for(lambda: _notice(seated) == (None, False))
    first_answer, second_answer = stored_answers(seated)
    assert (first_answer.prompt_id, second_answer.prompt_id) == (
        first["step_id"],
        second["step_id"],
    )
    assert [line.text for line in said] == [
        first["question"],
        second["question"],
        second_answer.reply,
    ]
    assert_verify_clean(seated)


def test_a_console_answer_given_while_the_robot_is_away_is_said_once_it_is_back(
    seated: Lab, url: str
) -> None:
    """The robot drops while listening and stays away; the console answers the question
    meanwhile: once the robot is back it says that answer's reply (the question is not asked
    again, and nothing else has happened since)."""
    script = Script()
    script.add(Drop())
    robot = FakeRobot(script)
    robot.away_after_drop = True
    with RunningBridge(robot, url, seated.station, seated.key) as bridge:
        step = ask_now(seated)
        wait_for(lambda: (_notice(seated)[0] or "").startswith("lost the robot"))
        woz = seated.experimenter.post(
            f"/api/v1/stations/{seated.station}/steps/{step['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": "woz-away"},
        )
        assert woz.status_code == 200, woz.text
        robot.away.clear()
        said = script.wait_said(2, BOUND)
        wait_for(lambda: _notice(seated) == (None, False))
    assert [line.text for line in said] == [step["question"], woz.json()["reply"]]
    assert len(script.vocabularies) == 1 and len(stored_answers(seated)) == 1
    assert any("given while the robot was away" in line for line in bridge.lines)


def test_a_console_answer_given_while_the_robot_is_away_is_flagged_once_the_study_moved_on(
    seated: Lab, url: str
) -> None:
    """The robot drops while listening and stays away; the console answers the question and
    asks the next one: once back, the robot does not say the stale reply, and the console is
    told that the participant never heard it, until the next reply is said."""
    script = Script()
    script.add(Drop())
    robot = FakeRobot(script)
    robot.away_after_drop = True
    with RunningBridge(robot, url, seated.station, seated.key):
        first = ask_now(seated, "conation")
        wait_for(lambda: (_notice(seated)[0] or "").startswith("lost the robot"))
        woz = seated.experimenter.post(
            f"/api/v1/stations/{seated.station}/steps/{first['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": "woz-away"},
        )
        assert woz.status_code == 200, woz.text
        second = ask_now(seated, "affection")
        robot.hold = True
        robot.away.clear()
        wait_for(lambda: "moved on" in (_notice(seated)[0] or ""))
        notice, attention = _notice(seated)
        assert attention and notice is not None
        assert notice.startswith(
            f"the robot was away when P001's answer to “{first['question']}” was given on this "
            "console, and the study has moved on"
        )
        assert f"the reply “{woz.json()['reply']}” was recorded but not heard" in notice
        assert robot.listening.wait(BOUND)  # the next question is asked
        script.add("no")
        robot.release.set()
        said = script.wait_said(3, BOUND)
        wait_for(lambda: _notice(seated) == (None, False))
    first_answer, second_answer = stored_answers(seated)
    assert (first_answer.prompt_id, second_answer.prompt_id) == (
        first["step_id"],
        second["step_id"],
    )
    assert [line.text for line in said] == [
        first["question"],
        second["question"],
        second_answer.reply,
    ]
    assert_verify_clean(seated)


@SQLITE_ONLY
def test_a_confidence_outside_0_to_1_is_refused_not_taken_as_certain(seated: Lab, url: str) -> None:
    """A recogniser reporting 85 (per cent) is not clamped to 1.0 and answered with: the bridge
    says so in one line and asks again; the next clear answer is stored with its own
    confidence."""
    script = Script()
    script.add(Words("yes", 85), Words("yes", 0.9))
    with RunningBridge(FakeRobot(script), url, seated.station, seated.key) as bridge:
        step = ask_now(seated)
        said = script.wait_said(3, BOUND)
    [answer] = stored_answers(seated)
    assert (answer.prompt_id, answer.transcript_confidence) == (step["step_id"], 0.9)
    assert [line.text for line in said] == [step["question"], REPROMPT, answer.reply]
    [refused] = [line for line in bridge.lines if "not taken as an answer" in line]
    assert "“yes” (confidence 85, not within 0-1)" in refused and "\n" not in refused


def test_a_bridge_killed_mid_answer_and_restarted_answers_once(seated: Lab, url: str) -> None:
    first = Script()
    first.add(Silence())
    with RunningBridge(FakeRobot(first), url, seated.station, seated.key):
        step = ask_now(seated)
        first.wait_said(2, BOUND)  # the question and a reprompt: killed while listening again
    assert stored_answers(seated) == []
    second = Script()
    second.add("no")
    with RunningBridge(FakeRobot(second), url, seated.station, seated.key):
        said = second.wait_said(2, BOUND)  # the open question is asked again at start
    assert said[0].text == step["question"]
    [answer] = stored_answers(seated)
    assert (answer.prompt_id, answer.answer, said[1].text) == (step["step_id"], False, answer.reply)
    assert_verify_clean(seated)


@SQLITE_ONLY
def test_refusals_at_start_are_one_line_and_send_nothing(lab: Lab, url: str) -> None:
    cases = [
        (
            url,
            "lab-2",
            lab.key,
            FakeRobot(Script()),
            "the key belongs to station 'lab-1', not 'lab-2'",
        ),
        (url, lab.station, "tlk_not-a-key", FakeRobot(Script()), "refused the key"),
        (
            "http://127.0.0.1:9",
            lab.station,
            lab.key,
            FakeRobot(Script()),
            "cannot reach the trustlab server at http://127.0.0.1:9",
        ),
        (
            url,
            lab.station,
            lab.key,
            FakeRobot(Script(), refuse_connects=1),
            "the fake robot refused the connection",
        ),
    ]
    for address, station, key, robot, reason in cases:
        with pytest.raises(BridgeRefused) as refused:
            RunningBridge(robot, address, station, key).__enter__()
        message = str(refused.value)
        assert reason in message and "\n" not in message
    with lab.database.read_session() as db:
        assert db.scalar(select(Prompt)) is None


@SQLITE_ONLY
def test_an_answer_heard_while_the_server_is_away_is_recorded_once(seated: Lab) -> None:
    script = Script()
    script.add("yes")
    robot = FakeRobot(script)
    robot.hold = True
    port = free_port()
    with served(seated.app, port) as url:
        bridge = RunningBridge(robot, url, seated.station, seated.key).__enter__()
        step = ask_now(seated)
        assert robot.listening.wait(BOUND)
    robot.release.set()  # the participant answers while the server is gone
    try:
        wait_for(lambda: not script.replies)  # heard; the answer waits for the server
        assert (
            stored_answers(seated) == [] and len(script.said) == 1
        )  # no reply before it is stored
        with served(seated.app, port):
            said = script.wait_said(2, BOUND)
    finally:
        bridge.stop()
    [answer] = stored_answers(seated)
    assert (answer.prompt_id, answer.answer, answer.transcript) == (step["step_id"], True, "yes")
    assert said[1].text == answer.reply
    assert_verify_clean(seated)


@SQLITE_ONLY
def test_a_console_answer_given_while_the_server_is_away_is_said_on_return(seated: Lab) -> None:
    """The bridge is cut off from the server while the console answers the question it asked:
    the push never reaches it, and the state it reconnects with brings the reply."""
    script = Script()
    script.add(Words("maybe", 0.9), Words("maybe", 0.9), Words("maybe", 0.9))
    port = free_port()
    with served(seated.app, port) as url:
        bridge = RunningBridge(FakeRobot(script), url, seated.station, seated.key).__enter__()
        step = ask_now(seated)
        wait_for(lambda: _notice(seated)[1])  # unclear three times: the console is asked
    try:
        woz = seated.experimenter.post(  # the console is in touch; the bridge is not
            f"/api/v1/stations/{seated.station}/steps/{step['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": "woz-away"},
        )
        assert woz.status_code == 200, woz.text
        with served(seated.app, port):
            said = script.wait_said(4, BOUND)
            wait_for(lambda: _notice(seated) == (None, False))
    finally:
        bridge.stop()
    assert [line.text for line in said[1:]] == [REPROMPT, REPROMPT, woz.json()["reply"]]
    assert any("back in touch with the server" in line for line in bridge.lines)
    assert len(stored_answers(seated)) == 1


@SQLITE_ONLY
def test_an_answer_stored_whose_response_is_lost_is_stored_and_replied_once(
    seated: Lab, url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server commits the answer, then the connection is cut before anything it sends
    reaches the bridge (the result, the answer_recorded push): the bridge sends the answer again
    after reconnecting, under the same idempotency key, so the server replays the stored one.
    One answer stored, the reply said once. (A fresh key per retry fails the same-key check
    only: the server keeps one answer per step and replays it for the same yes/no whatever the
    key, so the step, not the key, is what keeps a retried answer from being stored twice.)"""
    committed = threading.Event()
    calls: list[str] = []
    real_answer = station_ops.answer

    def answer_then_note(db: Any, **arguments: Any) -> Any:
        calls.append(arguments["body"].idempotency_key)
        out = real_answer(db, **arguments)  # commits
        committed.set()
        return out

    cut = {"done": False, "dropping": False}
    real_connect = StationSocket._connect
    real_dispatch = StationSocket._dispatch

    async def connect_with_a_cut(self: StationSocket) -> None:
        await real_connect(self)
        cut["dropping"] = False  # a new connection: its frames arrive again
        connection = self._connection
        assert connection is not None
        real_send = connection.send

        async def send(message: Any, *args: Any, **kwargs: Any) -> None:
            await real_send(message, *args, **kwargs)
            if not cut["done"] and json.loads(message).get("type") == "answer":
                cut["done"] = cut["dropping"] = True  # nothing from here on reaches the bridge
                await asyncio.to_thread(committed.wait, BOUND)
                connection.transport.abort()  # the network fails after the commit

        connection.send = send  # type: ignore[method-assign]

    async def dispatch(self: StationSocket, message: dict[str, Any]) -> None:
        if not cut["dropping"]:
            await real_dispatch(self, message)

    monkeypatch.setattr(station_ops, "answer", answer_then_note)
    monkeypatch.setattr(StationSocket, "_connect", connect_with_a_cut)
    monkeypatch.setattr(StationSocket, "_dispatch", dispatch)
    script = Script()
    script.add("yes")
    with RunningBridge(FakeRobot(script), url, seated.station, seated.key) as bridge:
        step = ask_now(seated)
        said = script.wait_said(2, BOUND)
    assert cut["done"] and committed.is_set()
    assert len(calls) == 2 and len(set(calls)) == 1  # sent again, under the same key
    [answer] = stored_answers(seated)
    assert (answer.prompt_id, answer.answer, answer.transcript) == (step["step_id"], True, "yes")
    assert [line.text for line in said] == [step["question"], answer.reply]
    assert len(script.said) == 2
    assert not any("refused" in line for line in bridge.lines)
    assert_verify_clean(seated)


@SQLITE_ONLY
def test_a_server_hiccup_before_asking_delays_the_question_not_loses_it(
    seated: Lab, url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_speech = RobotClient.speech
    failures = {"speech": 1}

    async def flaky_speech(self: RobotClient) -> Any:
        if failures["speech"]:
            failures["speech"] -= 1
            raise httpx.ConnectError("connection refused")
        return await real_speech(self)

    async def no_console(self: RobotClient, text: str | None, *, attention: bool = False) -> None:
        raise httpx.ConnectError("connection refused")

    monkeypatch.setattr(RobotClient, "speech", flaky_speech)
    monkeypatch.setattr(RobotClient, "notice", no_console)
    script = Script()
    script.add(Drop(), "no")
    with RunningBridge(FakeRobot(script), url, seated.station, seated.key) as bridge:
        step = ask_now(seated)
        said = script.wait_said(3, BOUND)
    assert [line.text for line in said[:2]] == [step["question"], step["question"]]
    [answer] = stored_answers(seated)
    assert (answer.prompt_id, answer.answer, said[2].text) == (step["step_id"], False, answer.reply)
    assert any(
        "lost the server (connection refused); trying again" in line for line in bridge.lines
    )
    assert any("could not update the console (connection refused)" in line for line in bridge.lines)


@SQLITE_ONLY
def test_a_participant_in_another_language_is_left_to_the_console(lab: Lab, url: str) -> None:
    """A robot set up for English says nothing to a Swedish participant (not the question in
    the wrong voice): the console is asked for the answer, and the step is answered once."""
    text = (resources.files("app.protocols") / "fast_adaptation_trust_sv.toml").read_text()
    with lab.database.writing() as db:
        studies.create_study(
            db,
            name="sv",
            loaded=parse_protocol(text.replace('learner = "meta"', 'learner = "exp3"')),
            actor=Actor.system(),
        )
    lab.study = "sv"
    enrolled = lab.experimenter.post(
        "/api/v1/studies/sv/participants", json={"code": "S1", "language": "sv"}
    )
    assert enrolled.status_code == 201, enrolled.text
    seated = lab.experimenter.put(
        f"/api/v1/stations/{lab.station}/participant", json={"study": "sv", "code": "S1"}
    )
    assert seated.status_code == 200, seated.text
    fill_pre_study(tablet_client(lab.app, lab, "S1"))
    lab.start_session()
    script = Script()
    with RunningBridge(FakeRobot(script), url, lab.station, lab.key) as bridge:
        step = ask_now(lab)
        wait_for(lambda: _notice(lab)[1])
        notice, attention = _notice(lab)
        assert attention and notice is not None
        assert notice.startswith("S1 takes part in 'sv', but this robot speaks 'en'")
        answered = lab.experimenter.post(
            f"/api/v1/stations/{lab.station}/steps/{step['step_id']}/answer",
            json={"answer": "yes", "idempotency_key": "wizard"},
        )
        assert answered.status_code == 200, answered.text
        wait_for(lambda: _notice(lab) == (None, False))
    assert script.said == [] and script.vocabularies == []
    assert any("takes part in 'sv'" in line for line in bridge.lines)
    assert len(stored_answers(lab)) == 1
