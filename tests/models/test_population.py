"""Fitting a population (prior, slip rate, hazard) from logged answers by EM (issue 20)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from models.feedback import FeedbackModel, switch_matrix
from models.population import (
    MIN_PARTICIPANTS,
    AnswerSequences,
    CategoryFit,
    bootstrap,
    fit_category,
)


def _simulate(
    rng: np.random.Generator, n: int, prior: list[float], slip: float, hazard: float, t: int = 12
) -> AnswerSequences:
    """Participants of a known population, asked questions at random."""
    model = FeedbackModel(slips=(slip,), hazard=hazard)
    k = len(prior)
    preferred = rng.choice(k, size=n, p=prior)
    actions = rng.integers(0, k, size=(n, t))
    answers = np.zeros((n, t), dtype=bool)
    for step in range(t):
        answers[:, step] = (actions[:, step] == preferred) != (rng.random(n) < slip)
        preferred = model.change_preference(rng, preferred, np.asarray(prior))
    return AnswerSequences(k, actions, answers)


def _brute_force_log_likelihood(
    seq: AnswerSequences, prior: np.ndarray, slip: float, hazard: float
) -> float:
    """Σ over participants of log Σ over every path of preferred questions."""
    switch = switch_matrix(prior, hazard)
    total = 0.0
    for actions, answers in zip(seq.actions, seq.answers, strict=True):
        steps = [t for t in range(len(actions)) if actions[t] >= 0]
        probability = 0.0
        for path in itertools.product(range(seq.n_arms), repeat=len(steps)):
            p = prior[path[0]]
            for i, t in enumerate(steps):
                if i:
                    p *= switch[path[i - 1], path[i]]
                meant = actions[t] == path[i]
                p *= (1 - slip) if meant == answers[t] else slip
            probability += p
        total += np.log(probability)
    return total


def test_the_likelihood_is_the_sum_over_every_hidden_path() -> None:
    rng = np.random.default_rng(3)
    seq = _simulate(rng, MIN_PARTICIPANTS + 2, [0.5, 0.3, 0.2], 0.1, 0.2, t=5)
    actions = seq.actions.copy()
    actions[0, 3:] = -1  # a participant who stopped early
    seq = AnswerSequences(3, actions, seq.answers)
    fit = fit_category(seq, max_iterations=3)
    expected = _brute_force_log_likelihood(seq, fit.prior, fit.slip, fit.hazard)
    assert fit.log_likelihood == pytest.approx(expected, rel=1e-10)


def test_em_never_lowers_the_likelihood() -> None:
    seq = _simulate(np.random.default_rng(5), 60, [0.55, 0.25, 0.1, 0.1], 0.08, 0.05)
    previous = -np.inf
    for iterations in (1, 2, 4, 8, 16, 32):
        value = fit_category(seq, max_iterations=iterations).log_likelihood
        assert value >= previous - 1e-9
        previous = value


def test_a_known_population_is_recovered() -> None:
    seq = _simulate(np.random.default_rng(7), 4000, [0.7, 0.1, 0.1, 0.1], 0.06, 0.02)
    fit = fit_category(seq)
    assert fit.converged
    np.testing.assert_allclose(fit.prior, [0.7, 0.1, 0.1, 0.1], atol=0.02)
    assert fit.slip == pytest.approx(0.06, abs=0.01)
    assert fit.hazard == pytest.approx(0.02, abs=0.01)


def test_bootstrap_intervals_cover_the_truth_and_shrink_with_more_participants() -> None:
    rng = np.random.default_rng(11)
    widths = []
    for n in (40, 400):
        seq = _simulate(rng, n, [0.6, 0.2, 0.1, 0.1], 0.05, 0.0)
        fit = fit_category(seq)
        calls = [0]

        def tick(counter: list[int] = calls) -> None:
            counter[0] += 1

        intervals = bootstrap(seq, fit, np.random.default_rng(1), replicates=40, progress=tick)
        assert calls[0] == 40 and intervals.replicates == 40
        low, high = intervals.prior[0]
        assert low <= fit.prior[0] <= high
        assert intervals.slip[0] <= fit.slip <= intervals.slip[1]
        widths.append(high - low)
    assert widths[1] < widths[0] / 2


def test_too_few_participants_are_refused_with_the_numbers() -> None:
    seq = _simulate(np.random.default_rng(2), MIN_PARTICIPANTS - 1, [0.5, 0.5], 0.1, 0.0)
    with pytest.raises(ValueError, match=rf"5 participant.*at least {MIN_PARTICIPANTS}"):
        fit_category(seq)
    empty = AnswerSequences(2, np.full((9, 3), -1), np.zeros((9, 3), dtype=bool))
    with pytest.raises(ValueError, match="0 participant"):
        fit_category(empty)


def test_bad_sequences_are_refused() -> None:
    with pytest.raises(ValueError, match=r"outside 0\.\.1"):
        AnswerSequences(2, np.array([[2]]), np.array([[True]]))
    with pytest.raises(ValueError, match="same"):
        AnswerSequences(2, np.array([[0, 1]]), np.array([[True]]))
    start = CategoryFit(np.array([0.5, 0.5]), 0.1, 0.0, 0.0, 0, True)
    seq = _simulate(np.random.default_rng(4), 20, [0.5, 0.5], 0.1, 0.0)
    with pytest.raises(ValueError, match="replicate"):
        bootstrap(seq, start, np.random.default_rng(0), replicates=0)
