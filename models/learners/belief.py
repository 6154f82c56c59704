"""The exact reference for participants who slip and change their minds: an HMM forward filter.

The hidden state is the pair (slip rate s_j, preferred question i). The slip rate is drawn once
from the feedback model's prior and kept; the preferred question follows a Markov switch (after
each answer it changes with the hazard, to another question by the prior: :func:`models.feedback.
switch_matrix`). After rewards r_1..r_t the filter holds::

    α_t(j, i) ∝ P(s_j, z_{t+1} = i | r_1..t)

(the belief about the preference *at the next answer*), updated per answer by multiplying in the
likelihood of the reward under every (j, i) and then applying the switch. Its probabilities are
the marginal over j, and it acts by posterior sampling, as :class:`models.learners.bayes.
BayesLearner` does. With no slips and no hazard it is that learner, exactly. It knows the true
feedback model: the yardstick for C2, and what a ``bayes`` condition runs for every model but the
paper's (models/learners/exact.py). An answer impossible under the model (possible only without
slips) is ignored, since no posterior exists after it; a ``bayes`` condition with such a model is
refused (:func:`models.learners.exact.unsupported`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from models.feedback import FeedbackModel, acceptable_sets, switch_matrix
from models.learners.base import (
    check_action,
    check_n_arms,
    check_reward,
    check_state_header,
    sample_index,
)
from models.tasks import check_prior

_KIND = "belief"
_VERSION = 1


class BatchBelief:
    """The forward filter for ``n`` participants at once: ``log_alpha`` has shape (n, J, S), S
    the hypotheses about what a participant accepts: one question each (S = K, the usual case),
    or every set of ``acceptable`` questions (:func:`models.feedback.acceptable_sets`)."""

    def __init__(
        self,
        n: int,
        n_arms: int,
        feedback: FeedbackModel,
        prior: np.ndarray | None = None,
        acceptable: int = 1,
    ) -> None:
        self.n_arms = check_n_arms(n_arms)
        self.feedback = feedback
        self.prior = check_prior(prior, self.n_arms)
        self.acceptable = acceptable
        self.members, self.set_prior = acceptable_sets(self.prior, acceptable)  # (S, K), (S,)
        self.switch = switch_matrix(self.set_prior, feedback.hazard)
        self._slips = feedback.slip_values[:, None]  # (J, 1)
        with np.errstate(divide="ignore"):
            start = np.log(feedback.slip_prior)[:, None] + np.log(self.set_prior)[None, :]
        self.log_alpha = np.tile(start, (n, 1, 1))

    def set_probabilities(self) -> np.ndarray:
        """(n, S): P(each hypothesis holds at the next answer | the answers so far)."""
        joint = np.exp(self.log_alpha - self.log_alpha.max(axis=(1, 2), keepdims=True))
        marginal = joint.sum(axis=1)
        return marginal / marginal.sum(axis=1, keepdims=True)

    def probabilities(self) -> np.ndarray:
        """(n, K): posterior sampling's chance of asking each question: draw a hypothesis, ask
        one of its questions at random (for one acceptable question: P(preferred = each))."""
        return (self.set_probabilities() @ self.members) / self.acceptable

    def update(self, actions: np.ndarray, rewards: np.ndarray) -> None:
        """One answer each: the likelihood under every (slip, hypothesis), then the switch."""
        hit = self.members.T[np.asarray(actions)][:, None, :]  # (n, 1, S)
        likelihood = self.feedback.likelihood(
            np.asarray(rewards, np.float64)[:, None, None], hit, self._slips[None]
        )
        with np.errstate(divide="ignore"):
            posterior = self.log_alpha + np.log(likelihood)
        # An answer the model says cannot happen (no slips, and a "no" to the question it is
        # certain of) leaves that participant's belief as it was: the posterior is undefined.
        impossible = ~np.isfinite(posterior.max(axis=(1, 2)))
        posterior[impossible] = self.log_alpha[impossible]
        posterior -= posterior.max(axis=(1, 2), keepdims=True)
        if self.feedback.hazard > 0:
            with np.errstate(divide="ignore"):
                posterior = np.log(np.exp(posterior) @ self.switch)
        self.log_alpha = posterior - posterior.max(axis=(1, 2), keepdims=True)


class BeliefLearner:
    """The forward filter for one participant, with the interface every learner offers.

    Parameters
    ----------
    n_arms
        K.
    feedback
        The feedback model whose slips and hazard the filter assumes.
    prior
        Prior over the preferred question (uniform if None).
    acceptable
        How many questions a participant says yes to (1: one preferred question).
    """

    def __init__(
        self,
        n_arms: int,
        feedback: FeedbackModel,
        prior: np.ndarray | None = None,
        acceptable: int = 1,
    ) -> None:
        self._batch = BatchBelief(1, n_arms, feedback, prior, acceptable)
        self.n_arms = self._batch.n_arms
        self._answers = 0

    def probabilities(self) -> np.ndarray:
        """P(each question is preferred at the next answer)."""
        return self._batch.probabilities()[0]

    def select(self, rng: np.random.Generator) -> int:
        """Posterior sampling (one uniform)."""
        return sample_index(self.probabilities(), rng)

    def update(self, action: int, reward: float) -> None:
        """Learn from one answer (ValueError for an out-of-range action or a non-finite reward)."""
        a = check_action(action, self.n_arms)
        r = check_reward(reward)
        self._batch.update(np.array([a]), np.array([r]))
        self._answers += 1

    def state_dict(self) -> dict[str, Any]:
        """``{"kind", "version", "n_arms", "answers", "log_alpha"}`` (−∞ stored as null)."""
        return {
            "kind": _KIND,
            "version": _VERSION,
            "n_arms": self.n_arms,
            "answers": self._answers,
            "log_alpha": [
                [float(v) if np.isfinite(v) else None for v in row]
                for row in self._batch.log_alpha[0]
            ],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state from :meth:`state_dict` (ValueError if it does not fit this filter)."""
        check_state_header(state, _KIND, self.n_arms)
        if state.get("version") != _VERSION:
            raise ValueError(f"belief state version {state.get('version')!r} is not {_VERSION}")
        try:
            rows = [[-np.inf if v is None else float(v) for v in row] for row in state["log_alpha"]]
            answers = int(state["answers"])
            values = np.asarray(rows, dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"belief state is malformed: {exc}") from None
        expected = self._batch.log_alpha.shape[1:]
        if values.shape != expected or not np.any(np.isfinite(values)):
            raise ValueError(f"belief state needs {expected[0]}×{expected[1]} values, one finite")
        if np.any(np.isnan(values)) or np.any(values == np.inf) or answers < 0:
            raise ValueError("belief state has NaN, +inf or a negative answer count")
        self._batch.log_alpha = values[None].copy()
        self._answers = answers

    def __repr__(self) -> str:
        return f"BeliefLearner(n_arms={self.n_arms}, answers={self._answers})"
