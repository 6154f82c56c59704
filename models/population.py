"""The population a study's participants came from, fitted from its logged answers (issue 20).

Per category the model is the one participants are simulated with (models/feedback.py): each
participant prefers a question drawn from ``prior``, answers yes exactly when asked it except that
each answer slips (says the opposite) with probability ``slip``, and after each answer the
preference changes with probability ``hazard``, to another question drawn by the prior
(:func:`models.feedback.switch_matrix`). A participant's answers in one category are a short
hidden Markov sequence over the preferred question.

The fit is maximum likelihood by EM (Baum–Welch with these three parameters). Which question the
robot asked was chosen by the learner from the answers before it, with the probabilities the step
log records, so the choice carries no information about the preference beyond those answers: the
likelihood of the answers given the questions asked is the full likelihood up to a factor that
does not depend on the parameters, for Exp3 and C2 data alike. The M-step is exact for the slip
rate and the hazard; for the prior it is the expected share of each first preference, holding the
prior inside the switch's destination weights at its previous value (simply adding the switch
destinations to the counts would bias it toward uniform: a switch away from the popular question
must land elsewhere). That conditional step is monotone (tested) and its fixed point is the
maximum-likelihood estimate up to the switch term, negligible at small hazards. Numpy only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from models.feedback import switch_matrix

MIN_PARTICIPANTS = 6
"""Fewer participants than this in a category cannot say anything useful about a population."""


@dataclass(frozen=True)
class AnswerSequences:
    """One category's answers: ``actions[n, t]`` the question asked (−1 past a participant's
    last answer) and ``answers[n, t]`` whether they said yes."""

    n_arms: int
    actions: np.ndarray
    answers: np.ndarray

    def __post_init__(self) -> None:
        if self.actions.shape != self.answers.shape or self.actions.ndim != 2:
            raise ValueError("actions and answers must be two arrays of the same (n, T) shape")
        if np.any(self.actions >= self.n_arms) or np.any(self.actions < -1):
            raise ValueError(f"a question number is outside 0..{self.n_arms - 1}")

    @property
    def observed(self) -> np.ndarray:
        """(n, T) whether there is an answer at t."""
        return self.actions >= 0

    @property
    def participants(self) -> int:
        """Participants with at least one answer."""
        return int(self.observed.any(axis=1).sum())

    def subset(self, rows: np.ndarray) -> AnswerSequences:
        """These participants' sequences (rows may repeat: a bootstrap sample)."""
        return AnswerSequences(self.n_arms, self.actions[rows], self.answers[rows])


@dataclass(frozen=True)
class CategoryFit:
    """The fitted population of one category."""

    prior: np.ndarray
    slip: float
    hazard: float
    log_likelihood: float
    iterations: int
    converged: bool


def _emissions(seq: AnswerSequences, slip: float) -> np.ndarray:
    """(n, T, K): P(answer_t | preferred = k) — 1 where there is no answer."""
    k = np.arange(seq.n_arms)
    hit = seq.actions[..., None] == k
    meant_yes = hit
    agrees = meant_yes == seq.answers[..., None]
    likelihood = np.where(agrees, 1.0 - slip, slip)
    return np.where(seq.observed[..., None], likelihood, 1.0)


