"""Simulations: batch learners equal the deployed classes; the summary figures; seeding."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from models.checkpoints import Checkpoint
from models.feedback import FeedbackModel
from models.learners.bayes import BayesLearner
from models.learners.belief import BatchBelief
from models.learners.exp3 import Exp3
from models.learners.meta_policy import MetaPolicyLearner
from models.simulate import (
    BatchBayes,
    BatchExp3,
    BatchMetaPolicy,
    Scenario,
    Trajectories,
    random_init_params,
    reply_level_shares,
    run,
    sample_actions,
    simulate_adaptation,
    simulate_learner,
    summarise,
)
from models.tasks import TaskDistribution


def _feed(batch, singles, rng: np.random.Generator) -> None:  # type: ignore[no-untyped-def]
    """Feed the same answers to the batch learner and to one class instance per row."""
    for _ in range(6):
        actions = rng.integers(0, 4, size=len(singles))
        rewards = rng.normal(0.4, 0.6, size=len(singles))
        batch.update(actions, rewards)
        for i, single in enumerate(singles):
            single.update(int(actions[i]), float(rewards[i]))
        expected = np.stack([s.probabilities() for s in singles])
        np.testing.assert_allclose(batch.probabilities(), expected, rtol=1e-10, atol=1e-13)


def test_batch_exp3_equals_exp3() -> None:
    _feed(BatchExp3(3, 4, 0.3), [Exp3(4, gamma=0.3) for _ in range(3)], np.random.default_rng(0))


def test_batch_bayes_equals_bayes() -> None:
    tasks = TaskDistribution(4, preferred_prior=(0.1, 0.2, 0.3, 0.4))
    _feed(BatchBayes(3, tasks), [BayesLearner(tasks) for _ in range(3)], np.random.default_rng(1))


def test_batch_meta_policy_equals_the_learner(checkpoint: Checkpoint) -> None:
    singles = [MetaPolicyLearner(checkpoint) for _ in range(3)]
    _feed(BatchMetaPolicy(checkpoint), singles, np.random.default_rng(2))
    params = random_init_params(checkpoint, 3, np.random.default_rng(5))
    rng = np.random.default_rng(5)
    randoms = [MetaPolicyLearner.random_init(checkpoint, rng) for _ in range(3)]
    _feed(BatchMetaPolicy(checkpoint, params), randoms, np.random.default_rng(3))


def test_sample_actions_follows_the_probabilities() -> None:
    probs = np.tile([0.1, 0.6, 0.3], (60_000, 1))
    counts = np.bincount(sample_actions(probs, np.random.default_rng(0)), minlength=3) / 60_000
    np.testing.assert_allclose(counts, [0.1, 0.6, 0.3], atol=0.01)


def test_summary_by_hand() -> None:
    # Participant 0 reaches .95 after 2 answers; 1 never (counts as T + 1 = 4); 2 at once (0)
    # and participant 1 has another question reach .95: wrong_95 = 1/3.
    p = np.array([[0.3, 0.6, 0.96, 0.99], [0.3, 0.2, 0.1, 0.01], [0.95, 0.97, 0.98, 0.99]])
    other = np.array([[0.3, 0.2, 0.02, 0.0], [0.3, 0.5, 0.9, 0.96], [0.01, 0.01, 0.0, 0.0]])
    summary = summarise(Trajectories(np.zeros(3, dtype=int), p, other))
    assert summary["iterations_to_95"] == pytest.approx((2 + 4 + 0) / 3)
    assert summary["reached_95"] == pytest.approx(2 / 3)
    assert summary["wrong_95"] == pytest.approx(1 / 3)
    assert summary["p_correct"] == pytest.approx(p.mean(axis=0).tolist())


def test_same_seed_same_run_and_learners_see_the_same_participants(
    checkpoint: Checkpoint,
) -> None:
    tasks = TaskDistribution(4)
    args: dict[str, Any] = {
        "participants": 300,
        "iterations": 5,
        "seed": 9,
        "checkpoint": checkpoint,
        "gamma": 0.5,
    }
    assert simulate_adaptation(tasks, **args) == simulate_adaptation(tasks, **args)
    assert simulate_adaptation(tasks, **{**args, "seed": 10}) != simulate_adaptation(tasks, **args)
    a = simulate_learner("exp3", tasks, participants=50, iterations=3, seed=1, gamma=0.5)
    b = simulate_learner("bayes", tasks, participants=50, iterations=3, seed=1)
    assert np.array_equal(a.preferred, b.preferred)


def test_bayes_learns_and_exp3_at_half_gamma_never_reaches_95() -> None:
    tasks = TaskDistribution(4)
    bayes = summarise(simulate_learner("bayes", tasks, participants=2000, iterations=12, seed=0))
    exp3 = summarise(
        simulate_learner("exp3", tasks, participants=2000, iterations=12, seed=0, gamma=0.5)
    )
    assert bayes["reached_95"] > 0.97
    assert bayes["p_correct"][12] > 0.95
    assert exp3["reached_95"] == 0.0
    assert max(exp3["p_correct"]) <= 0.625 + 1e-12  # (1 − γ) + γ/K at γ = .5, K = 4


def test_bad_arguments_are_refused(checkpoint: Checkpoint) -> None:
    tasks = TaskDistribution(3)
    with pytest.raises(ValueError, match="unknown learner"):
        simulate_learner("ucb", tasks, participants=5, iterations=2, seed=0)
    with pytest.raises(ValueError, match="4 questions"):
        simulate_learner("meta", tasks, participants=5, iterations=2, seed=0, checkpoint=checkpoint)
    with pytest.raises(ValueError, match="at least 1"):
        simulate_learner("bayes", tasks, participants=0, iterations=2, seed=0)


def test_participants_who_slip_get_the_filter_as_their_reference() -> None:
    """With slips the exact reference is the forward filter: the plain posterior, which assumes
    nobody slips, is confidently wrong far more often on the same participants."""
    tasks = TaskDistribution(4)
    slipping = Scenario(feedback=FeedbackModel(slips=(0.1,)))
    args: dict[str, Any] = {"participants": 3000, "iterations": 12, "seed": 4}
    plain = summarise(
        simulate_learner("bayes", tasks, **args, scenario=Scenario(feedback=FeedbackModel()))
    )
    # the plain posterior's view on slipping participants: run BatchBayes by its own kind
    naive = summarise(
        run(
            BatchBelief(3000, 4, FeedbackModel()),
            tasks,
            np.zeros(3000, dtype=int),
            12,
            np.random.default_rng(4),
            slipping,
        )
    )
    exact = summarise(simulate_learner("bayes", tasks, **args, scenario=slipping))
    assert plain["wrong_95"] == 0.0  # consistent answers: never confidently wrong
    assert exact["wrong_95"] < 0.05 < naive["wrong_95"]
    assert exact["reached_95"] > 0.95


def test_a_changed_preference_is_followed_by_the_reference_only_if_it_expects_changes() -> None:
    tasks = TaskDistribution(4)
    args: dict[str, Any] = {"participants": 3000, "iterations": 12, "seed": 5}
    expects = Scenario(feedback=FeedbackModel(hazard=0.02, slips=(0.02,)), change_after=6)
    result = simulate_adaptation(
        tasks, **args, checkpoint=None, gamma=0.5, learners=("exp3", "bayes"), scenario=expects
    )
    reference = result["learners"]["bayes"]
    assert reference["recovered"] > 0.85 and reference["p_new_final"] > 0.85
    assert result["learners"]["exp3"]["recovered"] < reference["recovered"]
    with pytest.raises(ValueError, match="at least 1"):
        Scenario(change_after=0)


def test_reply_level_shares_follow_the_protocols_thresholds() -> None:
    shares = reply_level_shares(np.array([[0.25, 0.5, 0.64, 0.65], [0.79, 0.8, 0.99, 0.1]]))
    assert shares == {"low": 0.25, "medium-low": 0.25, "medium": 0.25, "high": 0.25}
    tasks = TaskDistribution(4)
    exp3 = summarise(
        simulate_learner("exp3", tasks, participants=500, iterations=12, seed=0, gamma=0.5)
    )
    # γ = .5 with four questions never exceeds p = .625: C1 never sounds more than medium-low
    assert exp3["reply_levels"]["medium"] == exp3["reply_levels"]["high"] == 0.0
