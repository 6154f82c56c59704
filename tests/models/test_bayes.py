"""The Bayesian reference learner: exact posterior, posterior sampling, stored state."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from models.learners.bayes import BayesLearner
from models.tasks import TaskDistribution


def test_posterior_matches_bayes_rule_by_hand() -> None:
    learner = BayesLearner(TaskDistribution(3))
    learner.update(0, 0.9)
    # Likelihood ratio of "arm 0 preferred" vs "not": N(0.9; 1, .1) / N(0.9; 0, .1)
    # = exp((0.81 - 0.01) / 0.2) = e^4; the other two hypotheses share the rest.
    expected = np.array([math.exp(4.0), 1.0, 1.0]) / (math.exp(4.0) + 2.0)
    np.testing.assert_allclose(learner.probabilities(), expected, rtol=1e-12)


def test_prior_is_used_and_impossible_arms_stay_impossible() -> None:
    learner = BayesLearner(TaskDistribution(3, preferred_prior=(0.0, 3.0, 1.0)))
    np.testing.assert_allclose(learner.probabilities(), [0.0, 0.75, 0.25])
    learner.update(0, 1.0)
    assert learner.probabilities()[0] == 0.0
    restored = BayesLearner(TaskDistribution(3, preferred_prior=(0.0, 3.0, 1.0)))
    restored.load_state_dict(json.loads(json.dumps(learner.state_dict())))
    assert restored.probabilities().tobytes() == learner.probabilities().tobytes()


def test_concentrates_on_the_preferred_arm() -> None:
    rng = np.random.default_rng(0)
    tasks = TaskDistribution(6)
    learner = BayesLearner(tasks)
    for _ in range(12):
        a = learner.select(rng)
        learner.update(a, float(tasks.rewards(rng, np.array(4), np.array(a))))
    assert learner.probabilities()[4] > 0.99


def test_state_round_trip_is_bitwise() -> None:
    rng = np.random.default_rng(1)
    tasks = TaskDistribution(4)
    learner, copy = BayesLearner(tasks), BayesLearner(tasks)
    for _ in range(3):
        learner.update(learner.select(rng), float(rng.normal()))
    copy.load_state_dict(json.loads(json.dumps(learner.state_dict())))
    learner.update(2, 0.4)
    copy.update(2, 0.4)
    assert learner.probabilities().tobytes() == copy.probabilities().tobytes()


def test_bad_input_is_refused() -> None:
    learner = BayesLearner(TaskDistribution(4))
    with pytest.raises(ValueError, match="reward"):
        learner.update(0, math.nan)
    with pytest.raises(ValueError, match="action"):
        learner.update(4, 1.0)
    with pytest.raises(ValueError, match="preferred prior"):
        TaskDistribution(4, preferred_prior=(1.0, 1.0))
    with pytest.raises(ValueError, match="variance"):
        TaskDistribution(4, variance=0.0)
