"""The room previewed by staff (issue 50, item 3): walk into a zone, hear and answer a question,
hear the robot's reply, with the study's own learners and reply rules, and nothing stored.

A :class:`PreviewRoom` lives as long as the preview's socket (app.web.preview_room) and holds
one learner per category, built as enrolment builds them for a condition, in memory. It answers
the same ``state``, ``prompt`` and ``answer`` requests as a station, in the same shapes (the web
layer checks them against the station's own output models, so the browser's room client draws
it as it draws a station), for an imagined participant in the first adapting session: a run asks
each category once, the session has the protocol's runs, and then the preview says it is over.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.errors import Conflict, InvalidInput, NotFound
from app.protocol import Protocol
from app.services.sessions import learners, replies

PREVIEW_PARTICIPANT = "preview"
"""The code the preview's state gives its imagined participant (nobody is enrolled)."""
SESSION = 1
"""The preview runs the first adapting session (the familiarisation run teaches nothing)."""


@dataclass
class _Step:
    id: int
    run: int
    category: str
    action: int
    question: str
    probabilities: list[float]
    reply: str | None = None
    confidence: str | None = None


@dataclass
class PreviewRoom:
    """One staff member's walk through a study's room, in memory only."""

    study: str
    station: str
    protocol: Protocol
    """The study's protocol in the preview's language."""
    condition: str
    checkpoint_dir: Path | None = None
    run: int = 1
    steps: list[_Step] = field(default_factory=list)
    over: bool = False
    """The session's last run was answered: nothing more to ask."""

    def __post_init__(self) -> None:
        known = [c.id for c in self.protocol.conditions]
        if self.condition not in known:
            raise InvalidInput(f"condition {self.condition!r}: choose one of {', '.join(known)}")
        self._specs = {
            c.name: learners.learner_spec(self.protocol, self.condition, c, self.checkpoint_dir)
            for c in self.protocol.categories
        }
        self._learners = {name: learners.build(spec) for name, spec in self._specs.items()}
        self._ids = itertools.count(1)
        self._rng = np.random.default_rng()

    # ------------------------------------------------------------------------------ reading

    def _answered(self) -> list[str]:
        return [s.category for s in self._current() if s.reply is not None]

    def _current(self) -> list[_Step]:
        return [s for s in self.steps if s.run == self.run]

    def _pending(self) -> list[str]:
        asked = {s.category for s in self._current()}
        return [c.name for c in self.protocol.categories if c.name not in asked]

    def _open(self) -> list[_Step]:
        return [s for s in self._current() if s.reply is None]

    def _prompt_out(self, step: _Step, *, created: bool) -> dict[str, Any]:
        return {
            "step_id": step.id,
            "category": step.category,
            "action": step.action,
            "question": step.question,
            "language": self.protocol.default_language,
            "adapts": True,
            "session": SESSION,
            "run": step.run,
            "created": created,
            "probabilities": step.probabilities,
        }

    def _expected(self) -> dict[str, Any]:
        if self.over:
            action, message, categories, step_id = (
                "done",
                "the preview is over: reload the page to walk it again",
                [],
                None,
            )
        elif waiting := self._open():
            action, message, categories, step_id = (
                "answer",
                f"answer the question of {waiting[0].category}",
                [s.category for s in waiting],
                waiting[0].id,
            )
        else:
            action, message, categories, step_id = (
                "prompt",
                f"walk into a zone: {', '.join(self._pending())}",
                self._pending(),
                None,
            )
        return {
            "action": action,
            "message": message,
            "categories": categories,
            "step_id": step_id,
            "session": None if self.over else SESSION,
        }

    def state(self) -> dict[str, Any]:
        """Where the preview stands, as a station's state."""
        answered = [s for s in self._current() if s.reply is not None]
        last = answered[-1] if answered else None
        return {
            "station": self.station,
            "participant": PREVIEW_PARTICIPANT,
            "study": self.study,
            "session": {
                "number": SESSION,
                "status": "completed" if self.over else "running",
                "runs": self.protocol.schedule.runs_per_session,
                "familiarisation": False,
            },
            "run": {
                "number": self.run,
                "status": "running" if self._pending() or self._open() else "completed",
                "answered": self._answered(),
                "pending": self._pending(),
            },
            "expected": self._expected(),
            "language": self.protocol.default_language,
            "open_prompts": [self._prompt_out(s, created=False) for s in self._open()],
            "last_reply": None
            if last is None
            else {
                "step_id": last.id,
                "category": last.category,
                "reply": last.reply,
                "confidence": last.confidence,
            },
        }

    # ------------------------------------------------------------------------------ acting

    def prompt(self, category: str) -> dict[str, Any]:
        """The question the category's learner chooses (its open one again, when asked twice)."""
        if self.over:
            raise Conflict("the preview is over: reload the page to walk it again")
        if category not in self._specs:
            raise NotFound(f"no category {category!r} in this study")
        if not self._pending() and not self._open():
            self.run += 1  # walking into a zone after a run's last answer starts the next run
        for step in self._open():
            if step.category == category:
                return self._prompt_out(step, created=False)
        if category not in self._pending():
            raise Conflict(f"{category} was already answered in this run: walk to another zone")
        learner = self._learners[category]
        probabilities = learners.probabilities_list(learner)
        action = int(learner.select(self._rng))
        index = [c.name for c in self.protocol.categories].index(category)
        step = _Step(
            id=next(self._ids),
            run=self.run,
            category=category,
            action=action,
            question=self.protocol.categories[index].questions[action],
            probabilities=probabilities,
        )
        self.steps.append(step)
        return self._prompt_out(step, created=True)

    def answer(self, step_id: int, *, said_yes: bool) -> dict[str, Any]:
        """Learn from the answer and choose the reply, as a station does (nothing stored)."""
        step = next((s for s in self.steps if s.id == step_id), None)
        if step is None:
            raise NotFound(f"no step {step_id} in this preview")
        if step.reply is not None or step.run != self.run:
            raise Conflict(f"step {step_id} was answered already")
        learner = self._learners[step.category]
        reward = self.protocol.reward.yes if said_yes else self.protocol.reward.no
        learner.update(step.action, reward)
        after = learners.probabilities_list(learner)
        reply = replies.choose_reply(
            self.protocol,
            self._specs[step.category],
            before=step.probabilities,
            action=step.action,
            after=after,
            said_yes=said_yes,
        )
        step.reply, step.confidence = reply.text, reply.name
        run_done = not self._pending() and not self._open()
        session_done = run_done and self.run >= self.protocol.schedule.runs_per_session
        self.over = session_done
        return {
            "step_id": step.id,
            "category": step.category,
            "answer": "yes" if said_yes else "no",
            "reply": reply.text,
            "replayed": False,
            "run_completed": run_done,
            "session_completed": session_done,
            "expected": self._expected(),
            "confidence_level": reply.level,
            "confidence": reply.name,
            "probability": reply.probability,
            "probabilities": after,
        }
