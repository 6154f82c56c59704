"""The Bayesian reference: the exact posterior over which question the participant prefers.

Under the task distribution (:mod:`models.tasks`) the only unknown is which question is preferred.
After rewards ``r_1..r_t`` on questions ``a_1..a_t``, the posterior that question i is preferred::

    P(i | data) ∝ prior_i · Π_t N(r_t; μ_pref if a_t = i else μ_other, σ²)

and the learner acts by posterior sampling (ask question i with probability P(i | data)), so its
``probabilities()`` are the posterior itself. No policy can do much better on this distribution,
which makes it the yardstick for C2 (issue 3: C2 within 1.25 × its answers-to-95 %). It knows the
true reward model. A ``bayes`` condition of a protocol that declares the paper's model runs it
(models/learners/exact.py); for real yes/no answers the exact filter is the forward filter of
models/learners/belief.py.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from models.learners.base import (
    check_action,
    check_n_arms,
    check_reward,
    check_state_header,
    sample_index,
)
from models.tasks import TaskDistribution

_KIND = "bayes"
_VERSION = 1


class BayesLearner:
    """Exact posterior over the preferred question, acting by posterior sampling.

    Parameters
    ----------
    tasks
        The task distribution whose prior and reward model the posterior uses.
    """

    def __init__(self, tasks: TaskDistribution) -> None:
        self.tasks = tasks
        self.n_arms = check_n_arms(tasks.n_arms)
        with np.errstate(divide="ignore"):
            self._initial = np.log(tasks.prior)
        self._log_posterior = self._initial.copy()
        self._answers = 0

    def probabilities(self) -> np.ndarray:
        """The posterior probability that each question is the preferred one."""
        z = np.exp(self._log_posterior - self._log_posterior.max())
        return z / z.sum()

    def select(self, rng: np.random.Generator) -> int:
        """Posterior sampling: draw the question to ask from the posterior (one uniform)."""
        return sample_index(self.probabilities(), rng)

    def update(self, action: int, reward: float) -> None:
        """Multiply in the likelihood of ``reward`` on ``action`` under every hypothesis.

        Raises
        ------
        ValueError
            If ``action`` is out of range or ``reward`` is NaN or infinite.
        """
        a = check_action(action, self.n_arms)
        r = check_reward(reward)
        t = self.tasks
        log_lik = np.full(self.n_arms, -((r - t.mu_other) ** 2) / (2 * t.variance))
        log_lik[a] = -((r - t.mu_preferred) ** 2) / (2 * t.variance)
        posterior = self._log_posterior + log_lik
        self._log_posterior = posterior - posterior.max()
        self._answers += 1

    def state_dict(self) -> dict[str, Any]:
        """``{"kind", "version", "n_arms", "answers", "log_posterior"}`` as plain JSON.

        An impossible question (prior 0) is stored as ``null``: JSON has no −∞.
        """
        return {
            "kind": _KIND,
            "version": _VERSION,
            "n_arms": self.n_arms,
            "answers": self._answers,
            "log_posterior": [float(v) if np.isfinite(v) else None for v in self._log_posterior],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state from :meth:`state_dict`.

        Raises
        ------
        ValueError
            If the state is for another learner or K, or its posterior is malformed.
        """
        check_state_header(state, _KIND, self.n_arms)
        if state.get("version") != _VERSION:
            raise ValueError(f"bayes state version {state.get('version')!r} is not {_VERSION}")
        try:
            values = [-np.inf if v is None else float(v) for v in state["log_posterior"]]
            answers = int(state["answers"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"bayes state is malformed: {exc}") from None
        log_posterior = np.asarray(values, dtype=np.float64)
        if log_posterior.shape != (self.n_arms,) or not np.any(np.isfinite(log_posterior)):
            raise ValueError(f"bayes state needs {self.n_arms} log-probabilities, one finite")
        if np.any(np.isnan(log_posterior)) or np.any(log_posterior == np.inf) or answers < 0:
            raise ValueError("bayes state has NaN, +inf or a negative answer count")
        self._log_posterior = log_posterior
        self._answers = answers

    def __repr__(self) -> str:
        return f"BayesLearner(n_arms={self.n_arms}, answers={self._answers})"
