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
from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from analysis.adaptation_trust import AdaptationTrust, adaptation_trust, session_adaptation
from analysis.errors import AnalysisError, InvalidInputError
from analysis.lmm import LinearMixedModels, linear_mixed_models
from analysis.ordinal import OrdinalFit, not_single_item, ordinal_model
from analysis.specification import COVARIATES, planned
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
    covariates : tuple of str
        The specification's covariates the linear mixed models of this measure include.
    covariates_left_out : dict of str to str
        A specified covariate the models could not include, with why (every participant who
        rated it shares one level, or some lack the attribute): a deviation from the
        registration, which the report names.
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
    covariates: tuple[str, ...] = ()
    covariates_left_out: dict[str, str] = field(default_factory=dict)

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
            "covariates": list(self.covariates),
            "covariates_left_out": dict(self.covariates_left_out),
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
    attributes = _covariates(result)
    outcomes = []
    for outcome in chosen:
        if progress is not None:
            progress(outcome.key)
        outcomes.append(
            _outcome_models(
                outcome, measures, measures_problem, random_slope, result.confidence, attributes
            )
        )
    return StudyMixedModels(
        outcomes=tuple(outcomes),
        measures=measures,
        measures_problem=measures_problem,
        random_slope=random_slope,
    )


def _covariates(result: StudyAnalysis) -> dict[str, pd.Series]:
    """Each analysed participant's value of every covariate the specification
    (:func:`analysis.specification.analysis_specification`, from the protocol's languages and
    sites) gives the linear mixed models; whether a measure's models can include it is decided
    per measure, from those who rated it."""
    participants = result.dataset.participants
    analysed = participants[participants["participant"].isin(result.participants["participant"])]
    found = {}
    for column in planned(result.dataset.protocol, "lmm").covariates:
        values = analysed[column].to_numpy() if column in analysed else [None] * len(analysed)
        found[column] = pd.Series(
            values, index=analysed["participant"].to_numpy(), name=column, dtype=object
        )
    return found


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
    attributes: dict[str, pd.Series] | None = None,
) -> OutcomeMixedModels:
    dv = outcome.key if outcome.key not in (*_FACTORS, *COVARIATES) else "value"
    data = outcome.data.rename(columns={"value": dv})
    covariates: tuple[str, ...] = ()
    left_out: dict[str, str] = {}
    for column, values in (attributes or {}).items():
        data = data.assign(**{column: data["participant"].map(values).to_numpy()})
        rated = data.loc[data[dv].notna(), column]
        if rated.isna().any():
            left_out[column] = f"{rated.isna().sum()} ratings have no {column}"
        elif rated.nunique() < 2:
            level = ", ".join(map(str, rated.unique())) or "none"
            left_out[column] = f"every participant who rated it has the same {column} ({level})"
        else:
            covariates += (column,)
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
    excluded = len(outcome.excluded)
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
        covariates=covariates,
        covariates_left_out=left_out,
    )


def _is_single_item(outcome: OutcomeAnalysis) -> bool:
    values = outcome.data["value"].to_numpy(float)
    return outcome.kind == "item" and not not_single_item(values, outcome.key)
