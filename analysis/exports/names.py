"""Column names that SPSS, JASP and R accept unchanged."""

from __future__ import annotations

import re

__all__ = ["SPSS_RESERVED", "session_column", "spss_name"]

SPSS_RESERVED = frozenset(
    {"ALL", "AND", "BY", "EQ", "GE", "GT", "LE", "LT", "NE", "NOT", "OR", "TO", "WITH"}
)
"""Words SPSS refuses as variable names."""


def spss_name(name: str, taken: set[str] | None = None) -> str:
    """A valid SPSS variable name for ``name``: letters, digits and ``_``, starting with a letter,
    at most 64 bytes, not a reserved word, and not already in ``taken`` (case-insensitive).
    """
    clean = re.sub(r"[^0-9A-Za-z_]", "_", name.strip()).strip("_") or "var"
    if not clean[0].isalpha():
        clean = "v_" + clean
    clean = clean[:64].rstrip("_")
    if clean.upper() in SPSS_RESERVED:
        clean += "_"
    if taken is not None:
        lower = {t.lower() for t in taken}
        base, i = clean, 2
        while clean.lower() in lower:
            suffix = f"_{i}"
            clean = base[: 64 - len(suffix)] + suffix
            i += 1
    return clean


def session_column(base: str, session: int) -> str:
    """The wide column of a per-session value, e.g. ``trust_1_s1`` (JASP/SPSS repeated measures)."""
    return f"{base}_s{session}"
