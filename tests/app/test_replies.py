"""The robot's reply fits the answer it heard (issue 36 item 1), for every shipped C2 checkpoint
and for Exp3, over answer histories; the replication setting says exactly what it always said."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.protocol import Protocol, default_protocol
from app.services.sessions.learners import LearnerSpec, probabilities_list
from app.services.sessions.replies import choose_reply
from models.checkpoints import PRETRAINED_DIR, WEIGHTS_FILE, load_checkpoint
from models.learners.base import Learner
from models.learners.exp3 import Exp3
from models.learners.meta_policy import MetaPolicyLearner
from models.replies import reply_text

CHECKPOINTS = sorted(path.parent for path in PRETRAINED_DIR.rglob(WEIGHTS_FILE))
"""Every shipped checkpoint: the default, paper, replication and retired sets."""

SHIPPED = default_protocol().protocol
REPLICATION = SHIPPED.model_copy(
    update={"replies": SHIPPED.replies.model_copy(update={"basis": "chosen"})}
)
EXP3_GAMMA = SHIPPED.learners.exp3.gamma
KNEW = "Awesome, I knew you would say so."
DOUBT = "I do not believe it but fine."


@functools.cache
def _checkpoint_learner(path: Path) -> tuple[MetaPolicyLearner, LearnerSpec]:
    checkpoint = load_checkpoint(path)
    spec = LearnerSpec("meta", checkpoint.n_arms, {"checkpoint": str(path)}, checkpoint.sha256)
    return MetaPolicyLearner(checkpoint), spec


def _fresh(kind: Path | str) -> tuple[Learner, LearnerSpec, float]:
    """A new learner, its spec, and how the test reads its belief in the asked question."""
    if kind == "exp3":
        spec = LearnerSpec("exp3", 4, {"gamma": EXP3_GAMMA}, None)
        return Exp3(4, EXP3_GAMMA), spec, EXP3_GAMMA
    assert isinstance(kind, Path)
    learner, spec = _checkpoint_learner(kind)
    learner.reset()
    return learner, spec, 0.0


def _belief(p_asked: float, floor_gamma: float, n_arms: int) -> float:
    """The learner's belief in the asked question: its probability, less Exp3's uniform floor."""
    return (p_asked - floor_gamma / n_arms) / (1.0 - floor_gamma)


@st.composite
def _histories(draw: st.DrawFn, n_arms: int) -> list[tuple[int, bool]]:
    """Up to the protocol's 12 answers: which question was asked, and yes or no."""
    step = st.tuples(st.integers(0, n_arms - 1), st.booleans())
    return draw(st.lists(step, max_size=12))


def _replies_along(
    protocol: Protocol, kind: Path | str, history: list[tuple[int, bool]]
) -> list[tuple[str, float, bool, float]]:
    """(line, belief in the asked question, answer, asked probability) per answer."""
    learner, spec, floor = _fresh(kind)
    said = []
    for action, yes in history:
        before = probabilities_list(learner)
        if action >= len(before):
            continue
        learner.update(action, protocol.reward.yes if yes else protocol.reward.no)
        after = probabilities_list(learner)
        reply = choose_reply(
            protocol, spec, before=before, action=action, after=after, said_yes=yes
        )
        said.append((reply.text, _belief(before[action], floor, len(before)), yes, before[action]))
    return said


LEARNERS: list[Path | str] = ["exp3", *CHECKPOINTS]


def _name(kind: Path | str) -> str:
    return kind if isinstance(kind, str) else str(kind.relative_to(PRETRAINED_DIR))


@pytest.mark.parametrize("kind", LEARNERS, ids=_name)
@settings(max_examples=15, deadline=None)
@given(history=_histories(10))
def test_the_shipped_reply_never_contradicts_the_answer(
    kind: Path | str, history: list[tuple[int, bool]]
) -> None:
    """Doubt exactly when the robot found the answer unlikely (it believed the other one), and
    "I knew you would say so" never then."""
    for line, belief, yes, _ in _replies_along(SHIPPED, kind, history):
        surprised = belief < 0.5 if yes else belief > 0.5
        assert (line == DOUBT) == surprised, (line, belief, yes)
        assert not (surprised and line == KNEW)


@pytest.mark.parametrize("kind", LEARNERS, ids=_name)
@settings(max_examples=15, deadline=None)
@given(history=_histories(10))
def test_the_replication_setting_says_what_it_always_said(
    kind: Path | str, history: list[tuple[int, bool]]
) -> None:
    """basis = "chosen" gives the line of the probability the question was asked with, as the
    paper's rule (models.replies.reply_text) always has, whatever the answer."""
    for line, _, _, asked in _replies_along(REPLICATION, kind, history):
        assert line == reply_text(asked)


def test_a_no_to_a_question_c2_was_sure_of_is_not_what_it_knew() -> None:
    """The issue's demo: C2 sure of a question, the participant says no."""
    learner, spec, _ = _fresh(PRETRAINED_DIR / "online" / "conation-k4")
    for _ in range(3):
        learner.update(0, 1.0)
    before = probabilities_list(learner)
    assert before[0] >= 0.8
    learner.update(0, 0.0)
    after = probabilities_list(learner)
    heard = choose_reply(SHIPPED, spec, before=before, action=0, after=after, said_yes=False)
    paper = choose_reply(REPLICATION, spec, before=before, action=0, after=after, said_yes=False)
    assert (paper.text, heard.text) == (KNEW, DOUBT)
    assert heard.probability == pytest.approx(1.0 - (0.05 + 0.9 * before[0]))
