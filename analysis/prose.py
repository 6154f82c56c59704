"""The small pieces of English every analysis text is built from, in one place (issue 21).

Counts agree with their nouns ("1 participant", "2 participants"), an item's text used as a title
loses its closing full stop before a colon ("I perceive the robot as trustworthy: mean ± 95 % CI",
not "trustworthy.: mean"), a reverse-scored item says so, a range of one value is one value
("aged 34 years", not "34–34"), and a participant's own description of their gender is reported
as "self-described", never as the option's text. The methods paragraph, the report, the analysis
page and the exports use these, so small and odd samples read right everywhere.
"""

from __future__ import annotations

_IRREGULAR = {"category": "categories", "person": "people"}


def count(n: int, noun: str) -> str:
    """``n`` and ``noun``, agreeing: ``count(1, "participant")`` → ``"1 participant"``."""
    return f"{n} " + (noun if n == 1 else _IRREGULAR.get(noun, noun + "s"))


def item_title(text: str, *, reverse_keyed: bool = False) -> str:
    """An item's text as a title: without a closing full stop, marked when reverse-scored."""
    title = text.strip().rstrip(".")
    return title + (" (reverse-scored)" if reverse_keyed else "")


def value_range(low: float, high: float, unit: str = "") -> str:
    """``34–48 years``, or ``34 years`` when every value is the same."""
    span = f"{low:g}" if low == high else f"{low:g}–{high:g}"
    return f"{span} {unit}".rstrip()


def gender_word(label: str) -> str:
    """A gender option's label as a word in a sentence: ``Female`` → ``female``; an option that
    asks for the participant's own words (``I describe myself as…``) → ``self-described``; ``Prefer
    not to say`` → ``not stated``."""
    lowered = label.strip().lower()
    if "describe" in lowered or lowered.endswith(("…", "...")):
        return "self-described"
    if lowered.startswith("prefer not"):
        return "not stated"
    return lowered
