"""Each bridge end to end: the real vendor client against a stand-in speaking that robot's own
protocol on loopback, the bridge loop, and the test's app served on loopback. A scripted
participant hesitates, mumbles and answers; the tests check the words the robot was told to say
and their order, the gestures, the answers stored (once each, with transcript and confidence), a
dropped robot connection, and ``trustlab verify``."""

from __future__ import annotations

import dataclasses

import pytest

from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from tests.conftest import EXP3_ONLY, Lab, protocol_text
from tests.robots.harness import (
    BOUND,
    RunningBridge,
    ask_now,
    assert_verify_clean,
    stored_answers,
    wait_for,
)
from tests.robots.kinds import KINDS, Kind
from tests.robots.standins.script import Drop, Script, Silence, Words

pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True),
]

GESTURES = {"low": "Shake", "medium_low": "Thoughtful", "medium": "Nod", "high": "BigSmile"}
REPROMPT = "Sorry, I did not catch that. Please answer yes or no."


@pytest.fixture(params=sorted(KINDS))
def kind(request: pytest.FixtureRequest) -> Kind:
    return KINDS[request.param]()


@pytest.fixture
def gesturing(lab: Lab) -> Lab:
    """The lab with a study whose replies each come with a gesture; P001 seated, session 1."""
    gestures = "\n".join(f'{level} = "{name}"' for level, name in GESTURES.items())
    speech = {
        "listen_seconds = 8.0": "listen_seconds = 0.3",  # silence costs the listening time
        "[reward]": f"[speech.gestures]\n{gestures}\n\n[reward]",
    }
    text = protocol_text(**EXP3_ONLY, **speech)
    with lab.database.writing() as db:
        studies.create_study(db, name="gestures", loaded=parse_protocol(text), actor=Actor.system())
    seated = dataclasses.replace(lab, study="gestures")
    seated.enrol_and_assign("P001")
    seated.start_session()
    return seated


LEDS = {"low": "#ff0000", "medium_low": "#ff8000", "medium": "#0080ff", "high": "#00ff00"}


@pytest.fixture
def lit(lab: Lab) -> Lab:
    """The lab with a study whose replies each light the robot's LEDs in the level's colour;
    P001 seated, session 1."""
    leds = "\n".join(f'{level} = "{colour}"' for level, colour in LEDS.items())
    text = protocol_text(**EXP3_ONLY, **{"[reward]": f"[speech.leds]\n{leds}\n\n[reward]"})
    with lab.database.writing() as db:
        studies.create_study(db, name="leds", loaded=parse_protocol(text), actor=Actor.system())
    seated = dataclasses.replace(lab, study="leds")
    seated.enrol_and_assign("P001")
    seated.start_session()
    return seated


def test_the_reply_s_level_lights_the_robot_s_leds(kind: Kind, lit: Lab, url: str) -> None:
    """Each robot's LEDs (NAOqi's ALLeds group, Furhat's /furhat/led, the ROS ColorRGBA topic)
    show the reply level's colour while the reply is said, and are the robot's own again
    before the next question."""
    script = Script()
    script.add(Words("yes", 0.9), Words("no", 0.9))
    with (
        kind.stand_in(script) as stand_in,
        RunningBridge(kind.robot(stand_in), url, lit.station, lit.key),
    ):
        first = ask_now(lit, "conation")
        script.wait_said(2, BOUND)
        second = ask_now(lit, "affection")
        said = script.wait_said(4, BOUND)
        wait_for(lambda: stand_in.led in (None, "#000000"))  # the robot's own colours again
    answers = stored_answers(lit)
    assert [(line.text, line.leds) for line in said] == [
        (first["question"], None),
        (answers[0].reply, LEDS[answers[0].confidence]),
        (second["question"], None),
        (answers[1].reply, LEDS[answers[1].confidence]),
    ]


