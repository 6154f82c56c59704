"""The simulated participants' pace (app/bots_online.py's Pace and arrivals, app/bots.py's
answer_session): which pauses come where, without waiting for them."""

from __future__ import annotations

import asyncio
import random
from types import SimpleNamespace
from typing import Any

import pytest

from app import bots_online
from app.bots import BotSummary, answer_session
from app.bots_online import HUMAN_PACE, Pace


def test_a_pace_refuses_negative_pauses_and_a_person_is_slower_than_the_speeding_flag() -> None:
    with pytest.raises(ValueError, match="≥ 0"):
        Pace(walk=-1.0)
    assert Pace() == Pace(0.0, 0.0, 0.0)
    assert HUMAN_PACE.per_item > 2.0  # app.quality's default: faster than 2 s an item is flagged


class _Robot:
    """Two categories, one run: each prompt and answer noted in ``events``."""

    def __init__(self, events: list[str]) -> None:
        self.events = events
        self.left = ["a", "b"]

    async def prompt(self, category: str) -> Any:
        self.events.append(f"prompt {category}")
        return SimpleNamespace(step_id=len(self.events), action=0)

    async def answer(self, step_id: int, answer: str) -> Any:
        self.events.append("answer")
        self.left.pop()
        action = "prompt" if self.left else "questionnaire"
        return SimpleNamespace(
            expected=SimpleNamespace(action=action, categories=self.left), run_completed=False
        )


def test_a_session_walks_before_each_question_and_thinks_before_each_answer() -> None:
    events: list[str] = []

    async def walk() -> None:
        events.append("walk")

    async def think() -> None:
        events.append("think")

    steps = asyncio.run(
        answer_session(
            _Robot(events),  # type: ignore[arg-type]
            ["a", "b"],
            {"a": 0, "b": 0},
            rng=random.Random(1),
            noise=0.0,
            think=think,
            walk=walk,
        )
    )
    assert steps == 2
    pairs = [events[i : i + 4] for i in range(0, len(events), 4)]
    assert [pair[0::2] for pair in pairs] == [["walk", "think"]] * 2
    assert [pair[3] for pair in pairs] == ["answer"] * 2


def test_arrivals_are_spread_evenly_and_the_most_at_once_is_counted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    clock = [100.0]
    slept: list[float] = []

    async def sleep(seconds: float) -> None:
        slept.append(seconds)

    monkeypatch.setattr(bots_online.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(bots_online.asyncio, "sleep", sleep)
    arrivals = bots_online._Arrivals(60.0, 4)  # one every 15 s
    clock[0] = 110.0  # 10 s on
    for index in range(4):
        asyncio.run(arrivals.wait_for(index))
    assert slept == [0.0, 5.0, 20.0, 35.0]

    summary = BotSummary()
    arrivals.arrived(summary)
    arrivals.arrived(summary)
    arrivals.left()
    arrivals.arrived(summary)
    assert summary.most_at_once == 2 and arrivals.active == 2
