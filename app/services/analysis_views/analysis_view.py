"""The PI's analysis page: each measure's mixed ANOVA, descriptives and figure, ready to render.

The numbers come from :func:`analysis.study.analyse_study` and are formatted with the analysis
package's APA helpers, so the page, the report and ``trustlab anova`` say the same thing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from analysis.apa import format_number, format_p, format_proportion, sphericity_sentence
from analysis.figures import adaptation_payload_from_curves, mean_ci_payload_from_cells
from analysis.prose import count, item_title
from analysis.study import StudyAnalysis
from app.services.analysis_views.dashboard import json_safe


def _num(value: Any, decimals: int = 2) -> str:
    return (
        "—"
        if value is None or (isinstance(value, float) and math.isnan(value))
        else (format_number(float(value), decimals))
    )


def _prop(value: Any) -> str:
    return (
        "—"
        if value is None or (isinstance(value, float) and math.isnan(value))
        else (format_proportion(float(value)))
    )


def _p(value: Any) -> str:
    return (
        "—"
        if value is None or (isinstance(value, float) and math.isnan(value))
        else (format_p(float(value)).removeprefix("p ").removeprefix("= "))
    )


@dataclass
class OutcomeView:
    """One measure's results as strings and a figure payload."""

    key: str
    label: str
    problem: str
    sentences: list[str] = field(default_factory=list)
    anova: list[dict[str, str]] = field(default_factory=list)
    sphericity: str = ""
    descriptives: list[dict[str, str]] = field(default_factory=list)
    figure: dict[str, Any] | None = None


@dataclass
class AnalysisView:
    """The whole page."""

    ss_type: int
    outcomes: list[OutcomeView]
    exclusions: list[dict[str, str]]
    person_scores: list[dict[str, str]]
    adaptation: dict[str, Any] | None
    adaptation_problem: str
    analysed: int

    @property
    def analysed_text(self) -> str:
        """``1 participant analysed`` / ``24 participants analysed``."""
        return count(self.analysed, "participant") + " analysed"


def analysis_view(result: StudyAnalysis) -> AnalysisView:
    """Format an analysis for the page."""
    outcomes = []
    for outcome in result.outcomes:
        title = item_title(outcome.label, reverse_keyed=outcome.reverse_keyed)
        view = OutcomeView(outcome.key, title, outcome.problem)
        if outcome.anova is not None and outcome.sentences is not None:
            view.sentences = [str(text) for text in outcome.sentences["text"]]
            view.anova = [
                {
                    "source": str(row.Source),
                    "F": _num(row.F),
                    "df1": _num(row.DF1, 0),
                    "df2": _num(row.DF2, 0),
                    "p": _p(row.p_unc),
                    "np2": _prop(row.np2),
                    "ng2": _prop(row.ng2),
                    "eps": _prop(row.eps),
                    "p_gg": _p(row.p_GG_corr),
                }
                for row in outcome.anova.table.itertuples()
            ]
            view.sphericity = sphericity_sentence(outcome.anova)
        if len(outcome.descriptives):
            view.descriptives = [
                {
                    "condition": str(row.condition),
                    "session": str(row.session),
                    "n": str(row.n),
                    "mean": _num(row.mean),
                    "sd": _num(row.sd),
                    "ci": f"[{_num(row.ci_low)}, {_num(row.ci_high)}]",
                }
                for row in outcome.descriptives.itertuples()
            ]
            view.figure = json_safe(
                mean_ci_payload_from_cells(
                    outcome.descriptives,
                    dv=outcome.key,
                    within="session",
                    between="condition",
                    confidence=result.confidence,
                    title=f"{title}: mean ± 95 % CI",
                    y_range=outcome.value_range,
                    within_label="Session",
                    style="point",
                    colors=result.colors,
                )
            )
        outcomes.append(view)
    categories = list(result.dataset.protocol["preferred_arms"])
    adaptation = None
    if len(result.adaptation):
        adaptation = json_safe(
            adaptation_payload_from_curves(
                result.adaptation, categories, confidence=result.confidence, colors=result.colors
            )
        )
    return AnalysisView(
        ss_type=result.ss_type,
        outcomes=outcomes,
        exclusions=[
            {k: str(v) for k, v in row.items()} for row in result.exclusions().to_dict("records")
        ],
        person_scores=[
            {
                "scale": str(r["scale"]),
                "condition": str(r["condition"]),
                "n": str(r["n"]),
                "mean": _num(r["mean"]),
                "sd": _num(r["sd"]),
            }
            for r in result.person_summary.to_dict("records")
        ],
        adaptation=adaptation,
        adaptation_problem=result.adaptation_problem,
        analysed=len(result.participants),
    )
