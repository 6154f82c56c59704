"""The interface's words around a protocol's texts, in gettext catalogues a translator can edit.

Everything a participant reads that the protocol does not give — the tablet's buttons, progress
and validation messages, the room's banners and captions, the debrief — is written in English in
the templates, scripts and services, marked for translation (``{% trans %}``/``_()`` in
templates, ``_()`` in scripts, :class:`Message` in Python), and translated from one ``.po`` file
per language, ``app/i18n/locales/<language>/LC_MESSAGES/messages.po`` (docs/languages.md).
The ``.po`` files are read directly with Babel at start-up: there is no compile step to forget.

A catalogue is used only when it is complete and every translation keeps its source's
placeholders (``%(name)s``): a missing or broken one would put English, or a crash, in front of a
participant, so it is refused with one line naming the message.
"""

from __future__ import annotations

import functools
import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from babel.messages.catalog import Catalog
from babel.messages.mofile import write_mo
from babel.messages.pofile import read_po
from babel.support import Translations

from app.i18n.languages import direction

LOCALES = Path(__file__).parent / "locales"
DOMAIN = "messages"
SOURCE_LANGUAGE = "en"
"""The language the interface is written in (its message ids)."""

_PLACEHOLDER = re.compile(r"%\((\w+)\)[sd]")


class CatalogueError(ValueError):
    """A language without a usable interface catalogue (one line, naming the problem)."""


class Message(str):
    """An English sentence for a participant, with what it needs to be said in their language.

    It *is* the English text (so logs, the JSON API and older callers see a plain string), and
    keeps its template and values so :meth:`Catalogue.say` can translate it later, where the
    participant's language is known."""

    template: str
    values: dict[str, Any]

    def __new__(cls, template: str, **values: Any) -> Message:
        message = super().__new__(cls, template % values if values else template)
        message.template = template
        message.values = values
        return message


def _placeholders(text: str) -> set[str]:
    return set(_PLACEHOLDER.findall(text))


def path_of(language: str) -> Path:
    """Where the language's catalogue lives."""
    return LOCALES / language.replace("-", "_") / "LC_MESSAGES" / f"{DOMAIN}.po"


@functools.cache
def ui_languages() -> list[str]:
    """The languages with an interface catalogue, in code order."""
    found = LOCALES.glob(f"*/LC_MESSAGES/{DOMAIN}.po")
    return sorted(path.parent.parent.name.replace("_", "-") for path in found)


def read_catalog(language: str) -> Catalog:
    """The language's ``.po`` file as Babel reads it; CatalogueError when there is none."""
    path = path_of(language)
    if not path.is_file():
        raise CatalogueError(
            f"no interface catalogue for {language!r} (app/i18n/locales/"
            f"{path.relative_to(LOCALES)}): add one as docs/languages.md describes"
        )
    with path.open("rb") as handle:
        return read_po(handle, locale=language.replace("-", "_"), domain=DOMAIN)


def catalogue_problems(catalog: Catalog) -> list[str]:
    """One line per message that is untranslated, fuzzy, or whose translation has other
    placeholders than its source."""
    problems = []
    for message in catalog:
        if not message.id:
            continue  # the header
        ids = message.id if isinstance(message.id, (list, tuple)) else (message.id,)
        strings = message.string if isinstance(message.string, (list, tuple)) else (message.string,)
        shown = ids[0][:60]
        if message.fuzzy:
            problems.append(f"{shown!r}: marked fuzzy (check it, then remove the flag)")
        if not all(strings):
            problems.append(f"{shown!r}: not translated")
            continue
        wanted = _placeholders(ids[0]) | _placeholders(ids[-1])
        for string in strings:
            got = _placeholders(string or "")
            # A plural form may leave the count out ("one file"); a singular keeps them all.
            wrong = got - wanted if len(ids) > 1 else got ^ wanted
            if wrong:
                problems.append(
                    f"{shown!r}: the translation's placeholders {sorted(got)} differ from the "
                    f"source's {sorted(wanted)}"
                )
    return problems


@dataclass(frozen=True)
class Catalogue:
    """A language's complete, checked interface catalogue."""

    language: str
    translations: Translations = field(repr=False)
    messages: dict[str, str] = field(repr=False)
    """Singular message id → translation (what the room's scripts receive)."""

    @property
    def direction(self) -> str:
        """``rtl`` or ``ltr``, for HTML's ``dir``."""
        return direction(self.language)

    def gettext(self, text: str) -> str:
        """``text`` (an English message id) in this language."""
        return self.translations.ugettext(text)

    def ngettext(self, singular: str, plural: str, count: int) -> str:
        """The singular or plural form for ``count``, as this language counts."""
        return self.translations.ungettext(singular, plural, count)

    def say(self, message: str) -> str:
        """A :class:`Message` (or a plain message id) in this language, its values filled in."""
        if isinstance(message, Message):
            translated = self.gettext(message.template)
            return translated % message.values if message.values else translated
        return self.gettext(message)


@functools.cache
def catalogue(language: str) -> Catalogue:
    """The language's interface catalogue, read and checked once per process.

    CatalogueError (one line) when it is missing or not complete."""
    catalog = read_catalog(language)
    problems = catalogue_problems(catalog)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise CatalogueError(f"the {language!r} interface catalogue: {problems[0]}{more}")
    buffer = io.BytesIO()
    write_mo(buffer, catalog)
    buffer.seek(0)
    messages = {
        str(m.id): str(m.string) for m in catalog if m.id and isinstance(m.id, str) and m.string
    }
    return Catalogue(language, Translations(buffer, domain=DOMAIN), messages)


def check_language(language: str) -> str | None:
    """Why the interface cannot be shown in ``language`` (None when it can)."""
    try:
        catalogue(language)
    except CatalogueError as exc:
        return str(exc)
    return None
