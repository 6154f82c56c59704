"""The bandit tasks meta-training and the simulations draw participants from.

A task is one simulated participant in one category: K questions, one of which the participant
prefers. The paper's simulated feedback gives the preferred question's reward ~ N(1, σ²) and every
other question's ~ N(0, σ²), σ² = 0.1 (DESIGN.md, "The protocol"). Which question is preferred is
uniform over K unless a protocol supplies a prior (e.g. the rules tell every participant they "need
the second key", so cognition's second question is far more likely).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.learners.base import check_n_arms

DEFAULT_VARIANCE = 0.1
"""σ² of the simulated rewards (the paper's feedback model)."""


def check_prior(prior: Sequence[float] | np.ndarray | None, n_arms: int) -> np.ndarray:
    """Return ``prior`` normalised to sum to one (uniform if ``None``) after checking it.

    Raises
    ------
    ValueError
        If it does not have ``n_arms`` finite non-negative entries with a positive sum.
    """
    if prior is None:
        return np.full(n_arms, 1.0 / n_arms)
    values = np.asarray(prior, dtype=np.float64)
    if values.shape != (n_arms,):
        raise ValueError(f"preferred prior needs {n_arms} numbers, got {values.size}")
    if not np.all(np.isfinite(values)) or np.any(values < 0) or values.sum() <= 0:
        raise ValueError(
            f"preferred prior must be non-negative numbers with a positive sum: {prior}"
        )
    return values / values.sum()


@dataclass(frozen=True)
class TaskDistribution:
    """K-armed Gaussian bandits with one preferred arm.

    Attributes
    ----------
    n_arms
        K.
    preferred_prior
        Probability that each question is the preferred one (uniform by default).
    mu_preferred, mu_other
        Mean reward of the preferred question and of the others.
    variance
        σ² of every reward.
    """

    n_arms: int
    preferred_prior: tuple[float, ...] | None = None
    mu_preferred: float = 1.0
    mu_other: float = 0.0
    variance: float = DEFAULT_VARIANCE

    def __post_init__(self) -> None:
        check_n_arms(self.n_arms)
        check_prior(self.preferred_prior, self.n_arms)
        for name in ("mu_preferred", "mu_other"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")
        if not (math.isfinite(self.variance) and self.variance > 0):
            raise ValueError(f"reward variance must be positive, got {self.variance!r}")

    @property
    def prior(self) -> np.ndarray:
        """The normalised prior over the preferred question."""
        return check_prior(self.preferred_prior, self.n_arms)

    def sample_preferred(self, rng: np.random.Generator, size: int) -> np.ndarray:
        """Draw the preferred question of ``size`` participants."""
        return rng.choice(self.n_arms, size=size, p=self.prior)

    def means(self, preferred: np.ndarray) -> np.ndarray:
        """Mean reward of every question for each participant (…, K)."""
        hit = np.asarray(preferred)[..., None] == np.arange(self.n_arms)
        return np.where(hit, self.mu_preferred, self.mu_other)

    def rewards(
        self, rng: np.random.Generator, preferred: np.ndarray, actions: np.ndarray
    ) -> np.ndarray:
        """Draw the rewards of asking ``actions`` to participants preferring ``preferred``."""
        preferred = np.asarray(preferred)
        actions = np.asarray(actions)
        mean = np.where(actions == preferred, self.mu_preferred, self.mu_other)
        return mean + math.sqrt(self.variance) * rng.standard_normal(np.shape(mean))
