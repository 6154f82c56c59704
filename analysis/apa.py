"""APA-style (7th ed.) reporting strings for ANOVA effects and t tests.

A report is only reproducible if its sentences come from the computed numbers; these helpers
turn a result into text such as ``F(1, 22) = 4.79, p = .039, ηp² = .18``: statistics to two
decimals, p to three decimals without a leading zero (``p < .001`` below that), and proportions
that cannot exceed 1 (p, η²) without a leading zero. The numbers and the F and t sentences
are :mod:`analysis.apa_numbers`' (standard library only), imported here under their old names.
"""

from __future__ import annotations

import pandas as pd

from analysis.anova import EFFECTS, MixedAnovaResult
from analysis.apa_numbers import (
    format_df,
    format_number,
    format_p,
    format_proportion,
    sentence_f,
    sentence_t,
)

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
