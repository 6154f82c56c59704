"""The exact learner a ``bayes`` condition runs (issue 36): which filter for which feedback model,
its state round-tripping bit for bit, and the models it cannot run with as a live condition."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.feedback import FeedbackModel
from models.learners.bayes import BayesLearner
from models.learners.belief import BeliefLearner
from models.learners.exact import exact_learner, unsupported

SHIPPED = FeedbackModel(slips=(0.0, 0.025, 0.05, 0.075, 0.1), slip_weights=(0.2,) * 5, hazard=0.02)
MODELS = {
    "paper": FeedbackModel.paper(),
    "shipped": SHIPPED,
    "binary hazard": FeedbackModel(hazard=0.05),
    "gaussian slips": FeedbackModel(kind="gaussian", slips=(0.0, 0.1), slip_weights=(0.5, 0.5)),
    "other rewards": FeedbackModel(slips=(0.1,), yes=2.0, no=-1.0),
}


def test_the_paper_model_gets_the_bayes_posterior_and_the_others_the_forward_filter() -> None:
    assert isinstance(exact_learner(4, MODELS["paper"]), BayesLearner)
    for name in ("shipped", "binary hazard", "gaussian slips"):
        assert isinstance(exact_learner(4, MODELS[name]), BeliefLearner)
    # Where both are exact, they are the same posterior (here with a skewed prior and the
    # reward map's own values as the Gaussian means).
    paper = FeedbackModel(kind="gaussian", yes=2.0, no=-1.0, variance=0.5)
    prior = [0.1, 0.2, 0.3, 0.4]
    bayes, belief = exact_learner(4, paper, prior), BeliefLearner(4, paper, np.array(prior))
    for action, reward in [(0, -1.0), (3, 2.0), (3, -1.0), (1, 2.0)]:
        bayes.update(action, reward)
        belief.update(action, reward)
        assert np.allclose(bayes.probabilities(), belief.probabilities(), rtol=1e-12)


def _bits(state: Any) -> Any:
    """The state with every float as its exact bits (so -0.0 and 0.0 differ, as do NaNs)."""
    if isinstance(state, dict):
        return {key: _bits(value) for key, value in state.items()}
    if isinstance(state, list):
        return [_bits(value) for value in state]
    return state.hex() if isinstance(state, float) else state


@settings(max_examples=40, deadline=None)
@given(
    name=st.sampled_from(sorted(MODELS)),
    prior=st.none() | st.lists(st.floats(0.05, 1.0), min_size=4, max_size=4),
    history=st.lists(st.tuples(st.integers(0, 3), st.booleans()), max_size=14),
)
def test_state_round_trips_through_json_bit_for_bit(
    name: str, prior: list[float] | None, history: list[tuple[int, bool]]
) -> None:
    feedback = MODELS[name]
    learner = exact_learner(4, feedback, prior)
    for action, said_yes in history:
        learner.update(action, feedback.yes if said_yes else feedback.no)
    state = learner.state_dict()
    restored = exact_learner(4, feedback, prior)
    restored.load_state_dict(json.loads(json.dumps(state)))
    assert _bits(restored.state_dict()) == _bits(state)
    assert restored.probabilities().tobytes() == learner.probabilities().tobytes()
    learner.update(2, feedback.no)
    restored.update(2, feedback.no)
    assert _bits(restored.state_dict()) == _bits(learner.state_dict())


@pytest.mark.parametrize(
    ("feedback", "attribute", "reason"),
    [
        (FeedbackModel(), "slips", "certain after one yes"),
        (FeedbackModel(slips=(0.0, 0.1), slip_weights=(1.0, 0.0)), "slips", "never slip"),
        (FeedbackModel(kind="gaussian", variance=1e-310), "variance", "too small"),
    ],
    ids=["binary, no slips, no hazard", "slips of weight 0", "gaussian σ² underflows"],
)
def test_models_under_which_an_answer_can_be_impossible_are_unsupported(
    feedback: FeedbackModel, attribute: str, reason: str
) -> None:
    [(found, why)] = unsupported(feedback)
    assert found == attribute
    assert reason in why


def test_every_other_model_is_supported() -> None:
    assert all(unsupported(model) == [] for model in MODELS.values())
    assert unsupported(FeedbackModel(kind="gaussian", variance=1e-300)) == []
