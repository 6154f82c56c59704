"""The analysis page's "Mixed models" section: one measure's models, ready to render.

Numbers are formatted with the analysis package's APA helpers and sentences come from
:mod:`analysis.mixed_prose`, so the page, the report and ``trustlab mixed`` say the same thing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from analysis.adaptation_trust import MEASURES
from analysis.apa import format_number, format_p
from analysis.figures import trust_confidence_payload
from analysis.mixed_models import OutcomeMixedModels
from analysis.mixed_prose import (
    adaptation_sentences,
    comparison_sentence,
    covariate_sentences,
    lmm_sentences,
    ordinal_sentences,
)
from analysis.prose import item_title
from analysis.study import OutcomeAnalysis, StudyAnalysis
from app.services.analysis_views.dashboard import json_safe


def _num(value: Any, decimals: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return format_number(float(value), decimals)


def _p(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return format_p(float(value)).removeprefix("p ").removeprefix("= ")


@dataclass
class FitView:
    """One linear mixed model: status, tests, variances, marginal means."""

    name: str
    formula: str
    status: str
    converged: bool
    df_method: str = ""
    tests: list[dict[str, str]] = field(default_factory=list)
    variance: list[dict[str, str]] = field(default_factory=list)
    emmeans: list[dict[str, str]] = field(default_factory=list)
    aic: str = ""


@dataclass
class MixedView:
    """The section for one measure."""

    key: str
    label: str
    choices: list[tuple[str, str]]
    random_slope: bool
    lmm_problem: str = ""
    lmm_sentences: list[str] = field(default_factory=list)
    comparison: str = ""
    fits: list[FitView] = field(default_factory=list)
    kept: list[dict[str, str]] = field(default_factory=list)
    ordinal_problem: str = ""
    ordinal_sentences: list[str] = field(default_factory=list)
    ordinal_rows: list[dict[str, str]] = field(default_factory=list)
    po_rows: list[dict[str, str]] = field(default_factory=list)
    adaptation_problem: str = ""
    adaptation_sentences: list[str] = field(default_factory=list)
    adaptation_rows: list[dict[str, str]] = field(default_factory=list)
    figure: dict[str, Any] | None = None


def _fit_view(fit: Any) -> FitView:
    view = FitView(fit.name, fit.formula, fit.status, fit.converged, fit.df_method)
    if not fit.converged:
        return view
    view.aic = _num(fit.aic, 1)
    view.tests = [
        {
            "source": str(r["Source"]),
            "F": _num(r["F"]),
            "df1": _num(r["df1"], 0),
            "df2": _num(r["df2"]),
            "p": _p(r["p"]),
        }
        for r in fit.tests.to_dict("records")
    ]
    view.variance = [
        {
            "component": str(r["component"]),
            "sd": _num(r["sd"], 3),
            "corr": _num(r["corr"], 3) if not pd.isna(r["corr"]) else "",
        }
        for r in fit.variance.to_dict("records")
    ]
    view.emmeans = [
        {
            "condition": str(r["condition"]),
            "session": str(r["session"]),
            "emmean": _num(r["emmean"]),
            "se": _num(r["se"], 3),
            "df": _num(r["df"], 1),
            "ci": f"[{_num(r['ci_low'])}, {_num(r['ci_high'])}]",
        }
        for r in fit.emmeans.to_dict("records")
    ]
    return view


def mixed_view(
    result: StudyAnalysis, models: OutcomeMixedModels, *, random_slope: bool
) -> MixedView:
    """Format one measure's mixed models for the page."""
    outcome: OutcomeAnalysis = result.outcome(models.key)
    title = item_title(outcome.label, reverse_keyed=outcome.reverse_keyed)
    view = MixedView(
        key=models.key,
        label=title,
        choices=[
            (o.key, item_title(o.label, reverse_keyed=o.reverse_keyed)) for o in result.outcomes
        ],
        random_slope=random_slope,
        lmm_problem=models.lmm_problem,
        ordinal_problem=models.ordinal_problem,
        adaptation_problem=models.adaptation_problem,
    )
    if models.lmm is not None:
        # A specified (registered) covariate these models had to leave out is said here too.
        view.lmm_sentences = lmm_sentences(models.lmm) + covariate_sentences(
            models.covariates_left_out
        )
        view.comparison = comparison_sentence(models.lmm)
        view.fits = [_fit_view(fit) for fit in models.lmm.models]
        view.kept = [
            {
                "participant": str(r["subject"]),
                "condition": str(r["between"]),
                "reason": str(r["reason"]),
            }
            for r in models.lmm.kept.to_dict("records")
        ]
    if models.ordinal is not None:
        view.ordinal_sentences = ordinal_sentences(models.ordinal)
        view.ordinal_rows = [
            {
                "term": str(r["term"]),
                "estimate": _num(r["estimate"]),
                "se": _num(r["se"], 3),
                "odds_ratio": _num(r["odds_ratio"]),
                "p": _p(r["p"]),
            }
            for r in models.ordinal.coefficients.to_dict("records")
        ]
        view.po_rows = [
            {
                "source": str(r["Source"]),
                "chi2": _num(r["chi2"]),
                "df": str(int(r["df"])),
                "p": _p(r["p"]),
            }
            for r in models.ordinal.po_check.to_dict("records")
        ]
    if models.adaptation is not None:
        view.adaptation_sentences = adaptation_sentences(models.adaptation)
        view.adaptation_rows = [
            {
                "measure": MEASURES[str(r["measure"])],
                "part": str(r["part"]),
                "estimate": _num(r["estimate"]),
                "ci": f"[{_num(r['ci_low'])}, {_num(r['ci_high'])}]",
                "df": _num(r["df"], 1),
                "p": _p(r["p"]),
            }
            for r in models.adaptation.effects.to_dict("records")
        ]
        data = models.adaptation.data
        if len(data) and "confidence" in data.columns:
            view.figure = json_safe(
                trust_confidence_payload(
                    data,
                    dv=models.adaptation.dv,
                    title=f"{title} and the robot's confidence",
                    y_label=title,
                    y_range=outcome.value_range,
                    colors=result.colors,
                )
            )
    return view
