"""APA-style (7th ed.) reporting strings for ANOVA effects and t tests.

A report is only reproducible if its sentences come from the computed numbers; these helpers
turn a result into text such as ``F(1, 22) = 4.79, p = .039, ηp² = .18``: statistics to two
decimals, p to three decimals without a leading zero (``p < .001`` below that), and proportions
that cannot exceed 1 (p, η²) without a leading zero.
"""

from __future__ import annotations

import math

import pandas as pd

from analysis.anova import EFFECTS, MixedAnovaResult
from analysis.errors import InvalidInputError

__all__ = [
    "SPHERICITY_ALPHA",
    "anova_sentences",
    "format_df",
    "format_number",
    "format_p",
    "format_proportion",
    "sentence_f",
    "sentence_t",
    "sphericity_sentence",
]

SPHERICITY_ALPHA = 0.05
"""Mauchly p below which the Greenhouse–Geisser corrected test is reported."""


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


def sphericity_sentence(result: MixedAnovaResult) -> str:
    """Mauchly's test and ε as one clause, e.g. ``Mauchly's W = .89, p = .754, ε = .93``."""
    sph = result.sphericity
    if result.design.n_levels == 2:
        return "Sphericity holds trivially with two levels (ε = 1)"
    if sph.p is None:
        eps = format_proportion(sph.eps_gg)
        return f"Mauchly's test could not be computed ({sph.note}); ε = {eps}"
    return (
        f"Mauchly's W = {format_proportion(sph.W)}, {format_p(sph.p)}, "
        f"ε = {format_proportion(sph.eps_gg)}"
    )


def anova_sentences(
    result: MixedAnovaResult, *, sphericity_alpha: float = SPHERICITY_ALPHA
) -> pd.DataFrame:
    """One APA sentence per effect of a mixed ANOVA.

    Parameters
    ----------
    result : MixedAnovaResult
    sphericity_alpha : float
        When Mauchly's p is below this (or undefined), the within and interaction sentences use
        the Greenhouse–Geisser corrected degrees of freedom and p, and say so.

    Returns
    -------
    pandas.DataFrame
        Columns ``effect``, ``Source``, ``corrected`` (bool) and ``text``, e.g.
        ``"condition: F(1, 22) = 4.79, p = .039, ηp² = .18"``.

    Notes
    -----
    Every p value is taken from the result, which computes it from F and its degrees of
    freedom; no sentence copies a p from elsewhere.
    """
    sph = result.sphericity
    violated = result.design.n_levels > 2 and (sph.p is None or sph.p < sphericity_alpha)
    rows = []
    for name in EFFECTS:
        row = result.effect(name)
        corrected = violated and name != "between"
        if corrected:
            eps = float(row["eps"])
            text = (
                sentence_f(
                    row["F"], row["DF1"] * eps, row["DF2"] * eps, row["p_GG_corr"], row["np2"]
                )
                + f", ε = {format_proportion(eps)} (Greenhouse–Geisser)"
            )
        else:
            text = sentence_f(row["F"], row["DF1"], row["DF2"], row["p_unc"], row["np2"])
        rows.append(
            {
                "effect": name,
                "Source": row["Source"],
                "corrected": corrected,
                "text": f"{row['Source']}: {text}",
            }
        )
    return pd.DataFrame(rows, columns=["effect", "Source", "corrected", "text"])
