"""The feedback model and the exact reference for it (issue 19): the forward filter against
brute-force enumeration of every hidden path, against the plain Bayes posterior where they must
agree, and on the participants the plain posterior fails."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from models.feedback import FeedbackModel, acceptable_sets, draw_other, switch_matrix
from models.learners.base import Learner
from models.learners.bayes import BayesLearner
from models.learners.belief import BatchBelief, BeliefLearner
from models.tasks import TaskDistribution


def _brute_force(
    feedback: FeedbackModel, prior: np.ndarray, answers: list[tuple[int, float]]
) -> np.ndarray:
    """P(preferred at the next answer | answers), summing over every slip rate and every
    sequence of preferred questions (K^(T+1) paths)."""
    k = prior.size
    switch = switch_matrix(prior, feedback.hazard)
    predictive = np.zeros(k)
    for slip, weight in zip(feedback.slips, feedback.slip_weights, strict=True):
        for path in itertools.product(range(k), repeat=len(answers) + 1):
            p = weight * prior[path[0]]
            for t, (action, reward) in enumerate(answers):
                p *= float(feedback.likelihood(np.array(reward), np.array(action == path[t]), slip))
                p *= switch[path[t], path[t + 1]]
            predictive[path[-1]] += p
    return predictive / predictive.sum()


MODELS = [
    FeedbackModel(slips=(0.1,), hazard=0.0),
    FeedbackModel(slips=(0.0, 0.05, 0.15), slip_weights=(0.5, 0.3, 0.2), hazard=0.1),
    FeedbackModel.with_uniform_slips(0.0, 0.15, points=4, hazard=0.05),
    FeedbackModel(kind="gaussian", slips=(0.0, 0.2), slip_weights=(0.6, 0.4), hazard=0.2),
]


@pytest.mark.parametrize("feedback", MODELS, ids=["slips", "prior+hazard", "grid", "gaussian"])
@pytest.mark.parametrize("prior", [[1 / 3] * 3, [0.6, 0.3, 0.1]], ids=["uniform", "skewed"])
def test_the_filter_equals_brute_force_enumeration(
    feedback: FeedbackModel, prior: list[float]
) -> None:
    rng = np.random.default_rng(7)
    learner = BeliefLearner(3, feedback, np.array(prior))
    assert np.allclose(learner.probabilities(), prior)
    answers: list[tuple[int, float]] = []
    for _ in range(5):
        action = int(rng.integers(3))
        reward = float(rng.choice([0.0, 1.0]))
        if feedback.kind == "gaussian":
            reward += float(rng.normal(0, 0.3))
        learner.update(action, reward)
        answers.append((action, reward))
        expected = _brute_force(feedback, np.array(prior), answers)
        assert np.allclose(learner.probabilities(), expected, rtol=1e-10, atol=1e-12)


def _brute_force_sets(
    feedback: FeedbackModel,
    members: np.ndarray,
    weights: np.ndarray,
    answers: list[tuple[int, float]],
) -> np.ndarray:
    """As :func:`_brute_force`, over sets of acceptable questions; returns P(ask each question)."""
    switch = switch_matrix(weights, feedback.hazard)
    predictive = np.zeros(len(weights))
    for slip, weight in zip(feedback.slips, feedback.slip_weights, strict=True):
        for path in itertools.product(range(len(weights)), repeat=len(answers) + 1):
            p = weight * weights[path[0]]
            for t, (action, reward) in enumerate(answers):
                hit = np.array(members[path[t], action])
                p *= float(feedback.likelihood(np.array(reward), hit, slip))
                p *= switch[path[t], path[t + 1]]
            predictive[path[-1]] += p
    return (predictive / predictive.sum()) @ members / members[0].sum()


def test_participants_who_accept_several_questions_are_filtered_over_sets() -> None:
    consistent = BeliefLearner(4, FeedbackModel(), acceptable=2)
    consistent.update(0, 1.0)  # yes to question 0
    consistent.update(1, 0.0)  # no to question 1: the set is {0, 2} or {0, 3}
    assert np.allclose(consistent.probabilities(), [0.5, 0.0, 0.25, 0.25])
    feedback = FeedbackModel(slips=(0.0, 0.1), slip_weights=(0.5, 0.5), hazard=0.1)
    prior = np.array([0.4, 0.3, 0.2, 0.1])
    learner = BeliefLearner(4, feedback, prior, acceptable=2)
    members, weights = acceptable_sets(prior, 2)
    answers = [(0, 1.0), (1, 0.0), (3, 1.0)]
    for action, reward in answers:
        learner.update(action, reward)
    expected = _brute_force_sets(feedback, members, weights, answers)
    assert np.allclose(learner.probabilities(), expected, rtol=1e-10)
    with pytest.raises(ValueError, match="between 1 and 3"):
        acceptable_sets(prior, 4)


def test_without_slips_or_changes_it_is_the_bayes_posterior() -> None:
    rng = np.random.default_rng(3)
    tasks = TaskDistribution(4, variance=0.1)
    bayes, belief = BayesLearner(tasks), BeliefLearner(4, FeedbackModel.paper(0.1))
    for _ in range(12):
        action = int(rng.integers(4))
        reward = float(rng.normal(action == 2, math.sqrt(0.1)))
        bayes.update(action, reward)
        belief.update(action, reward)
        assert np.allclose(bayes.probabilities(), belief.probabilities(), rtol=1e-9)


def test_with_slips_a_run_of_noes_undoes_a_run_of_yeses() -> None:
    """The saturation case of the issue: after five consistent yeses, three noes in a row must
    bring the probability below one half (the plain posterior never leaves it)."""
    feedback = FeedbackModel.with_uniform_slips(0.0, 0.15, hazard=0.02)
    belief, plain = BeliefLearner(4, feedback), BeliefLearner(4, FeedbackModel())
    for learner in (belief, plain):
        for _ in range(5):
            learner.update(1, 1.0)
    assert belief.probabilities()[1] > 0.95
    for learner in (belief, plain):
        for _ in range(3):
            learner.update(1, 0.0)
    assert belief.probabilities()[1] < 0.5
    # without slips the model cannot explain a "no" to the question it is certain of: no
    # posterior exists, so it ignores the answer and never leaves its belief
    assert plain.probabilities()[1] == 1.0


def test_the_batch_filter_is_the_learner_row_by_row() -> None:
    feedback = MODELS[1]
    rng = np.random.default_rng(11)
    batch = BatchBelief(5, 3, feedback)
    singles = [BeliefLearner(3, feedback) for _ in range(5)]
    for _ in range(6):
        actions = rng.integers(3, size=5)
        rewards = rng.choice([0.0, 1.0], size=5)
        batch.update(actions, rewards)
        for learner, a, r in zip(singles, actions, rewards, strict=True):
            learner.update(int(a), float(r))
    assert np.allclose(batch.probabilities(), [s.probabilities() for s in singles], rtol=1e-12)


def test_state_round_trips_bitwise_through_json() -> None:
    feedback = FeedbackModel(slips=(0.0, 0.1), slip_weights=(0.5, 0.5), hazard=0.05)
    learner = BeliefLearner(4, feedback, np.array([0.0, 0.5, 0.25, 0.25]))  # one impossible
    assert isinstance(learner, Learner)
    for action, reward in [(1, 1.0), (2, 0.0), (1, 0.0)]:
        learner.update(action, reward)
    restored = BeliefLearner(4, feedback, np.array([0.0, 0.5, 0.25, 0.25]))
    restored.load_state_dict(json.loads(json.dumps(learner.state_dict())))
    assert restored.probabilities().tobytes() == learner.probabilities().tobytes()
    learner.update(3, 1.0)
    restored.update(3, 1.0)
    assert restored.probabilities().tobytes() == learner.probabilities().tobytes()
    with pytest.raises(ValueError, match="needs 2×4 values"):
        restored.load_state_dict({**learner.state_dict(), "log_alpha": [[0.0] * 4]})
    with pytest.raises(ValueError, match="version"):
        restored.load_state_dict({**learner.state_dict(), "version": 99})


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"slips": (0.5,)}, r"slip rates must lie in \[0, 0.5\)"),
        ({"slips": (-0.1,)}, "slip rates must lie"),
        ({"slips": (0.1, 0.2), "slip_weights": (0.5, 0.6)}, "sum to 1"),
        ({"slips": (0.1, 0.2), "slip_weights": (1.0,)}, "as many weights"),
        ({"hazard": -0.01}, r"hazard must lie in \[0, 1\)"),
        ({"kind": "likert"}, "'binary' or 'gaussian'"),
        ({"yes": 1.0, "no": 1.0}, "two numbers"),
    ],
)
def test_an_impossible_feedback_model_is_refused(
    arguments: dict[str, object], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        FeedbackModel(**arguments)  # type: ignore[arg-type]


def test_simulated_participants_slip_and_change_at_the_declared_rates() -> None:
    rng = np.random.default_rng(5)
    feedback = FeedbackModel(slips=(0.1,), hazard=0.2)
    n = 200_000
    preferred = np.zeros(n, dtype=int)
    said_yes = feedback.rewards(rng, np.ones(n, dtype=bool), feedback.sample_slips(rng, n))
    assert abs((said_yes == 0.0).mean() - 0.1) < 0.005  # a hit answered "no": a slip
    moved = feedback.change_preference(rng, preferred, np.full(4, 0.25))
    assert abs((moved != 0).mean() - 0.2) < 0.005
    assert np.allclose(
        np.bincount(moved[moved != 0], minlength=4)[1:] / (moved != 0).sum(), 1 / 3, atol=0.01
    )
    others = draw_other(rng, np.full(n, 2), np.array([0.7, 0.1, 0.1, 0.1]))
    assert 2 not in set(others.tolist())
    assert abs((others == 0).mean() - 0.7 / 0.9) < 0.005