def _forward_backward(
    emissions: np.ndarray, prior: np.ndarray, switch: np.ndarray, pairs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Scaled forward–backward over every participant at once.

    Returns the posteriors γ (n, T, K) of the preferred question at each answer, the expected
    transitions ξ (n, K, K) summed over the answered pairs (t, t + 1) marked in ``pairs``
    (n, T − 1), and the log-likelihood of all the answers.
    """
    n, horizon, k = emissions.shape
    alpha = np.empty((n, horizon, k))
    scale = np.empty((n, horizon))
    a = prior[None, :] * emissions[:, 0]
    scale[:, 0] = a.sum(axis=1)
    alpha[:, 0] = a / scale[:, 0:1]
    for t in range(1, horizon):
        a = (alpha[:, t - 1] @ switch) * emissions[:, t]
        scale[:, t] = a.sum(axis=1)
        alpha[:, t] = a / scale[:, t : t + 1]
    beta = np.ones((n, horizon, k))
    for t in range(horizon - 2, -1, -1):
        b = (emissions[:, t + 1] * beta[:, t + 1]) @ switch.T
        beta[:, t] = b / scale[:, t + 1 : t + 2]
    gamma = alpha * beta
    gamma /= gamma.sum(axis=2, keepdims=True)
    xi = np.zeros((n, k, k))
    for t in range(horizon - 1):
        after = (emissions[:, t + 1] * beta[:, t + 1]) / scale[:, t + 1 : t + 2]
        pair = alpha[:, t, :, None] * switch[None] * after[:, None, :]
        xi += pair * pairs[:, t, None, None]
    return gamma, xi, float(np.log(scale).sum())


def fit_category(
    seq: AnswerSequences,
    *,
    start: CategoryFit | None = None,
    max_iterations: int = 500,
    tolerance: float = 1e-9,
) -> CategoryFit:
    """Maximum-likelihood prior, slip rate and hazard of one category by EM.

    Raises
    ------
    ValueError
        With fewer than :data:`MIN_PARTICIPANTS` participants who answered (the message says how
        many there are and how many are needed).
    """
    if seq.participants < MIN_PARTICIPANTS:
        raise ValueError(
            f"{seq.participants} participant(s) answered here; fitting a population needs at "
            f"least {MIN_PARTICIPANTS}"
        )
    k = seq.n_arms
    keep = seq.observed.any(axis=1)
    seq = seq.subset(np.flatnonzero(keep))
    # Pairs (t, t+1) that are both answered: only those are evidence about the hazard.
    pairs = seq.observed[:, :-1] & seq.observed[:, 1:]
    answers = float(seq.observed.sum())
    if start is None:
        prior, slip, hazard = np.full(k, 1.0 / k), 0.1, 0.05
    else:
        prior, slip, hazard = start.prior.copy(), start.slip, start.hazard
    previous = -np.inf
    converged = False
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        switch = switch_matrix(prior, hazard)
        gamma, xi, log_likelihood = _forward_backward(_emissions(seq, slip), prior, switch, pairs)
        stays = float(np.trace(xi.sum(axis=0)))
        moves = float(xi.sum()) - stays
        counts = gamma[:, 0].sum(axis=0)
        prior = np.clip(counts / counts.sum(), 1e-12, None)
        prior /= prior.sum()
        hit = seq.actions[..., None] == np.arange(k)
        slipped = hit != seq.answers[..., None]
        expected_slips = float((gamma * slipped * seq.observed[..., None]).sum())
        slip = min(max(expected_slips / answers, 1e-9), 0.5 - 1e-9)
        hazard = min(max(moves / max(stays + moves, 1e-12), 0.0), 1.0 - 1e-9)
        if abs(log_likelihood - previous) <= tolerance * max(1.0, abs(log_likelihood)):
            converged = True
            break
        previous = log_likelihood
    final = _forward_backward(_emissions(seq, slip), prior, switch_matrix(prior, hazard), pairs)[2]
    return CategoryFit(prior, float(slip), float(hazard), final, iterations, converged)


@dataclass(frozen=True)
class Intervals:
    """Percentile bootstrap intervals (over participants) of a category's fit."""

    prior: np.ndarray  # (K, 2)
    slip: tuple[float, float]
    hazard: tuple[float, float]
    replicates: int
    level: float


def bootstrap(
    seq: AnswerSequences,
    fit: CategoryFit,
    rng: np.random.Generator,
    *,
    replicates: int = 200,
    level: float = 0.95,
    progress: Callable[[], None] | None = None,
) -> Intervals:
    """Refit ``replicates`` resamples of the participants (starting at ``fit``, which makes each
    refit a few iterations) and take the percentile interval of each figure at ``level``.
    ``progress()`` is called after each refit."""
    if replicates < 1 or not 0 < level < 1:
        raise ValueError("a bootstrap needs at least one replicate and a level in (0, 1)")
    rows = np.flatnonzero(seq.observed.any(axis=1))
    priors, slips, hazards = [], [], []
    for _ in range(replicates):
        sample = seq.subset(rng.choice(rows, size=rows.size, replace=True))
        refit = fit_category(sample, start=fit)
        priors.append(refit.prior)
        slips.append(refit.slip)
        hazards.append(refit.hazard)
        if progress is not None:
            progress()
    tails = [50 * (1 - level), 100 - 50 * (1 - level)]
    prior = np.percentile(np.stack(priors), tails, axis=0).T
    slip = np.percentile(slips, tails)
    hazard = np.percentile(hazards, tails)
    return Intervals(
        prior,
        (float(slip[0]), float(slip[1])),
        (float(hazard[0]), float(hazard[1])),
        replicates,
        level,
    )
