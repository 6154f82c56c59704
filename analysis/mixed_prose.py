"""APA-style sentences for the mixed models: one wording for the page, the report and the CLI.

Each function returns plain sentences built from the result objects with the formatting helpers
of :mod:`analysis.apa`, so every number appears exactly as in the tables. A model that could not
be fitted gives its one-line reason instead of a sentence.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from analysis.adaptation_trust import MEASURES, AdaptationTrust
from analysis.apa import format_df, format_number, format_p
from analysis.lmm import LinearMixedModels, MixedModelFit
from analysis.ordinal import OrdinalFit
from analysis.prose import count

__all__ = [
    "adaptation_sentences",
    "comparison_sentence",
    "covariate_sentences",
    "lmm_sentences",
    "ordinal_sentences",
]


def _f(row: dict[str, float]) -> str:
    df2 = row["df2"]
    df2_text = "∞" if not math.isfinite(df2) else format_df(round(df2, 2))
    return (
        f"F({format_df(row['df1'])}, {df2_text}) = {format_number(row['F'])}, {format_p(row['p'])}"
    )


def covariate_sentences(left_out: Mapping[str, str]) -> list[str]:
    """One sentence per covariate the analysis specification gives the linear mixed models that
    a measure's models could not include (:attr:`analysis.mixed_models.OutcomeMixedModels.
    covariates_left_out`): a deviation from the registration, said where the models are."""
    return [
        f"The linear mixed models leave out the specified covariate {covariate}: {why}."
        for covariate, why in left_out.items()
    ]


def lmm_sentences(models: LinearMixedModels, fit: MixedModelFit | None = None) -> list[str]:
    """What the (preferred) linear mixed model found, and whom it kept.

    Example: "A linear mixed model (REML, random intercept per participant; Satterthwaite df)
    used 95 ratings of 24 participants, 2 of whom the ANOVA excluded for a missing session.
    condition: F(1, 22.01) = 4.07, p = .056; …"
    """
    fit = fit or models.preferred
    if not fit.converged:
        return [fit.problem]
    random = (
        "random intercept per participant"
        if fit.name == "random intercept"
        else f"random intercept and {models.within} slope per participant"
    )
    kept = len(models.kept)
    opening = (
        f"A linear mixed model (REML, {random}; {fit.df_method} df) used "
        f"{count(fit.n_obs, 'rating')} of {count(fit.n_subjects, 'participant')}"
        + (f", {kept} of whom the ANOVA excluded for a missing {models.within}." if kept else ".")
    )
    effects = "; ".join(f"{row['Source']}: {_f(row)}" for row in fit.tests.to_dict("records"))
    sentences = [opening, effects + "."]
    sentences.extend(f"Note: {note}." for note in fit.notes)
    return sentences


def comparison_sentence(models: LinearMixedModels) -> str:
    """The random-slope comparison in one sentence (empty when it was not made)."""
    if models.slope is None:
        return f"No random-slope model: {models.slope_skipped}." if models.slope_skipped else ""
    if models.comparison is None:
        failed = [m for m in models.models if not m.converged]
        refused = [m.problem for m in failed if "did not converge" not in m.problem]
        if refused:
            return "The random-slope comparison could not be made: " + "; ".join(refused) + "."
        return (
            "The random-slope comparison could not be made: the "
            + " and the ".join(m.name for m in failed)
            + " model did not converge."
        )
    c = models.comparison
    verdict = (
        "improved the fit"
        if c["preferred"] == models.slope.name
        else "did not improve the fit enough to keep it"
    )
    return (
        f"Letting the {models.within} slope vary by participant {verdict}, "
        f"χ²({format_df(c['df'])}) = {format_number(c['chi2'])}, {format_p(c['p'])} "
        f"(boundary-corrected), AIC {format_number(c['aic_slope'], 1)} vs "
        f"{format_number(c['aic_intercept'], 1)} with a random intercept only."
    )


def ordinal_sentences(fit: OrdinalFit) -> list[str]:
    """The proportional-odds model's tests and its proportional-odds check."""
    if not fit.converged:
        return [fit.problem]
    tests = "; ".join(
        f"{row['Source']}: Wald χ²({row['df']}) = {format_number(row['chi2'])}, "
        f"{format_p(row['p'])}"
        for row in fit.tests.to_dict("records")
    )
    sentences = [
        f"A proportional-odds (cumulative logit) model of the {len(fit.categories)} rating "
        f"categories with {fit.se_type} standard errors: {tests}."
    ]
    if len(fit.po_check):
        omnibus = fit.po_check.iloc[0]
        holds = "is compatible with" if omnibus["p"] >= 0.05 else "questions"
        sentences.append(
            f"Brant's test {holds} proportional odds, χ²({int(omnibus['df'])}) = "
            f"{format_number(omnibus['chi2'])}, {format_p(omnibus['p'])}."
        )
    elif fit.po_problem:
        sentences.append(f"The proportional-odds check: {fit.po_problem}.")
    sentences.extend(f"Note: {note}." for note in fit.notes if note != fit.po_problem)
    return sentences


def adaptation_sentences(result: AdaptationTrust) -> list[str]:
    """One sentence per adaptation measure: its within- and between-participant slopes."""
    sentences = []
    for measure, words in MEASURES.items():
        rows = result.effects[result.effects["measure"] == measure]
        if rows.empty:
            if measure in result.problems:
                sentences.append(f"{words.capitalize()}: {result.problems[measure]}.")
            continue
        parts = []
        for row in rows.to_dict("records"):
            parts.append(
                f"{row['part']} participants b = {format_number(row['estimate'])} "
                f"[{format_number(row['ci_low'])}, {format_number(row['ci_high'])}], "
                f"t({format_df(round(row['df'], 2))}) = {format_number(row['t'])}, "
                f"{format_p(row['p'])}"
            )
        sentences.append(f"{words.capitalize()}: " + "; ".join(parts) + ".")
    return sentences
