"""Exp3 (Auer, Cesa-Bianchi, Freund & Schapire 2002): the study's C1 condition.

Exp3 keeps one weight per question and mixes the normalised weights with a uniform floor::

    p_i = (1 - γ) · w_i / Σ_j w_j + γ / K

After asking question ``a`` and receiving reward ``x`` in [0, 1], only that question's weight moves,
by the importance-weighted reward ``x̂ = x / p_a``::

    w_a ← w_a · exp(γ · x̂ / K)

The weights are renormalised to sum to one after every update. This changes nothing in ``p`` (it is
scale invariant) but keeps the numbers in range however long a learner runs: the factor is at most
``exp(1)`` because ``x̂ ≤ 1 / p_a ≤ K / γ``. There is no forced round-robin over the arms.

Rewards are clipped into [0, 1] after the study's reward map: Exp3's guarantees (and the bound on
the exponent above) hold only for rewards in that range.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from models.learners.base import (
    check_action,
    check_n_arms,
    check_reward,
    check_state_header,
    sample_index,
)

DEFAULT_EXP3_GAMMA = 0.5
"""Default exploration rate γ. See docs/engine.md, "Exp3 γ": over the protocol's 12
answers at K = 4, γ = 0.5 gives the highest mean probability of the preferred question (γ = 0.52 is
also Auer et al.'s horizon-tuned value ``sqrt(K ln K / ((e − 1) T))`` for K = 4, T = 12). A study
that wants C1 to be able to reach the "high" reply level must use γ ≤ 0.2 · K / (K − 1)."""

_KIND = "exp3"
_VERSION = 1


def check_gamma(gamma: float) -> float:
    """Return ``gamma`` as a float after checking it is a valid Exp3 exploration rate in (0, 1]."""
    value = float(gamma)
    if not math.isfinite(value) or not 0.0 < value <= 1.0:
        raise ValueError(f"Exp3 gamma must be in (0, 1], got {gamma!r}")
    return value


class Exp3:
    """Exp3 learner over ``n_arms`` questions with exploration rate ``gamma``.

    Parameters
    ----------
    n_arms
        K ≥ 2, the number of questions.
    gamma
        Exploration rate γ in (0, 1]: the share of probability spread uniformly over all questions
        (γ = 1 never learns; small γ learns slowly because each update moves a weight by at most a
        factor ``exp(γ · x̂ / K)``).
    """

    def __init__(self, n_arms: int, gamma: float = DEFAULT_EXP3_GAMMA) -> None:
        self.n_arms = check_n_arms(n_arms)
        self.gamma = check_gamma(gamma)
        self._weights = np.full(self.n_arms, 1.0 / self.n_arms)
        self._updates = 0

    @property
    def weights(self) -> np.ndarray:
        """A copy of the normalised weights (they sum to one)."""
        return self._weights.copy()

    @property
    def updates(self) -> int:
        """How many answers the learner has learned from."""
        return self._updates

    def probabilities(self) -> np.ndarray:
        """Return ``(1 − γ) · w / Σw + γ / K`` (float64, sums to one, every entry ≥ γ / K)."""
        w = self._weights
        return (1.0 - self.gamma) * (w / w.sum()) + self.gamma / self.n_arms

    def select(self, rng: np.random.Generator) -> int:
        """Draw the next question from :meth:`probabilities` using one uniform from ``rng``."""
        return sample_index(self.probabilities(), rng)

    def update(self, action: int, reward: float) -> None:
        """Apply the Exp3 update for ``reward`` (clipped into [0, 1]) on question ``action``.

        Raises
        ------
        ValueError
            If ``action`` is out of range or ``reward`` is NaN or infinite.
        """
        a = check_action(action, self.n_arms)
        x = min(max(check_reward(reward), 0.0), 1.0)
        p_a = self.probabilities()[a]
        x_hat = x / p_a
        weights = self._weights.copy()
        weights[a] *= math.exp(self.gamma * x_hat / self.n_arms)
        self._weights = weights / weights.sum()
        self._updates += 1

    def state_dict(self) -> dict[str, Any]:
        """Return ``{"kind", "version", "n_arms", "gamma", "updates", "weights"}`` as plain JSON.

        The weights are float64 written as Python floats, whose JSON text round-trips exactly.
        """
        return {
            "kind": _KIND,
            "version": _VERSION,
            "n_arms": self.n_arms,
            "gamma": self.gamma,
            "updates": self._updates,
            "weights": [float(w) for w in self._weights],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state from :meth:`state_dict`.

        Raises
        ------
        ValueError
            If the state belongs to another kind of learner, another K or another γ, or its weights
            are not K positive finite numbers.
        """
        check_state_header(state, _KIND, self.n_arms)
        if state.get("version") != _VERSION:
            raise ValueError(f"exp3 state version {state.get('version')!r} is not {_VERSION}")
        if state.get("gamma") != self.gamma:
            raise ValueError(
                f"exp3 state was made with gamma={state.get('gamma')!r}, this learner has "
                f"gamma={self.gamma!r}"
            )
        try:
            weights = np.asarray(state["weights"], dtype=np.float64)
            updates = int(state["updates"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"exp3 state is malformed: {exc}") from None
        if (
            weights.shape != (self.n_arms,)
            or not np.all(np.isfinite(weights))
            or np.any(weights < 0)
            or weights.sum() <= 0
        ):
            raise ValueError(f"exp3 state weights must be {self.n_arms} non-negative numbers")
        if updates < 0:
            raise ValueError(f"exp3 state has a negative update count {updates}")
        self._weights = weights
        self._updates = updates

    def __repr__(self) -> str:
        return f"Exp3(n_arms={self.n_arms}, gamma={self.gamma}, updates={self._updates})"
