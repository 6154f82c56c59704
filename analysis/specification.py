"""The one specification of a study's analyses: what is registered is what is fitted and reported.

Three places describe a study's models: ``trustlab prereg`` registers them
(:func:`analysis.prereg.registered_plan`), the analysis fits them (:func:`analysis.study.
analyse_study`, :func:`analysis.mixed_models.analyse_mixed_models`) and the report describes
them. Each of those reads :func:`analysis_specification`, so a covariate the fitting code adds
(the language of a study run in several, the site of a multi-site one) is in the registration
and the report's description too, before the first participant: the covariates come from the
protocol (its languages and sites), never from whoever has enrolled so far.

Every :class:`PlannedAnalysis` names the result attribute its fit lands in (``result``), so a
test can enumerate the fitted analyses of a study and fail when one is added that is not
derived from here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = [
    "COVARIATES",
    "LANGUAGE",
    "SITE",
    "PlannedAnalysis",
    "analysis_specification",
    "planned",
    "study_covariates",
]

LANGUAGE = "language"
SITE = "site"
COVARIATES = (LANGUAGE, SITE)
"""Participant attributes the linear mixed models adjust for (sum-coded fixed effects) when the
protocol has more than one of them: the language of a study run in several
(``protocol["languages"]``), the site of a multi-site study (``protocol["sites"]``)."""


@dataclass(frozen=True)
class PlannedAnalysis:
    """One analysis of every per-session measure.

    Attributes
    ----------
    name : str
        Identifier (``"lmm"``), the key in the registered plan's ``analyses``.
    title : str
        What readers call it ("linear mixed models").
    result : str
        ``Class.attribute`` the fit is stored in (``"OutcomeMixedModels.lmm"``).
    formulas : tuple of str
        The models it fits, with ``{dv}`` for the measure (as the fitted models display them).
    covariates : tuple of str
        Participant attributes added as fixed effects.
    description : str
        The sentence registered and shown in the report.
    """

    name: str
    title: str
    result: str
    formulas: tuple[str, ...]
    covariates: tuple[str, ...]
    description: str

    def formulas_for(self, dv: str) -> tuple[str, ...]:
        """The formulas with the measure's name in them."""
        return tuple(formula.replace("{dv}", dv) for formula in self.formulas)

    def to_dict(self) -> dict[str, Any]:
        """The registered, checkable part: name, formulas and covariates."""
        return {
            "name": self.name,
            "formulas": list(self.formulas),
            "covariates": list(self.covariates),
        }


def study_covariates(protocol: Mapping[str, Any]) -> tuple[str, ...]:
    """The covariates of the linear mixed models, from the protocol: ``language`` when it runs
    in two or more languages, ``site`` when it has two or more sites."""
    found = []
    if len(protocol.get("languages") or ()) >= 2:
        found.append(LANGUAGE)
    if len(protocol.get("sites") or ()) >= 2:
        found.append(SITE)
    return tuple(found)


def _terms(covariates: tuple[str, ...]) -> str:
    return "".join(f" + {c}" for c in covariates)


def analysis_specification(protocol: Mapping[str, Any]) -> tuple[PlannedAnalysis, ...]:
    """Every analysis the report runs on each per-session measure, in report order.

    Parameters
    ----------
    protocol : mapping
        The :class:`analysis.dataset.ProtocolSummary` (its ``languages`` and ``sites`` decide
        the covariates).
    """
    covariates = study_covariates(protocol)
    fixed = "{dv} ~ condition * session" + _terms(covariates)
    adjusted = (
        f"; adjusted for {' and '.join(covariates)} (sum-coded fixed effects, marginal means "
        "averaged over their levels with equal weights)"
        if covariates
        else "; no covariates"
    )
    return (
        PlannedAnalysis(
            name="mixed_anova",
            title="mixed ANOVA",
            result="OutcomeAnalysis.anova",
            formulas=("{dv} ~ condition * session (complete cases)",),
            covariates=(),
            description="mixed ANOVA: condition (between) × session (within) on each "
            "per-session measure; sphericity by Mauchly's test, Greenhouse–Geisser corrected "
            "df and p when it is violated; effect sizes partial and generalised η²",
        ),
        PlannedAnalysis(
            name="posthoc",
            title="post-hoc tests",
            result="OutcomeAnalysis.posthoc",
            formulas=(),
            covariates=(),
            description="post-hoc tests: sessions within each condition (paired t) and "
            "conditions within each session (independent t, Welch's with unequal groups), "
            "Holm-corrected within each family",
        ),
        PlannedAnalysis(
            name="lmm",
            title="linear mixed models",
            result="OutcomeMixedModels.lmm",
            formulas=(
                fixed + " + (1 | participant)",
                fixed + " + (1 + session_step | participant)",
            ),
            covariates=covariates,
            description=f"linear mixed models: {fixed.replace('{dv}', 'value')} + "
            "(1 | participant), and with three or more sessions the random-slope model "
            f"{fixed.replace('{dv}', 'value')} + (1 + session_step | participant), preferred "
            "when its likelihood-ratio test (p < .05) and AIC favour it; REML, type III F tests "
            "with Satterthwaite df (all participants, incomplete ones too)" + adjusted,
        ),
        PlannedAnalysis(
            name="ordinal",
            title="ordinal model",
            result="OutcomeMixedModels.ordinal",
            formulas=("{dv} ~ condition * session (cumulative logit, clustered by participant)",),
            covariates=(),
            description="ordinal model for single Likert items: value ~ condition * session, "
            "proportional odds (cumulative logit) with participant-clustered standard errors; "
            "no covariates",
        ),
        PlannedAnalysis(
            name="adaptation_trust",
            title="adaptation and trust",
            result="OutcomeMixedModels.adaptation",
            formulas=(
                "{dv} ~ condition + session + {measure}_within + {measure}_between "
                "+ (1 | participant)",
            ),
            covariates=(),
            description="adaptation and trust (with a step log): value ~ condition + session + "
            "x_within + x_between + (1 | participant) for each adaptation measure x of the "
            "session, split by person-mean centring; no covariates",
        ),
    )


def planned(protocol: Mapping[str, Any], name: str) -> PlannedAnalysis:
    """The planned analysis called ``name`` (e.g. ``"lmm"``)."""
    for analysis in analysis_specification(protocol):
        if analysis.name == name:
            return analysis
    raise KeyError(name)
