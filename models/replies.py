"""The robot's reply to an answer, chosen by a probability the protocol names (its *basis*).

After each answer the robot says one of a few sentences. The protocol fixes thresholds that split
[0, 1] into levels (by default four) and one line per level, or one per level and answer. Which
probability picks the level is the protocol's ``replies.basis``:

``chosen``
    the probability the learner asked the question with: the seed paper's rule and the
    replication setting. It ignores the answer, so after a "no" to a question the robot was sure
    of it says "Awesome, I knew you would say so.".
``updated``
    the question's probability after learning from the answer.
``heard``
    the probability the robot gave to the answer it heard (:func:`heard_probability`): for a yes
    its predicted probability that this participant says yes to this question, for a no the
    complement. The level then says how expected the answer was, so a line for an expected
    answer ("I knew you would say so") never follows an answer the robot found unlikely.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

BASES: tuple[str, str, str] = ("chosen", "updated", "heard")
"""The probabilities a protocol can choose its reply level by (see the module docstring)."""

DEFAULT_THRESHOLDS: tuple[float, float, float] = (0.5, 0.65, 0.8)
"""Protocol defaults: p < .5 low, p < .65 medium-low, p < .8 medium, p ≥ .8 high."""

LEVEL_NAMES: tuple[str, str, str, str] = ("low", "medium-low", "medium", "high")
"""Names of the four levels of the default protocol, indexed by :func:`confidence_level`."""

DEFAULT_REPLIES: tuple[str, str, str, str] = (
    "I do not believe it but fine.",
    "Is that really so? I am not sure.",
    "I understand now.",
    "Awesome, I knew you would say so.",
)
"""The protocol's reply sentences, indexed by :func:`confidence_level`."""


def validate_thresholds(thresholds: Sequence[float]) -> tuple[float, ...]:
    """Return ``thresholds`` as a tuple after checking they can split [0, 1] into levels.

    Raises
    ------
    ValueError
        If there are no thresholds, one is not finite or outside [0, 1], or they do not increase
        strictly (two equal thresholds would make a level that can never be reached).
    """
    values = tuple(float(t) for t in thresholds)
    if not values:
        raise ValueError("confidence thresholds: need at least one threshold")
    for t in values:
        if not math.isfinite(t) or not 0.0 <= t <= 1.0:
            raise ValueError(f"confidence thresholds: {t!r} is not a probability in [0, 1]")
    if any(b <= a for a, b in itertools.pairwise(values)):
        raise ValueError(f"confidence thresholds must increase strictly, got {list(values)}")
    return values


def confidence_level(p: float, thresholds: Sequence[float] = DEFAULT_THRESHOLDS) -> int:
    """Return the index of the confidence level of probability ``p``.

    Level ``i`` holds the probabilities in ``[thresholds[i-1], thresholds[i])``; a probability equal
    to a threshold belongs to the higher level, so with the protocol defaults ``p = .8`` is "high"
    (index 3) and ``p = .5`` is "medium-low" (index 1).

    Parameters
    ----------
    p
        The probability the learner gave the question it asked, in [0, 1].
    thresholds
        Strictly increasing cut points in [0, 1]; ``len(thresholds) + 1`` levels result.

    Raises
    ------
    ValueError
        If ``p`` is not a finite probability or the thresholds are invalid.
    """
    cuts = validate_thresholds(thresholds)
    value = float(p)
    if not math.isfinite(value) or not 0.0 <= value <= 1.0:
        raise ValueError(f"confidence level: p={p!r} is not a probability in [0, 1]")
    return sum(1 for t in cuts if value >= t)


def reply_text(
    p: float,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    replies: Sequence[str] = DEFAULT_REPLIES,
) -> str:
    """Return the reply sentence for probability ``p`` (one sentence per level).

    Raises
    ------
    ValueError
        If ``len(replies)`` is not ``len(thresholds) + 1`` or ``p``/``thresholds`` are invalid.
    """
    if len(replies) != len(thresholds) + 1:
        raise ValueError(
            f"replies: {len(thresholds)} thresholds make {len(thresholds) + 1} levels, "
            f"but {len(replies)} reply texts were given"
        )
    return replies[confidence_level(p, thresholds)]


def exp3_belief(p_asked: float, *, gamma: float, n_arms: int) -> float:
    """Exp3's belief that the asked question is the one the participant says yes to.

    Exp3 asks with ``p = (1 − γ) · w / Σw + γ / K``: the uniform floor ``γ / K`` is exploration it
    adds on purpose, not something it believes about the participant, so its belief is the
    exponential-weights share ``w / Σw = (p − γ / K) / (1 − γ)`` (with γ = 1 it never learns and
    believes the uniform 1 / K). Without removing the floor, a C1 robot at the shipped γ = .5
    could never be more than .625 sure of a yes, however many it had heard.
    """
    return float(exp3_beliefs(np.asarray(p_asked, np.float64), gamma=gamma, n_arms=n_arms))


def exp3_beliefs(p_asked: np.ndarray, *, gamma: float, n_arms: int) -> np.ndarray:
    """:func:`exp3_belief` for an array of asked probabilities (simulations)."""
    if gamma >= 1.0:
        return np.full_like(p_asked, 1.0 / n_arms)
    share = (p_asked - gamma / n_arms) / (1.0 - gamma)
    return np.clip(share, 0.0, 1.0)  # rounding aside, p ≥ γ / K and share ≤ 1


def heard_probability(belief: float, *, said_yes: bool, slip: float) -> float:
    """The probability the robot gave to the answer it heard.

    ``belief`` is the learner's probability that the asked question is the one the participant
    wants (the posterior for a Bayesian learner, the policy's probability for C2, the weights'
    share for Exp3: :func:`exp3_belief`); ``slip`` the share of answers that say the opposite
    of what the participant means (the protocol's feedback model's mean). Then
    ``P(yes) = slip + (1 − 2 · slip) · belief`` and ``P(no) = 1 − P(yes)``.
    """
    beliefs = np.asarray(belief, np.float64)
    return float(heard_probabilities(beliefs, np.asarray(said_yes), slip=slip))


def heard_probabilities(belief: np.ndarray, said_yes: np.ndarray, *, slip: float) -> np.ndarray:
    """:func:`heard_probability` for arrays of beliefs and answers (simulations)."""
    p_yes = np.clip(slip + (1.0 - 2.0 * slip) * belief, 0.0, 1.0)
    return np.where(said_yes, p_yes, 1.0 - p_yes)


def reply_probability(
    basis: str, *, asked: float, updated: float, belief: float, said_yes: bool, slip: float
) -> float:
    """The probability that sets the reply's level under ``basis`` (one of :data:`BASES`):
    ``asked`` for "chosen", ``updated`` for "updated", :func:`heard_probability` for "heard".

    Raises
    ------
    ValueError
        For an unknown basis.
    """
    if basis == "chosen":
        return float(asked)
    if basis == "updated":
        return float(updated)
    if basis == "heard":
        return heard_probability(belief, said_yes=said_yes, slip=slip)
    raise ValueError(f"unknown reply basis {basis!r}: use one of {', '.join(BASES)}")
