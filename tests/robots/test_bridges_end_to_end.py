"""Each bridge end to end: the real vendor client against a stand-in speaking that robot's own
protocol on loopback, the bridge loop, and the test's app served on loopback. A scripted
participant hesitates, mumbles and answers; the tests check the words the robot was told to say
and their order, the gestures, the answers stored (once each, with transcript and confidence), a
dropped robot connection, and ``trustlab verify``."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from sqlalchemy import select

from app.protocol import parse_protocol
from app.services import studies, verify
from app.services.audit import Actor
from app.tables import Answer
from tests.conftest import EXP3_ONLY, Lab, protocol_text
from tests.robots.harness import BOUND, RunningBridge, served
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


@pytest.fixture
def url(lab: Lab) -> Iterator[str]:
    with served(lab.app) as address:
        yield address


def _ask_now(lab: Lab, category: str) -> dict[str, Any]:
    response = lab.experimenter.post(
        f"/api/v1/stations/{lab.station}/prompts", json={"category": category}
    )
    assert response.status_code in (200, 201), response.text
    return dict(response.json())


def _answers(lab: Lab) -> list[Answer]:
    with lab.database.read_session() as db:
        return list(db.scalars(select(Answer).order_by(Answer.id)))


def _wait_until(condition: Callable[[], bool]) -> None:
    for _ in range(int(BOUND / 0.02)):
        if condition():
            return
        threading.Event().wait(0.02)
    raise AssertionError("never happened")


def _verify_clean(lab: Lab) -> None:
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    assert report.ok, report.findings


def test_a_participant_answers_through_the_robot(kind: Kind, gesturing: Lab, url: str) -> None:
    script = Script()
    script.add(Silence(), Words("maybe", 0.95), Words("Yeah", 0.8), Words("no way", 0.7))
    with (
        kind.stand_in(script) as stand_in,
        RunningBridge(kind.robot(stand_in), url, gesturing.station, gesturing.key),
    ):
        first = _ask_now(gesturing, "conation")
        script.wait_said(4, BOUND)
        second = _ask_now(gesturing, "affection")
        said = script.wait_said(6, BOUND)
    answers = _answers(gesturing)
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
    _verify_clean(gesturing)


def test_a_dropped_robot_connection_is_survived(kind: Kind, gesturing: Lab, url: str) -> None:
    script = Script()
    script.add(Drop(), "yes")
    with (
        kind.stand_in(script) as stand_in,
        RunningBridge(kind.robot(stand_in), url, gesturing.station, gesturing.key) as bridge,
    ):
        step = _ask_now(gesturing, "cognition")
        _wait_until(lambda: any("reconnecting" in line for line in bridge.lines))
        kind.recover(stand_in)
        said = script.wait_said(3, BOUND)
    [answer] = _answers(gesturing)
    assert (answer.prompt_id, answer.answer, answer.transcript) == (step["step_id"], True, "yes")
    assert [line.text for line in said] == [step["question"], step["question"], answer.reply]
    assert any("reconnecting" in line for line in bridge.lines)
    assert any("is back" in line for line in bridge.lines)
    _verify_clean(gesturing)
