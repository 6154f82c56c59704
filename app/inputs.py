"""The shapes every request's integers and names must have, in one place.

Integers: a database row id is a signed 64-bit integer, so an id, page or session number outside
that range can never name anything, and handing one to the driver fails deep inside it (SQLite
raises ``OverflowError``: a 500 and a reset connection). Every integer a route takes (path, query,
form, JSON body, WebSocket frame) is therefore one of :data:`INTEGER_TYPES`, all built on
:func:`canonical_int`: decimal digits only when it arrives as text (no sign, blank, ``_`` or
``.0``: ``" 8"``, ``"1_000"`` and ``"8.0"`` are refused, where pydantic's lax mode would read them
as 8), a real ``int`` when it arrives as JSON (``true`` and ``8.0`` are refused), and at most 19
digits, so a 5,000-digit number is refused before Python converts it.
tests/app/test_inputs.py walks every route and checks that no integer parameter escapes this.

Names: a pattern checked with :meth:`re.Pattern.fullmatch`, never ``match`` with a ``$`` (which
also matches before a trailing newline, so ``"default\\n"`` would have been a second study that
looks like ``default``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated, Any

from pydantic import BeforeValidator, Field

from app.errors import InvalidInput

MAX_ROW_ID = 2**63 - 1
"""The largest id a row can have (a signed 64-bit integer on both databases)."""

MAX_DIGITS = len(str(MAX_ROW_ID))
"""No integer a request may carry has more digits than the largest row id."""

_DIGITS = re.compile(r"[0-9]+")


def canonical_int(value: Any) -> Any:
    """An integer as a request may write it, or a ``ValueError`` saying what is wrong.

    Runs before pydantic's own checks, which then apply the range (``ge``/``le``)."""
    if isinstance(value, bool):
        raise ValueError("expected a whole number, not true/false")
    if isinstance(value, int):
        if len(str(abs(value))) > MAX_DIGITS:
            raise ValueError(f"a whole number of at most {MAX_DIGITS} digits")
        return value
    if isinstance(value, str):
        if not _DIGITS.fullmatch(value):
            raise ValueError("expected a whole number written with the digits 0-9 only")
        if len(value) > MAX_DIGITS:
            raise ValueError(f"a whole number of at most {MAX_DIGITS} digits")
        return int(value)
    raise ValueError("expected a whole number")


_Canonical = BeforeValidator(canonical_int)

RowId = Annotated[int, _Canonical, Field(ge=1, le=MAX_ROW_ID)]
"""The id of a row (a step, a device key…): 1 … 2**63 - 1."""

PageNumber = Annotated[int, _Canonical, Field(ge=1, le=10**9)]
"""A page of a paged listing: far past the last page is an empty page, not an error."""

SessionNumber = Annotated[int, _Canonical, Field(ge=1, le=10**6)]
"""A session's number within a study (1, 2, …)."""

VersionNumber = Annotated[int, _Canonical, Field(ge=1, le=10**6)]
"""A numbered version (of a study's consent text: 1, 2, …)."""

Count = Annotated[int, _Canonical, Field(ge=0, le=MAX_ROW_ID)]
"""A non-negative count or option (a sample size, a sums-of-squares type): 0 … 2**63 - 1."""

ScreenPixels = Annotated[int, _Canonical, Field(ge=0, le=100_000)]
"""A browser window's width or height in CSS pixels (the online browser check)."""

INTEGER_TYPES = (RowId, PageNumber, SessionNumber, VersionNumber, Count, ScreenPixels)
"""Every integer shape a request may use (the route-walking test checks for these)."""


@dataclass(frozen=True)
class NameRule:
    """What a kind of name (study, station, participant code, username) must look like."""

    what: str
    """How the error names the value, e.g. ``"study name"``."""
    pattern: re.Pattern[str]
    """Matched against the whole value (:meth:`re.Pattern.fullmatch`)."""
    rule: str
    """The rule in words, shown when a value breaks it."""

    @property
    def sentence(self) -> str:
        """The rule as a sentence for a form, beside its field ("Use 2-64 …."): the same words the
        error uses, so a page never states a rule the server does not apply."""
        return f"{self.rule[0].upper()}{self.rule[1:]}."

    def matches(self, value: str) -> bool:
        """Whether the whole value follows the rule (a trailing newline does not)."""
        return self.pattern.fullmatch(value) is not None

    def check(self, value: str) -> str:
        """The value itself, or InvalidInput saying what the rule is."""
        if not self.matches(value):
            raise InvalidInput(f"{self.what} {value!r}: {self.rule}")
        return value


STUDY_NAME = NameRule(
    "study name",
    re.compile(r"[a-z0-9][a-z0-9-]{1,63}"),
    "use 2-64 lower-case letters, digits or '-', starting with a letter or digit",
)
STATION_NAME = NameRule(
    "station name",
    re.compile(r"[a-z0-9][a-z0-9-]{0,63}"),
    "use 1-64 lower-case letters, digits or '-', starting with a letter or digit",
)
PARTICIPANT_CODE = NameRule(
    "participant code",
    re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,31}"),
    "use 1-32 letters, digits, '_' or '-', starting with a letter or digit",
)
USERNAME = NameRule(
    "username",
    re.compile(r"[a-z0-9][a-z0-9._-]{1,63}"),
    "a username has 2-64 characters: letters, digits, '.', '_' or '-', "
    "starting with a letter or digit",
)
STRATUM_VALUE = NameRule(
    "stratum value",
    re.compile(r"[^;=\s][^;=\x00-\x1f\x7f]{0,63}"),
    "a value has 1-64 characters, no ';', '=' or control characters",
)
