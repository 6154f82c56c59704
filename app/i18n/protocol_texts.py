"""A protocol's participant-facing texts, and the same protocol in another of its languages.

A protocol is written in its first language (``[study] languages``); each further language gives
its texts in ``[translations.<language>]``, a table that names every text by stable identifiers
(category names, level names, instrument and item keys, option values) rather than by position,
so a translator sees which text they are translating and reordering a list cannot swap two:

    [translations.sv]
    study.rules = ["…", "…"]
    categories.conation.questions = ["…", "…", "…", "…"]
    replies.low.text = "…"
    instruments.tipi.items.tipi_1.text = "…"
    instruments.demographics.items.gender.options.female = "…"

Everything here works on the protocol's plain data (its TOML/JSON form), so app.protocol can use
it to check a protocol and to build the translated one without a circle of imports.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Literal

from app.speech.vocabulary import normalise

TRANSLATIONS = "translations"
"""The protocol's table of translations, one sub-table per further language."""

SOURCE = "source"
"""A translation's own key that is not a text of the protocol: where the translation comes from
(who made it, or which published versions it uses, and whether it is validated). Optional, so
that studies created before it stay valid; the codebook and the report cite it (or say that it
was not given)."""

Shape = Literal["text", "lines", "phrases"]
"""A single text; a list whose entries correspond one to one (questions, scale labels, rules:
the same length in every language); a list of alternatives (speech phrases: any length, >= 1)."""


@dataclass(frozen=True)
class TextSlot:
    """One participant-facing text: where the translation names it, where it sits in the
    protocol's data, what it says in the protocol's first language, and its shape."""

    path: str
    location: tuple[str | int, ...]
    source: str | list[str]
    shape: Shape


def text_slots(data: dict[str, Any]) -> list[TextSlot]:
    """Every participant-facing text of a protocol's data, in file order.

    What a participant never sees (condition labels, the description, score labels) is not a
    slot; an optional text the protocol leaves empty (instructions, citation) has none either."""
    return list(_slots(data))


def _slots(data: dict[str, Any]) -> Iterator[TextSlot]:
    study = data.get("study", {})
    yield TextSlot("study.title", ("study", "title"), study.get("title", ""), "text")
    if study.get("rules"):
        yield TextSlot("study.rules", ("study", "rules"), study["rules"], "lines")
    for index, category in enumerate(data.get("categories", [])):
        base, at = f"categories.{category.get('name')}", ("categories", index)
        yield TextSlot(f"{base}.title", (*at, "title"), category.get("title", ""), "text")
        yield TextSlot(f"{base}.questions", (*at, "questions"), category["questions"], "lines")
    for index, level in enumerate(data.get("replies", {}).get("levels", [])):
        for field in ("text", "yes", "no"):
            if level.get(field) is not None:
                line_at = ("replies", "levels", index, field)
                path = f"replies.{level.get('name')}.{field}"
                yield TextSlot(path, line_at, level[field], "text")
    speech = data.get("speech", {})
    for field in ("yes", "no"):
        if field in speech:
            yield TextSlot(f"speech.{field}", ("speech", field), speech[field], "phrases")
    if "reprompt" in speech:
        yield TextSlot("speech.reprompt", ("speech", "reprompt"), speech["reprompt"], "text")
    yield from _questionnaire_slots(data.get("questionnaires", {}))


def _questionnaire_slots(questionnaires: dict[str, Any]) -> Iterator[TextSlot]:
    at: tuple[str | int, ...] = ("questionnaires", "consent", "text")
    yield TextSlot("consent.text", at, questionnaires.get("consent", {}).get("text", ""), "text")
    for index, scale in enumerate(questionnaires.get("scales", [])):
        at = ("questionnaires", "scales", index, "labels")
        if scale.get("labels"):
            yield TextSlot(f"scales.{scale.get('name')}.labels", at, scale["labels"], "lines")
    for index, instrument in enumerate(questionnaires.get("instruments", [])):
        base, at = f"instruments.{instrument.get('key')}", ("questionnaires", "instruments", index)
        for field in ("title", "instructions", "citation"):
            if instrument.get(field):
                yield TextSlot(f"{base}.{field}", (*at, field), instrument[field], "text")
        for i, item in enumerate(instrument.get("items", [])):
            item_base, item_at = f"{base}.items.{item.get('key')}", (*at, "items", i)
            yield TextSlot(f"{item_base}.text", (*item_at, "text"), item.get("text", ""), "text")
            for o, option in enumerate(item.get("options", [])):
                yield TextSlot(
                    f"{item_base}.options.{option.get('value')}",
                    (*item_at, "options", o, "label"),
                    option.get("label", ""),
                    "text",
                )


