"""Every mixed model of a study, beside its ANOVAs: what the page, the report and exports show.

:func:`analyse_mixed_models` takes the :class:`analysis.study.StudyAnalysis` (so the status
exclusions, scoring and reverse keys are exactly the ANOVA's) and, for every per-session trust
measure, fits the linear mixed models (:mod:`analysis.lmm`), the proportional-odds model when the
measure is a single Likert item (:mod:`analysis.ordinal`), and the adaptation-and-trust models
(:mod:`analysis.adaptation_trust`) when the step log is there. A measure whose model cannot be
computed carries the one-line reason; the others go on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import pandas as pd

from analysis.adaptation_trust import AdaptationTrust, adaptation_trust, session_adaptation
from analysis.errors import AnalysisError, InvalidInputError
from analysis.lmm import LinearMixedModels, linear_mixed_models
from analysis.ordinal import OrdinalFit, not_single_item, ordinal_model
from analysis.study import OutcomeAnalysis, StudyAnalysis

__all__ = ["OutcomeMixedModels", "StudyMixedModels", "analyse_mixed_models"]

_FACTORS = ("session", "condition", "participant")
"""Column names of :attr:`analysis.study.OutcomeAnalysis.data` besides the value."""


@dataclass(frozen=True)
class OutcomeMixedModels:
    """The mixed models of one per-session measure.

    Attributes
    ----------
    key, label : str
        As the ANOVA's :class:`analysis.study.OutcomeAnalysis`.
    lmm : LinearMixedModels or None
    lmm_problem : str
    ordinal : OrdinalFit or None
        Only for single Likert items (whole-number ratings).
    ordinal_problem : str
    adaptation : AdaptationTrust or None
        Only with a step log.
    adaptation_problem : str
    anova_excluded : int
        Participants the ANOVA of this measure drops (for the "kept" sentence).
    """

    key: str
    label: str
    lmm: LinearMixedModels | None
    lmm_problem: str
    ordinal: OrdinalFit | None
    ordinal_problem: str
    adaptation: AdaptationTrust | None
    adaptation_problem: str
    anova_excluded: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "key": self.key,
            "label": self.label,
            "lmm": self.lmm.to_dict() if self.lmm else None,
            "lmm_problem": self.lmm_problem,
            "ordinal": self.ordinal.to_dict() if self.ordinal else None,
            "ordinal_problem": self.ordinal_problem,
            "adaptation": self.adaptation.to_dict() if self.adaptation else None,
            "adaptation_problem": self.adaptation_problem,
        }


@dataclass(frozen=True)
class StudyMixedModels:
    """Result of :func:`analyse_mixed_models`.

    Attributes
    ----------
    outcomes : tuple of OutcomeMixedModels
        In the order of :attr:`analysis.study.StudyAnalysis.outcomes`.
    measures : pandas.DataFrame
        Per participant × session adaptation measures (:func:`session_adaptation`); empty without
        a step log.
    measures_problem : str
        Why there are no adaptation measures (no steps yet, steps withheld by blinding…).
    random_slope : bool
        Whether the random-slope models were fitted.
    """

    outcomes: tuple[OutcomeMixedModels, ...]
    measures: pd.DataFrame
    measures_problem: str
    random_slope: bool

    def outcome(self, key: str) -> OutcomeMixedModels:
        """The models of the measure with this key."""
        for outcome in self.outcomes:
            if outcome.key == key:
                return outcome
        raise InvalidInputError(f"no outcome {key!r}; have {[o.key for o in self.outcomes]}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (the ``mixed_models.json`` export)."""
        return {
            "random_slope": self.random_slope,
            "measures_problem": self.measures_problem,
            "outcomes": [o.to_dict() for o in self.outcomes],
        }


