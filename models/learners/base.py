"""The one interface every learner offers, and the input checks they share.

The web app drives a learner with exactly these calls, once per answer::

    p = learner.probabilities()          # what the robot believes before asking
    action = learner.select(rng)         # which question to ask
    learner.update(action, reward)       # the participant's answer, mapped to a reward
    row.state = learner.state_dict()     # stored as JSON in the same transaction

and restores a participant's learner with ``load_state_dict(json.loads(row.state))``. The state of
every learner is plain JSON (lists, numbers, strings) and restores bit for bit, so a crashed tablet
or a restarted worker continues exactly where it stopped.
"""

from __future__ import annotations

import math
from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Learner(Protocol):
    """A K-armed bandit learner: one per participant and category.

    Attributes
    ----------
    n_arms
        K, the number of questions the learner chooses from.
    """

    n_arms: int

    def probabilities(self) -> np.ndarray:
        """Return the probability of asking each question next (float64, length K, sums to 1)."""
        ...

    def select(self, rng: np.random.Generator) -> int:
        """Draw the next question from :meth:`probabilities` with ``rng``; does not change state."""
        ...

    def update(self, action: int, reward: float) -> None:
        """Learn from the reward the participant's answer to question ``action`` produced."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Return the learner's state as a JSON-serialisable dict."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state produced by :meth:`state_dict` (bitwise: later updates are identical)."""
        ...


def check_n_arms(n_arms: int) -> int:
    """Return ``n_arms`` as an int after checking a bandit can have that many arms (K ≥ 2)."""
    if isinstance(n_arms, bool) or not isinstance(n_arms, int | np.integer):
        raise ValueError(f"n_arms must be an integer, got {n_arms!r}")
    if n_arms < 2:
        raise ValueError(f"n_arms must be at least 2 (a choice needs two questions), got {n_arms}")
    return int(n_arms)


def check_action(action: int, n_arms: int) -> int:
    """Return ``action`` as an int after checking it names one of the ``n_arms`` questions.

    Raises
    ------
    ValueError
        If ``action`` is not an integer in ``0 .. n_arms - 1``.
    """
    if isinstance(action, bool) or not isinstance(action, int | np.integer):
        raise ValueError(f"action must be an integer arm index, got {action!r}")
    if not 0 <= action < n_arms:
        raise ValueError(f"action {action} is out of range: this learner has arms 0..{n_arms - 1}")
    return int(action)


def check_reward(reward: float) -> float:
    """Return ``reward`` as a float after checking it is a finite number.

    A NaN or infinite reward would silently poison every later probability, so it is refused here
    rather than clipped: it always means a bug in the reward map or a corrupted answer.
    """
    try:
        value = float(reward)
    except (TypeError, ValueError):
        raise ValueError(f"reward must be a number, got {reward!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"reward must be finite, got {value!r}")
    return value


def sample_index(probabilities: np.ndarray, rng: np.random.Generator) -> int:
    """Draw an index with the given probabilities using exactly one uniform from ``rng``.

    One draw per decision keeps a seeded run reproducible whatever the probabilities are, and is
    several times faster than ``rng.choice`` for the handful of arms a study has.
    """
    u = rng.random()
    cumulative = np.cumsum(probabilities)
    index = int(np.searchsorted(cumulative, u * cumulative[-1], side="right"))
    return min(index, len(probabilities) - 1)


def check_state_header(state: dict[str, Any], kind: str, n_arms: int) -> None:
    """Check that ``state`` was produced by a learner of this ``kind`` with ``n_arms`` arms.

    Raises
    ------
    ValueError
        If ``state`` is not a dict, names another kind of learner or another number of arms.
    """
    if not isinstance(state, dict):
        raise ValueError(f"{kind} state must be a dict, got {type(state).__name__}")
    if state.get("kind") != kind:
        raise ValueError(f"state is for a {state.get('kind')!r} learner, not {kind!r}")
    if state.get("n_arms") != n_arms:
        raise ValueError(
            f"{kind} state has n_arms={state.get('n_arms')!r} but this learner has {n_arms} arms"
        )
