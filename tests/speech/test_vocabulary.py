"""Which recognised words count as a yes or a no: only a phrase of one side, heard confidently."""

from __future__ import annotations

import pytest

from app.speech.vocabulary import Heard, Vocabulary, normalise

VOCABULARY = Vocabulary.of(["Yes", "yeah", "Sure!"], ["no", "No way", "nope"], 0.4)


@pytest.mark.parametrize(
    ("words", "confidence", "answer"),
    [
        ("yes", 0.9, "yes"),
        ("  YEAH. ", 0.5, "yes"),
        ("sure", 0.4, "yes"),  # exactly the threshold counts
        ("No way!", 0.8, "no"),
        ("no  way", 0.8, "no"),
        ("nope", 1.0, "no"),
        ("yes", 0.39, None),  # too doubtful
        ("yes", float("nan"), None),
        ("maybe", 0.9, None),
        ("yes no", 0.9, None),  # both sides: not one phrase
        ("yes please", 0.9, None),  # not a phrase as a whole
        ("", 0.9, None),
        ("\x00\ufffd\x1b[2J", 0.99, None),  # a recogniser returning garbage
        ("no way jose", 0.9, None),
    ],
)
def test_only_a_whole_phrase_of_one_side_heard_confidently_counts(
    words: str, confidence: float, answer: str | None
) -> None:
    assert VOCABULARY.classify(Heard(words, confidence)) == answer


def test_silence_is_unclear_and_the_phrases_are_normalised_once() -> None:
    assert VOCABULARY.classify(None) is None
    assert VOCABULARY.phrases == ["yes", "yeah", "sure", "no", "no way", "nope"]
    assert Vocabulary.of(["Yes", "yes!"], ["no"], 0.5).yes == ("yes",)
    assert normalise("It’s  FINE, 100%") == "it's fine"


def test_combining_marks_are_part_of_the_words() -> None:
    """The word "हूँ" ("am") is not "हाँ" ("yes"): they differ only in their vowel signs."""
    hindi = Vocabulary.of(["हाँ", "जी हाँ"], ["नहीं"], 0.4)
    assert hindi.classify(Heard("हाँ", 0.9)) == "yes"
    assert hindi.classify(Heard("हूँ", 0.9)) is None
    assert hindi.classify(Heard("नहीं!", 0.9)) == "no"
    assert normalise("สวัสดี ครับ") == "สวัสดี ครับ"  # Thai vowels and tone marks kept
