"""How counts read in messages people see: "1 participant", "2 participants", never "(s)"."""

from __future__ import annotations


def counted(number: int, noun: str, plural: str | None = None) -> str:
    """``number`` and ``noun``, the noun in the plural unless the number is one
    (``plural`` for nouns that do not just take an "s")."""
    return f"{number} {noun if number == 1 else plural or noun + 's'}"
