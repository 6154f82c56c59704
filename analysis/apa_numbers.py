"""APA-style (7th ed.) numbers and test sentences, with the standard library only.

The pure formatting half of :mod:`analysis.apa` (which re-exports every name here): statistics
to a fixed number of decimals, p to three decimals without a leading zero (``p < .001`` below
that), proportions that cannot exceed 1 (p, η²) without a leading zero, and the ``F(…)`` and
``t(…)`` sentences built from them. It lives apart from the ANOVA sentences so that a command
which only prints numbers (``trustlab power``) does not import pandas and the ANOVA to do it
(issue 49).
"""

from __future__ import annotations

import math

from analysis.errors import InvalidInputError

__all__ = [
    "format_df",
    "format_number",
    "format_p",
    "format_proportion",
    "sentence_f",
    "sentence_t",
]


def format_number(value: float, decimals: int = 2) -> str:
    """A statistic with a fixed number of decimals (ASCII minus, ``nan`` as an em dash)."""
    if value is None or not math.isfinite(value):
        return "—"
    text = f"{value:.{decimals}f}"
    return "0." + "0" * decimals if text == "-0." + "0" * decimals else text


def format_proportion(value: float, decimals: int = 2) -> str:
    """A value bounded by ±1 (η², ε, W, r) without the leading zero: ``.18``."""
    text = format_number(value, decimals)
    if text.startswith("0."):
        return text[1:]
    if text.startswith("-0."):
        return "-" + text[2:]
    return text


def format_p(p: float | None) -> str:
    """``p = .039``, ``p < .001`` or ``p > .999`` (never ``p = .000``)."""
    if p is None or not math.isfinite(p):
        return "p = —"
    if p < 0 or p > 1:
        raise InvalidInputError(f"a p value must be in [0, 1], got {p}")
    if p < 0.001:
        return "p < .001"
    if p > 0.999:
        return "p > .999"
    return "p = " + format_proportion(p, 3)


def format_df(df: float) -> str:
    """Degrees of freedom: integers as integers, corrected (fractional) df to two decimals."""
    if float(df).is_integer():
        return str(int(df))
    return format_number(df, 2)


def sentence_f(f: float, df1: float, df2: float, p: float, np2: float) -> str:
    """``F(df1, df2) = F, p = …, ηp² = …`` (p as given: compute it from F and df first)."""
    return (
        f"F({format_df(df1)}, {format_df(df2)}) = {format_number(f)}, {format_p(p)}, "
        f"ηp² = {format_proportion(np2)}"
    )


def sentence_t(t: float, dof: float, p: float, d: float | None = None) -> str:
    """``t(df) = t, p = …, d = …`` (d keeps its leading zero: it is not bounded by 1)."""
    text = f"t({format_df(dof)}) = {format_number(t)}, {format_p(p)}"
    if d is not None and math.isfinite(d):
        text += f", d = {format_number(d)}"
    return text