def analyse_mixed_models(
    result: StudyAnalysis,
    *,
    random_slope: bool = True,
    keys: Sequence[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> StudyMixedModels:
    """Fit the mixed models of every per-session measure of an analysed study.

    Parameters
    ----------
    result : StudyAnalysis
        From :func:`analysis.study.analyse_study`.
    random_slope : bool
        Also fit and compare the random-slope model.
    keys : sequence of str, optional
        Only these measures (default: all per-session measures).
    progress : callable, optional
        Called with the measure's key before it is fitted (for a progress bar).

    Returns
    -------
    StudyMixedModels
    """
    measures, measures_problem = _measures(result)
    chosen = [o for o in result.outcomes if keys is None or o.key in keys]
    if keys is not None:
        unknown = sorted(set(keys) - {o.key for o in result.outcomes})
        if unknown:
            raise InvalidInputError(
                f"no per-session measure {unknown}; have {[o.key for o in result.outcomes]}"
            )
    languages = _languages(result)
    outcomes = []
    for outcome in chosen:
        if progress is not None:
            progress(outcome.key)
        outcomes.append(
            _outcome_models(
                outcome, measures, measures_problem, random_slope, result.confidence, languages
            )
        )
    return StudyMixedModels(
        outcomes=tuple(outcomes),
        measures=measures,
        measures_problem=measures_problem,
        random_slope=random_slope,
    )


LANGUAGE = "language"


def _languages(result: StudyAnalysis) -> pd.Series | None:
    """Each analysed participant's language, when the study ran in more than one: the linear
    mixed models then adjust for it (a covariate); None otherwise."""
    participants = result.dataset.participants
    if LANGUAGE not in participants.columns:
        return None
    analysed = participants[participants["participant"].isin(result.participants["participant"])]
    if analysed[LANGUAGE].nunique(dropna=True) < 2:
        return None
    return pd.Series(
        analysed[LANGUAGE].to_numpy(), index=analysed["participant"].to_numpy(), name=LANGUAGE
    )


def _measures(result: StudyAnalysis) -> tuple[pd.DataFrame, str]:
    dataset = result.dataset
    if dataset.steps_withheld:
        return pd.DataFrame(), dataset.steps_withheld
    analysed = set(result.participants["participant"])
    steps = dataset.steps[dataset.steps["participant"].isin(analysed)]
    if steps.empty:
        return pd.DataFrame(), "no adaptation steps have been recorded yet"
    try:
        measures = session_adaptation(
            steps,
            dataset.protocol["preferred_arms"],
            reply_levels=dataset.protocol.get("reply_levels"),
        )
    except AnalysisError as error:
        return pd.DataFrame(), str(error)
    return measures, ""


def _outcome_models(
    outcome: OutcomeAnalysis,
    measures: pd.DataFrame,
    measures_problem: str,
    random_slope: bool,
    confidence: float,
    languages: pd.Series | None = None,
) -> OutcomeMixedModels:
    dv = outcome.key if outcome.key not in (*_FACTORS, LANGUAGE) else "value"
    data = outcome.data.rename(columns={"value": dv})
    covariates: tuple[str, ...] = ()
    if languages is not None:
        data = data.assign(**{LANGUAGE: data["participant"].map(languages).to_numpy()})
        if data[LANGUAGE].dropna().nunique() > 1 and not data[LANGUAGE].isna().any():
            covariates = (LANGUAGE,)
    lmm = ordinal = adaptation = None
    lmm_problem = ordinal_problem = adaptation_problem = ""
    try:
        lmm = linear_mixed_models(
            data,
            dv=dv,
            within="session",
            between="condition",
            subject="participant",
            random_slope=random_slope,
            confidence=confidence,
            covariates=covariates,
        )
    except AnalysisError as error:
        lmm_problem = str(error)
    if _is_single_item(outcome):
        try:
            ordinal = ordinal_model(
                data,
                dv=dv,
                within="session",
                between="condition",
                subject="participant",
                confidence=confidence,
            )
        except AnalysisError as error:
            ordinal_problem = str(error)
    else:
        ordinal_problem = "the ordinal model is fitted for single Likert items, not scale scores"
    if measures_problem:
        adaptation_problem = measures_problem
    else:
        try:
            adaptation = adaptation_trust(measures, data, dv=dv, confidence=confidence)
        except AnalysisError as error:
            adaptation_problem = str(error)
    excluded = 0 if outcome.anova is None else len(outcome.anova.excluded)
    return OutcomeMixedModels(
        key=outcome.key,
        label=outcome.label,
        lmm=lmm,
        lmm_problem=lmm_problem,
        ordinal=ordinal,
        ordinal_problem=ordinal_problem,
        adaptation=adaptation,
        adaptation_problem=adaptation_problem,
        anova_excluded=excluded,
    )


def _is_single_item(outcome: OutcomeAnalysis) -> bool:
    values = outcome.data["value"].to_numpy(float)
    return outcome.kind == "item" and not not_single_item(values, outcome.key)
