"""The robot's reply to an answer, chosen by how confident the learner was in the question it asked.

After each answer the robot says one of a few sentences. Which one depends on the probability ``p``
the learner gave the question it just asked: a learner that was confident the participant would say
yes sounds pleased ("Awesome, I knew you would say so."), a hesitant one sounds sceptical. The
protocol fixes three thresholds that split [0, 1] into four levels; a study may change them.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

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
