"""A repeated answer (same idempotency key) gets the original reply, completion flags included."""

from __future__ import annotations

import uuid
from collections.abc import Callable
from typing import Any

import pytest

from tests.conftest import Lab

SOCKET = "/api/v1/station/ws"

Answerer = Callable[[Lab, object, str, str], dict[str, Any]]


def _rest(lab: Lab, step_id: object, answer: str, key: str) -> dict[str, Any]:
    return lab.answer(step_id, answer, key)


def _socket(lab: Lab, step_id: object, answer: str, key: str) -> dict[str, Any]:
    with lab.robot.websocket_connect(SOCKET) as ws:
        assert ws.receive_json()["type"] == "hello"
        ws.send_json(
            {
                "id": 7,
                "type": "answer",
                "step_id": step_id,
                "answer": answer,
                "idempotency_key": key,
            }
        )
        for _ in range(50):
            message = ws.receive_json()
            if message["type"] in ("result", "error"):
                assert message["type"] == "result", message
                assert message["id"] == 7
                return dict(message["data"])
    raise AssertionError("no result")


def _answer_run(lab: Lab, answerer: Answerer) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """Answer every category of the current run, each twice with the same key."""
    pairs = []
    for category in ("conation", "affection", "cognition"):
        step = lab.prompt(category)
        key = uuid.uuid4().hex
        first = answerer(lab, step["step_id"], "yes", key)
        repeat = answerer(lab, step["step_id"], "yes", key)
        pairs.append((first, repeat))
    return pairs


def _same_but_replayed(first: dict[str, Any], repeat: dict[str, Any]) -> None:
    assert first["replayed"] is False and repeat["replayed"] is True
    assert repeat == {**first, "replayed": True}


@pytest.mark.parametrize("answerer", [_rest, _socket], ids=["rest", "websocket"])
def test_replay_of_the_last_answer_equals_the_original(lab: Lab, answerer: Answerer) -> None:
    lab.enrol_and_assign()
    lab.start_session()  # the familiarisation run: one run, so its last answer ends the session
    pairs = _answer_run(lab, answerer)
    for first, repeat in pairs:
        _same_but_replayed(first, repeat)
    last, _ = pairs[-1]
    assert (last["run_completed"], last["session_completed"]) == (True, True)
    assert [first["run_completed"] for first, _ in pairs[:-1]] == [False, False]

    lab.start_session()  # session 1: three runs
    for run in (1, 2, 3):
        pairs = _answer_run(lab, answerer)
        for first, repeat in pairs:
            _same_but_replayed(first, repeat)
        last, _ = pairs[-1]
        assert (last["run_completed"], last["session_completed"]) == (True, run == 3)


def test_replay_after_the_station_moved_on_keeps_the_completion_flags(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    keys = {}
    for category in ("conation", "affection", "cognition"):
        step = lab.prompt(category)
        keys[category] = (step["step_id"], uuid.uuid4().hex)
        lab.answer(step["step_id"], "no", keys[category][1])
    lab.prompt("conation")  # starts run 2
    step_id, key = keys["cognition"]
    repeat = lab.answer(step_id, "no", key)
    assert (repeat["replayed"], repeat["run_completed"], repeat["session_completed"]) == (
        True,
        True,
        False,
    )
    assert repeat["expected"]["action"] == "answer"  # what to do now: run 2's open prompt
    step_id, key = keys["affection"]
    earlier = lab.answer(step_id, "no", key)
    assert (earlier["run_completed"], earlier["session_completed"]) == (False, False)