def flatten(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A translation table as ``{"a.b.c": value}``: TOML's dotted keys nest tables, and a
    translator may write either form."""
    flat: dict[str, Any] = {}
    for key, value in table.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, dict):
            flat.update(flatten(value, path))
        else:
            flat[path] = value
    return flat


def translation_problems(data: dict[str, Any], languages: list[str]) -> list[tuple[str, str]]:
    """``(key path, reason)`` for every translation that is missing, empty, of the wrong shape
    or about no text of the protocol, and for a language the protocol does not declare."""
    problems: list[tuple[str, str]] = []
    translations = data.get(TRANSLATIONS) or {}
    default, further = languages[0], languages[1:]
    for language in translations:
        if language == default:
            problems.append(
                (
                    f"{TRANSLATIONS}.{language}",
                    f"{language!r} is the protocol's first language: its texts are the "
                    "protocol's own, not a translation",
                )
            )
        elif language not in further:
            problems.append(
                (
                    f"{TRANSLATIONS}.{language}",
                    f"{language!r} is not one of study.languages ({', '.join(languages)})",
                )
            )
    slots = text_slots(data)
    known = {slot.path for slot in slots}
    for language in further:
        table = translations.get(language)
        base = f"{TRANSLATIONS}.{language}"
        if not isinstance(table, dict):
            problems.append((base, f"missing: every participant-facing text in {language!r}"))
            continue
        given = flatten(table)
        source = given.pop(SOURCE, None)
        if source is not None and not (isinstance(source, str) and source.strip()):
            problems.append(
                (
                    f"{base}.{SOURCE}",
                    f"must be a non-empty text in {language!r}: who made the translation, or "
                    "the published versions it uses",
                )
            )
        for slot in slots:
            reason = _slot_problem(slot, given.get(slot.path), language)
            if reason:
                problems.append((f"{base}.{slot.path}", reason))
        problems += [
            (f"{base}.{path}", "not a participant-facing text of this protocol")
            for path in given
            if path not in known
        ]
        problems += _phrase_problems(given, base)
    return problems


def _slot_problem(slot: TextSlot, value: Any, language: str) -> str | None:
    if value is None:
        return f"missing in {language!r}"
    if slot.shape == "text":
        if not isinstance(value, str):
            return f"must be a text in {language!r}"
        return None if value.strip() else f"empty in {language!r}: give the text"
    if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
        return f"must be a list of non-empty texts in {language!r}"
    if slot.shape == "lines" and len(value) != len(slot.source):
        return f"{len(value)} entries in {language!r}, {len(slot.source)} in the protocol's own"
    if slot.shape == "phrases" and not value:
        return f"needs at least one phrase in {language!r}"
    return None


def _phrase_problems(given: dict[str, Any], base: str) -> list[tuple[str, str]]:
    """A spoken phrase must mean one answer only, in every language."""
    yes, no = given.get("speech.yes"), given.get("speech.no")
    if not (isinstance(yes, list) and isinstance(no, list)):
        return []
    said_yes = {normalise(p) for p in yes if isinstance(p, str)}
    return [
        (f"{base}.speech.no[{index}]", f"{phrase!r} is a yes phrase too")
        for index, phrase in enumerate(no)
        if isinstance(phrase, str) and normalise(phrase) in said_yes
    ]


def translated(data: dict[str, Any], language: str) -> dict[str, Any]:
    """The protocol's data with every participant-facing text in ``language`` (one of its
    further languages, checked by :func:`translation_problems`), as a protocol whose own
    language is ``language``: it comes first in ``study.languages`` (the others still listed,
    so the tablet can offer them) and it carries no translations."""
    given = flatten(data[TRANSLATIONS][language])
    given.pop(SOURCE, None)
    result = copy.deepcopy(data)
    for slot in text_slots(data):
        _set(result, slot.location, copy.deepcopy(given[slot.path]))
    result[TRANSLATIONS] = {}
    offered = result["study"]["languages"]
    result["study"]["languages"] = [language, *(code for code in offered if code != language)]
    return result


def _set(data: Any, location: tuple[str | int, ...], value: Any) -> None:
    for part in location[:-1]:
        data = data[part]
    data[location[-1]] = value