def test_a_participant_answers_through_the_robot(kind: Kind, gesturing: Lab, url: str) -> None:
    script = Script()
    script.add(Silence(), Words("maybe", 0.95), Words("Yeah", 0.8), Words("no way", 0.7))
    with (
        kind.stand_in(script) as stand_in,
        RunningBridge(kind.robot(stand_in), url, gesturing.station, gesturing.key),
    ):
        first = ask_now(gesturing, "conation")
        script.wait_said(4, BOUND)
        second = ask_now(gesturing, "affection")
        said = script.wait_said(6, BOUND)
    answers = stored_answers(gesturing)
    assert [(a.prompt_id, a.answer) for a in answers] == [
        (first["step_id"], True),
        (second["step_id"], False),
    ]
    assert [(a.modality, a.transcript) for a in answers] == [
        ("speech", "Yeah"),
        ("speech", "no way"),
    ]
    assert [a.transcript_confidence for a in answers] == [
        kind.confidence(0.8),
        kind.confidence(0.7),
    ]
    assert [(line.text, line.gesture) for line in said] == [
        (first["question"], None),
        (REPROMPT, None),
        (REPROMPT, None),
        (answers[0].reply, kind.gesture(GESTURES[answers[0].confidence])),
        (second["question"], None),
        (answers[1].reply, kind.gesture(GESTURES[answers[1].confidence])),
    ]
    assert all(line.leds is None for line in said)  # no LED colours unless the protocol sets them
    assert_verify_clean(gesturing)


def test_a_dropped_robot_connection_is_survived(kind: Kind, gesturing: Lab, url: str) -> None:
    script = Script()
    script.add(Drop(), "yes")
    with (
        kind.stand_in(script) as stand_in,
        RunningBridge(kind.robot(stand_in), url, gesturing.station, gesturing.key) as bridge,
    ):
        step = ask_now(gesturing, "cognition")
        wait_for(lambda: any("reconnecting" in line for line in bridge.lines))
        kind.recover(stand_in)
        said = script.wait_said(3, BOUND)
    [answer] = stored_answers(gesturing)
    assert (answer.prompt_id, answer.answer, answer.transcript) == (step["step_id"], True, "yes")
    assert [line.text for line in said] == [step["question"], step["question"], answer.reply]
    assert any("reconnecting" in line for line in bridge.lines)
    assert any("is back" in line for line in bridge.lines)
    assert_verify_clean(gesturing)


def test_a_furhat_lost_while_replying_says_the_reply_once_back(gesturing: Lab, url: str) -> None:
    """Furhat's Remote API drops the request to say the reply (the answer is already stored):
    the bridge reconnects and the robot says the reply, with its gesture; nothing is asked,
    heard or stored again."""
    kind = KINDS["furhat"]()
    script = Script()
    script.add(Words("yes", 0.9))
    script.drop_says = {2}
    with (
        kind.stand_in(script) as stand_in,
        RunningBridge(kind.robot(stand_in), url, gesturing.station, gesturing.key) as bridge,
    ):
        step = ask_now(gesturing, "conation")
        said = script.wait_said(2, BOUND)
    [answer] = stored_answers(gesturing)
    assert (answer.prompt_id, answer.answer, answer.transcript) == (step["step_id"], True, "yes")
    gesture = kind.gesture(GESTURES[answer.confidence])
    assert [(line.text, line.gesture) for line in said] == [
        (step["question"], None),
        (answer.reply, gesture),
    ]
    assert (
        len(stand_in.queries("/furhat/say")) == 3 and len(stand_in.queries("/furhat/listen")) == 1
    )
    assert any("reconnecting" in line for line in bridge.lines)
    assert_verify_clean(gesturing)


def test_a_rosbridge_node_s_late_result_of_a_cut_off_listen_is_not_the_next_answer(
    gesturing: Lab, url: str
) -> None:
    """The connection to rosbridge drops while the robot listens; the node still hears "yes" and
    publishes it, with that request's id, when the reconnected bridge asks again: the answer
    stored is the participant's "no" to the question asked now, with its confidence."""
    from app.robots.rosbridge import RosbridgeOptions, RosbridgeRobot
    from tests.robots.standins.rosbridge import RosbridgeStandIn

    script = Script()
    script.add(Drop(), Words("no", 0.7))
    with (
        RosbridgeStandIn(script, late_after_drop=Words("yes", 0.95)) as stand_in,
        RunningBridge(
            RosbridgeRobot(RosbridgeOptions(host="127.0.0.1", port=stand_in.port)),
            url,
            gesturing.station,
            gesturing.key,
        ),
    ):
        step = ask_now(gesturing, "conation")
        said = script.wait_said(3, BOUND)
    [answer] = stored_answers(gesturing)
    assert (answer.prompt_id, answer.answer) == (step["step_id"], False)
    assert (answer.transcript, answer.transcript_confidence) == ("no", 0.7)
    assert [line.text for line in said] == [step["question"], step["question"], answer.reply]
    cut_off, asked = (request["id"] for request in stand_in.listen_requests)
    assert stand_in.listen_log == [("listen", cut_off), ("cancel", cut_off), ("listen", asked)]
