"""Which recognised words count as a yes or a no.

A robot's recogniser is given the protocol's phrases (``[speech] yes`` and ``no``) and reports
what it heard with a confidence. Only a clear answer counts: the words must be one of the
phrases (after case, punctuation and spacing are set aside) and the confidence at least the
protocol's ``min_confidence``. Anything else — another word, words of both sides, a recogniser
that returns garbage, a doubtful guess — is *unclear*, and the robot asks again: a misheard answer
would teach the learner the wrong thing, while asking again only costs a few seconds.
"""

from __future__ import annotations

import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

Answer = Literal["yes", "no"]


@dataclass(frozen=True)
class Heard:
    """What a recogniser reported: its words and its confidence (0-1)."""

    words: str
    confidence: float


DEFAULT_YES = ("yes", "yeah", "yep", "sure")
DEFAULT_NO = ("no", "nope", "no way")
DEFAULT_MIN_CONFIDENCE = 0.4


def normalise(words: str) -> str:
    """Lower case, letters (with their combining marks: Indic vowel signs, Thai tone marks,
    Arabic vowels) and apostrophes only, single spaces: how phrases are compared."""
    text = words.lower().replace("\u2019", "'")
    kept = (c if c == "'" or unicodedata.category(c)[0] in "LM" else " " for c in text)
    return " ".join("".join(kept).split())


@dataclass(frozen=True)
class Vocabulary:
    """The phrases of each answer and the confidence a recognition needs to count."""

    yes: tuple[str, ...] = DEFAULT_YES
    no: tuple[str, ...] = DEFAULT_NO
    min_confidence: float = DEFAULT_MIN_CONFIDENCE

    @classmethod
    def of(cls, yes: Sequence[str], no: Sequence[str], min_confidence: float) -> Vocabulary:
        """A vocabulary from a protocol's lists (normalised; duplicates dropped, order kept)."""
        return cls(
            yes=tuple(dict.fromkeys(normalise(p) for p in yes)),
            no=tuple(dict.fromkeys(normalise(p) for p in no)),
            min_confidence=min_confidence,
        )

    @property
    def phrases(self) -> list[str]:
        """Everything the recogniser should listen for, yes phrases first."""
        return [*self.yes, *self.no]

    def classify(self, heard: Heard | None) -> Answer | None:
        """``"yes"``, ``"no"``, or None for silence and anything unclear."""
        if heard is None or not (heard.confidence >= self.min_confidence):
            return None
        text = normalise(heard.words)
        in_yes, in_no = text in self.yes, text in self.no
        if in_yes == in_no:
            return None
        return "yes" if in_yes else "no"
