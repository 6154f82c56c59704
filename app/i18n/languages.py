"""Language codes, as protocols, participants and catalogues name them.

A code is an ISO 639 language with an optional region (``sv``, ``de``, ``pt-BR``): what HTML's
``lang`` attribute and the robots' text-to-speech take. Babel's CLDR data decides whether it names
a real language and which way its script runs."""

from __future__ import annotations

import functools
import re

from babel import Locale, UnknownLocaleError

CODE = re.compile(r"^[a-z]{2,3}(-[A-Z]{2})?$")


class UnknownLanguage(ValueError):
    """A code that does not name a language (one line, fit for a 4xx or a protocol problem)."""


@functools.cache
def locale_of(code: str) -> Locale:
    """The CLDR locale of a language code; :class:`UnknownLanguage` if there is none."""
    if not isinstance(code, str) or not CODE.match(code):
        raise UnknownLanguage(
            f"{code!r} is not a language code: write it as 'sv', 'de' or 'pt-BR' "
            "(ISO 639, optionally a region)"
        )
    try:
        return Locale.parse(code, sep="-")
    except (UnknownLocaleError, ValueError):
        raise UnknownLanguage(f"{code!r} is not a language known to CLDR") from None


def check_code(code: str) -> str:
    """``code`` if it names a language, else :class:`UnknownLanguage`."""
    locale_of(code)
    return code


def is_rtl(code: str) -> bool:
    """Whether the language's script runs right to left (Arabic, Hebrew, Persian…)."""
    return locale_of(code).text_direction == "rtl"


def direction(code: str) -> str:
    """HTML's ``dir`` for the language: ``rtl`` or ``ltr``."""
    return "rtl" if is_rtl(code) else "ltr"


def native_name(code: str) -> str:
    """The language's name in itself ("svenska", "Deutsch"), for a participant choosing theirs."""
    name = locale_of(code).get_display_name(locale_of(code)) or code
    return name[:1].upper() + name[1:]
