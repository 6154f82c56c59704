"""Self-contained, offline HTML report of a study.

One file a PI can e-mail, archive with the paper, or open in a lab without internet: methods
written from the protocol, participants and exclusions, for every per-session outcome the APA
sentences, the ANOVA table (with sphericity), descriptives, marginal means, post-hoc tests and
figures, then the adaptation curves, the questionnaire scores and a manifest saying exactly
what produced it. plotly.js is embedded once, inline; nothing is fetched from the network.
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Callable, Mapping, Sequence
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any

import pandas as pd
import plotly.io as pio
import plotly.offline

from analysis.anova import SSType
from analysis.apa import format_df, format_number, format_p, format_proportion, sphericity_sentence
from analysis.dataset import StudyDataset
from analysis.figures import (
    adaptation_payload_from_curves,
    mean_ci_payload_from_cells,
    score_distribution_payload,
    trajectories_payload,
    trust_confidence_payload,
)
from analysis.methods import (
    analysis_paragraph,
    design_paragraph,
    exclusion_sentence,
    languages_paragraph,
    participants_paragraph,
    translation_references,
)
from analysis.mixed_models import StudyMixedModels, analyse_mixed_models
from analysis.mixed_prose import (
    adaptation_sentences,
    comparison_sentence,
    covariate_sentences,
    lmm_sentences,
    ordinal_sentences,
)
from analysis.prereg import check_registration, data_sentence
from analysis.prose import count, item_title
from analysis.specification import analysis_specification
from analysis.study import ALL_ANALYSES, OutcomeAnalysis, StudyAnalysis, analyse_study

__all__ = [
    "MAX_EXCLUSION_ROWS",
    "MAX_TRAJECTORIES",
    "analysis_provenance",
    "build_report",
    "write_report",
]

MAX_TRAJECTORIES = 100
"""Participants per condition drawn in the report's trajectory figures (first codes)."""

MAX_EXCLUSION_ROWS = 1000
"""Exclusion rows listed in the report; the rest are counted (all are in the exports)."""

_PACKAGES = ("numpy", "pandas", "scipy", "pingouin", "statsmodels", "plotly", "pyreadstat")

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;
max-width:1100px;padding:1.5rem;color:#1a1a1a;line-height:1.45}
h1{font-size:1.7rem;margin-bottom:.2rem}h2{border-bottom:2px solid #ddd;padding-bottom:.2rem;
margin-top:2.2rem}h3{margin-top:1.4rem}
table{border-collapse:collapse;margin:.6rem 0 1rem;font-size:.88rem}
th,td{border-bottom:1px solid #ddd;padding:.25rem .55rem;text-align:right;vertical-align:top}
th{background:#f4f4f4}td.l,th.l{text-align:left}
.apa{background:#f6f8fb;border-left:4px solid #0072B2;padding:.5rem .8rem}
.note{color:#555;font-size:.9rem}.problem{background:#fff4e5;border-left:4px solid #E69F00;
padding:.5rem .8rem}pre{background:#f6f6f6;padding:.8rem;overflow-x:auto;font-size:.82rem}
nav ul{columns:2}details{margin:.5rem 0}.figure{margin:.5rem 0 1rem}
"""


@lru_cache(maxsize=1)
def _plotly_js() -> str:
    return plotly.offline.get_plotlyjs()


@lru_cache(maxsize=1)
def _package_versions() -> tuple[tuple[str, str], ...]:
    versions = []
    for name in _PACKAGES:
        try:
            versions.append((name, metadata.version(name)))
        except metadata.PackageNotFoundError:  # pragma: no cover - all are dependencies
            versions.append((name, "not installed"))
    return tuple(versions)


def analysis_provenance(ss_type: int, confidence: float) -> dict[str, Any]:
    """Settings and package versions of the analysis, added to the report's manifest."""
    return {"ss_type": ss_type, "confidence": confidence, "packages": dict(_package_versions())}


def build_report(
    dataset: StudyDataset | StudyAnalysis,
    *,
    ss_type: SSType = 3,
    confidence: float = 0.95,
    title: str | None = None,
    mixed: StudyMixedModels | None = None,
) -> str:
    """The complete report as one HTML string.

    Parameters
    ----------
    dataset : StudyDataset or StudyAnalysis
        The study, or an analysis of it already computed (then ``ss_type`` and ``confidence``
        are taken from it and the arguments are ignored).
    ss_type : {3, 2}
        Sums of squares of the ANOVAs (default type III).
    confidence : float
        Coverage of the confidence intervals.
    title : str, optional
        Heading; default "Study report: <study title>" (``protocol["study"]``).
    mixed : StudyMixedModels, optional
        The mixed models (:func:`analysis.mixed_models.analyse_mixed_models`) of this analysis,
        reported in their own section beside the ANOVAs; without them the section is left out.

    Returns
    -------
    str
        A complete HTML document (UTF-8) with plotly.js inline; it opens offline.
    """
    if isinstance(dataset, StudyAnalysis):
        result = dataset
    else:
        result = analyse_study(dataset, ss_type=ss_type, confidence=confidence)
    confidence = result.confidence
    study = result.dataset.protocol["study"]
    heading = title or f"Study report: {study}"
    figures = _FigureCounter()
    sections = [
        _methods(result, confidence),
        *([_registration(result, mixed)] if result.dataset.registration is not None else []),
        _participants(result),
        *[_outcome_section(result, o, figures, confidence) for o in result.outcomes],
        *([mixed_models_section(result, mixed, figures)] if mixed is not None else []),
        _adaptation(result, figures, confidence),
        _questionnaires(result, figures),
        _manifest(result, confidence),
    ]
    toc = "".join(
        f'<li><a href="#{anchor}">{html.escape(name)}</a></li>' for anchor, name, _ in sections
    )
    body = "\n".join(content for _, _, content in sections)
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{html.escape(heading)}</title>\n<style>{_CSS}</style>\n"
        f'<script type="text/javascript">{_plotly_js()}</script>\n</head>\n<body>\n'
        f"<h1>{html.escape(heading)}</h1>\n"
        f'<p class="note">Generated by trustlab\'s analysis package from the data described in '
        f'the <a href="#manifest">manifest</a>. Figures are interactive and work offline.</p>\n'
        f"<nav><ul>{toc}</ul></nav>\n{body}\n</body>\n</html>\n"
    )


def write_report(
    dataset: StudyDataset | StudyAnalysis,
    path: str | Path,
    *,
    ss_type: SSType = 3,
    confidence: float = 0.95,
    title: str | None = None,
    mixed_models: bool = True,
) -> Path:
    """Write :func:`build_report` to ``path`` (UTF-8) and return the path; with
    ``mixed_models`` (the default) the mixed models of every measure are fitted and reported."""
    result = (
        dataset
        if isinstance(dataset, StudyAnalysis)
        else analyse_study(dataset, ss_type=ss_type, confidence=confidence)
    )
    mixed = analyse_mixed_models(result) if mixed_models else None
    target = Path(path)
    target.write_text(build_report(result, title=title, mixed=mixed), encoding="utf-8")
    return target


# ------------------------------------------------------------------------------ helpers


class _FigureCounter:
    """Stable figure ids (fig-1, fig-2, …) so the same data give the same bytes."""

    def __init__(self) -> None:
        self.n = 0

    def html(self, payload: Mapping[str, Any], height: int = 440) -> str:
        self.n += 1
        div = pio.to_html(
            {"data": payload["data"], "layout": payload["layout"]},
            include_plotlyjs=False,
            full_html=False,
            validate=False,
            div_id=f"fig-{self.n}",
            default_height=f"{height}px",
            config={"displaylogo": False, "responsive": True},
        )
        return f'<div class="figure">{div}</div>'


def _cell(value: Any, fmt: Callable[[Any], str] | None = None) -> str:
    if fmt is not None:
        return html.escape(fmt(value))
    if value is None or (isinstance(value, float) and math.isnan(value)) or value is pd.NA:
        return "—"
    if isinstance(value, float):
        return html.escape(format_number(value))
    return html.escape(str(value))


def _table(
    frame: pd.DataFrame,
    columns: Sequence[tuple[str, str, Callable[[Any], str] | None]],
    *,
    left: Sequence[str] = (),
) -> str:
    """An HTML table of ``frame``: (column, header, formatter) triples."""
    head = "".join(
        f'<th class="{"l" if col in left else ""}">{html.escape(header)}</th>'
        for col, header, _ in columns
    )
    rows = []
    for record in frame.to_dict("records"):
        cells = "".join(
            f'<td class="{"l" if col in left else ""}">{_cell(record.get(col), fmt)}</td>'
            for col, _, fmt in columns
        )
        rows.append(f"<tr>{cells}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


def _p(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return format_p(float(value)).replace("p = ", "").replace("p ", "")


def _prop(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return format_proportion(float(value), 3)


def _num(decimals: int) -> Callable[[Any], str]:
    def fmt(value: Any) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "—"
        return format_number(float(value), decimals)

    return fmt


def _df(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return format_df(float(value))


def _family(value: Any) -> str:
    return {"within": "sessions, within condition", "between": "conditions, at session"}.get(
        str(value), str(value)
    )


def _int(value: Any) -> str:
    return "—" if value is None or pd.isna(value) else str(int(value))


# ------------------------------------------------------------------------------ sections


def _methods(result: StudyAnalysis, confidence: float) -> tuple[str, str, str]:
    protocol = result.dataset.protocol
    paragraphs = [
        participants_paragraph(protocol, result.sample),
        design_paragraph(protocol, result.dataset.instruments),
        analysis_paragraph(protocol, len(protocol["conditions"]), result.ss_type, confidence)
        + " "
        + _exclusion_sentence(result),
    ]
    paragraphs += [p for p in (languages_paragraph(protocol),) if p]  # several languages
    citations = sorted(
        {spec.citation for spec in result.dataset.instruments if spec.citation}
        | {scale.citation for scale in result.dataset.scales if scale.citation}
        | set(translation_references(protocol))
    )
    refs = "".join(f"<li>{html.escape(c)}</li>" for c in citations)
    content = (
        '<section id="methods"><h2>Methods</h2>'
        + "".join(f"<p>{html.escape(p)}</p>" for p in paragraphs)
        + (f"<h3>Instrument sources</h3><ul>{refs}</ul>" if refs else "")
        + "</section>"
    )
    return "methods", "Methods", content


def _registration(result: StudyAnalysis, mixed: StudyMixedModels | None) -> tuple[str, str, str]:
    """Whether the analyses below are the registered ones (:mod:`analysis.prereg`), and when
    the registration was made against the data (before any participant, or after some)."""
    registration = result.dataset.registration
    assert registration is not None
    check = check_registration(
        registration, result, mixed=mixed, source=result.dataset.registration_source
    )
    when = html.escape(check.registered_at or "an unknown date")
    source = f" ({html.escape(check.source)})" if check.source else ""
    # Never a bare "as registered": when it was registered against the data comes with it.
    timing = html.escape(data_sentence(registration))
    if check.as_registered:
        body = (
            f'<p class="apa"><strong>As registered.</strong> {timing} The protocol, the '
            f"measures, the models (with their covariates), α, the sums of squares, the "
            f"confidence level and the exclusion rules of this report are those of that "
            f"pre-registration{source}.</p>"
        )
    else:
        items = "".join(f"<li>{html.escape(d)}</li>" for d in check.deviations)
        body = (
            f'<div class="problem"><p><strong>Deviations from the pre-registration</strong> of '
            f"{when}{source}:</p><ul>{items}</ul><p>{timing}</p></div>"
        )
    content = f'<section id="registration"><h2>Registration</h2>{body}</section>'
    return "registration", "Registration", content


def _exclusion_sentence(result: StudyAnalysis) -> str:
    return exclusion_sentence(result.exclusions().to_dict("records"), everywhere=ALL_ANALYSES)


def _participants(result: StudyAnalysis) -> tuple[str, str, str]:
    participants = result.dataset.participants
    counts = (
        participants.groupby(["condition", "status"], sort=True).size().rename("n").reset_index()
    )
    exclusions = result.exclusions()
    listed = ""
    if len(exclusions):
        # One row per participant and reason: "no trust_1 value for session 4" and
        # "no trust_2 value for session 4" are the same reason for two analyses.
        generic = [
            reason.replace(f"no {analysis} value", "no value")
            for reason, analysis in zip(exclusions["reason"], exclusions["analysis"], strict=True)
        ]
        merged = (
            exclusions.assign(reason=generic)
            .groupby(["participant", "condition", "reason"], sort=False)["analysis"]
            .agg(lambda s: ", ".join(map(str, s)))
            .reset_index()
        )
        shown = merged.head(MAX_EXCLUSION_ROWS)
        listed = _table(
            shown,
            [
                ("participant", "Participant", None),
                ("condition", "Condition", None),
                ("analysis", "Excluded from", None),
                ("reason", "Reason", None),
            ],
            left=("participant", "condition", "analysis", "reason"),
        )
        if len(merged) > len(shown):
            listed += (
                f'<p class="note">… and {len(merged) - len(shown)} more exclusions (every '
                "participant's data are in the exports).</p>"
            )
    else:
        listed = f"<p>{html.escape(_exclusion_sentence(result))}</p>"
    content = (
        '<section id="participants"><h2>Participants and exclusions</h2>'
        f"<p>{html.escape(participants_paragraph(result.dataset.protocol, result.sample))}</p>"
        + _table(
            counts,
            [("condition", "Condition", None), ("status", "Status", None), ("n", "n", _int)],
            left=("condition", "status"),
        )
        + _per_language(participants)
        + "<h3>Exclusions</h3>"
        + (
            f"<p>Statuses excluded from every analysis: "
            f"{html.escape(', '.join(sorted(result.dataset.excluded_statuses)) or 'none')}.</p>"
        )
        + listed
        + "</section>"
    )
    return "participants", "Participants and exclusions", content


def _per_language(participants: pd.DataFrame) -> str:
    """Participants per language and condition, for a study run in more than one language
    (nothing for a study in one: the table would say only that)."""
    if "language" not in participants or participants["language"].nunique(dropna=True) < 2:
        return ""
    counts = (
        participants.groupby(["language", "condition"], sort=True).size().rename("n").reset_index()
    )
    return "<h3>Languages</h3>" + _table(
        counts,
        [("language", "Language", None), ("condition", "Condition", None), ("n", "n", _int)],
        left=("language", "condition"),
    )


def _outcome_title(outcome: OutcomeAnalysis) -> str:
    return f"{outcome.key}: {item_title(outcome.label, reverse_keyed=outcome.reverse_keyed)}"


def _outcome_section(
    result: StudyAnalysis, outcome: OutcomeAnalysis, figures: _FigureCounter, confidence: float
) -> tuple[str, str, str]:
    anchor = f"outcome-{outcome.key}"
    title = _outcome_title(outcome)
    parts = [f'<section id="{html.escape(anchor)}"><h2>{html.escape(title)}</h2>']
    incomplete = len(outcome.excluded)
    excluded_note = (
        f"{incomplete} excluded as incomplete (listed under Exclusions)"
        if incomplete
        else "none excluded as incomplete"
    )
    if outcome.anova is None:
        parts.append(f'<p class="problem">{html.escape(outcome.problem)}</p>')
        if incomplete:
            parts.append(f"<p>{html.escape(excluded_note[0].upper() + excluded_note[1:])}.</p>")
    else:
        anova = outcome.anova
        sentences = outcome.sentences
        if sentences is not None:
            items = "".join(f"<li>{html.escape(t)}</li>" for t in sentences["text"])
            parts.append(f'<div class="apa"><ul>{items}</ul></div>')
        parts.append(
            f"<p>{html.escape(sphericity_sentence(anova))}. Type "
            f"{'III' if anova.ss_type == 3 else 'II'} sums of squares; "
            f"{count(anova.n_subjects_used, 'participant')} with complete data, "
            f"{html.escape(excluded_note)}.</p>"
        )
        parts.append(
            _table(
                anova.table,
                [
                    ("Source", "Effect", None),
                    ("SS", "SS", _num(3)),
                    ("DF1", "df1", _df),
                    ("DF2", "df2", _df),
                    ("MS", "MS", _num(3)),
                    ("F", "F", _num(2)),
                    ("p_unc", "p", _p),
                    ("np2", "ηp²", _prop),
                    ("ng2", "ηG²", _prop),
                    ("eps", "ε (GG)", _prop),
                    ("p_GG_corr", "p (GG)", _p),
                    ("W_spher", "Mauchly W", _prop),
                    ("p_spher", "p (Mauchly)", _p),
                ],
                left=("Source",),
            )
        )
    if len(outcome.descriptives):
        payload = mean_ci_payload_from_cells(
            outcome.descriptives,
            dv=outcome.key,
            within="session",
            between="condition",
            confidence=confidence,
            title=f"{outcome.key}: mean ± {confidence:.0%} CI",
            y_label=outcome.label if len(outcome.label) < 60 else outcome.key,
            y_range=outcome.value_range,
            within_label="Session",
            style="point",
            colors=result.colors,
        )
        parts.append(figures.html(payload))
        parts.append("<h3>Descriptives</h3>")
        parts.append(
            _table(
                outcome.descriptives,
                [
                    ("condition", "Condition", None),
                    ("session", "Session", None),
                    ("n", "n", _int),
                    ("mean", "M", _num(2)),
                    ("sd", "SD", _num(2)),
                    ("se", "SE", _num(2)),
                    ("ci_low", f"{confidence:.0%} CI low", _num(2)),
                    ("ci_high", f"{confidence:.0%} CI high", _num(2)),
                ],
                left=("condition",),
            )
        )
    if outcome.marginal_conditions is not None and outcome.marginal_sessions is not None:
        emm_cols: list[tuple[str, str, Callable[[Any], str] | None]] = [
            ("n", "n", _int),
            ("mean", "M", _num(2)),
            ("se", "SE", _num(3)),
            ("df", "df", _df),
            ("ci_low", "CI low", _num(2)),
            ("ci_high", "CI high", _num(2)),
        ]
        parts.append("<h3>Estimated marginal means</h3>")
        parts.append(
            _table(outcome.marginal_conditions, [("condition", "Condition", None), *emm_cols])
        )
        parts.append(_table(outcome.marginal_sessions, [("session", "Session", None), *emm_cols]))
    if outcome.posthoc is not None and len(outcome.posthoc):
        parts.append("<h3>Post-hoc comparisons (Holm)</h3>")
        parts.append(
            _table(
                outcome.posthoc,
                [
                    ("family", "Comparison", _family),
                    ("at", "At", None),
                    ("A", "A", None),
                    ("B", "B", None),
                    ("mean_diff", "M(A) − M(B)", _num(2)),
                    ("T", "t", _num(2)),
                    ("dof", "df", _df),
                    ("p_unc", "p", _p),
                    ("p_adj", "p (Holm)", _p),
                    ("cohen_d", "d", _num(2)),
                    ("note", "Note", None),
                ],
                left=("family", "at", "A", "B", "note"),
            )
        )
    if len(outcome.data):
        traj = trajectories_payload(
            outcome.data,
            dv="value",
            within="session",
            between="condition",
            subject="participant",
            max_per_condition=MAX_TRAJECTORIES,
            title=f"{outcome.key}: individual trajectories",
            y_label=outcome.key,
            y_range=outcome.value_range,
            colors=result.colors,
        )
        shown = ", ".join(f"{k}: {v} of {traj['total'][k]}" for k, v in traj["shown"].items())
        parts.append(
            f"<details><summary>Individual trajectories ({html.escape(shown)})</summary>"
            f"{figures.html(traj)}</details>"
        )
    parts.append("</section>")
    return anchor, title, "".join(parts)


def mixed_models_section(
    result: StudyAnalysis, mixed: StudyMixedModels, figures: _FigureCounter
) -> tuple[str, str, str]:
    """The mixed models of every measure: sentences, the preferred model's tests, the kept
    participants, the ordinal model and whether trust follows the robot's confidence."""
    # The models as the analysis specification (the registered one) describes them.
    planned = [
        analysis.description
        for analysis in analysis_specification(result.dataset.protocol)
        if analysis.result.startswith("OutcomeMixedModels.")
    ]
    parts = [
        '<section id="mixed-models"><h2>Mixed models</h2>',
        "<p>Beside the ANOVAs, these models keep every rating, including those of participants "
        "with a missing session:</p><ul>"
        + "".join(f"<li>{html.escape(text)}.</li>" for text in planned)
        + "</ul>",
    ]
    outcomes = {o.key: o for o in result.outcomes}
    for models in mixed.outcomes:
        outcome = outcomes[models.key]
        title = item_title(outcome.label, reverse_keyed=outcome.reverse_keyed)
        parts.append(f"<h3>{html.escape(title)} ({html.escape(models.key)})</h3>")
        sentences: list[str] = []
        if models.lmm is not None:
            sentences += lmm_sentences(models.lmm)
            if models.lmm.slope is not None:
                sentences.append(comparison_sentence(models.lmm))
        else:
            sentences.append(models.lmm_problem)
        sentences += covariate_sentences(models.covariates_left_out)
        if models.ordinal is not None:
            sentences += ordinal_sentences(models.ordinal)
        elif models.ordinal_problem:
            sentences.append(f"No ordinal model: {models.ordinal_problem}.")
        if models.adaptation is not None:
            sentences += adaptation_sentences(models.adaptation)
        else:
            sentences.append(f"No adaptation-and-trust model: {models.adaptation_problem}.")
        parts.append(
            '<ul class="apa">' + "".join(f"<li>{html.escape(t)}</li>" for t in sentences) + "</ul>"
        )
        if models.lmm is not None and models.lmm.preferred.converged:
            fit = models.lmm.preferred
            parts.append(
                f'<p class="note">{html.escape(fit.name.capitalize())} model: '
                f"<code>{html.escape(fit.formula)}</code></p>"
            )
            parts.append(
                _table(
                    fit.tests,
                    [
                        ("Source", "Effect", None),
                        ("F", "F", _num(2)),
                        ("df1", "df1", _df),
                        ("df2", f"df2 ({fit.df_method})", _num(2)),
                        ("p", "p", _p),
                    ],
                    left=("Source",),
                )
            )
            if len(models.lmm.kept):
                kept = ", ".join(str(s) for s in models.lmm.kept["subject"])
                parts.append(f"<p>Kept here, excluded by the ANOVA: {html.escape(kept)}.</p>")
        if models.adaptation is not None and "confidence" in models.adaptation.data.columns:
            data = models.adaptation.data
            payload = trust_confidence_payload(
                data,
                dv=models.adaptation.dv,
                title=f"{title} and the robot's confidence",
                y_label=title,
                y_range=outcome.value_range,
                colors=result.colors,
            )
            parts.append(figures.html(payload, height=400))
    parts.append("</section>")
    return "mixed-models", "Mixed models", "".join(parts)


def _adaptation(
    result: StudyAnalysis, figures: _FigureCounter, confidence: float
) -> tuple[str, str, str]:
    parts = ['<section id="adaptation"><h2>Adaptation</h2>']
    curves = result.adaptation
    if result.adaptation_problem:
        parts.append(f'<p class="problem">{html.escape(result.adaptation_problem)}</p>')
    elif curves.empty:
        parts.append("<p>No adaptation steps have been recorded.</p>")
    else:
        categories = list(result.dataset.protocol["preferred_arms"])
        payload = adaptation_payload_from_curves(
            curves, categories, confidence=confidence, colors=result.colors
        )
        parts.append(
            "<p>Mean probability that each category's learner gives to the question the "
            "protocol declares preferred, before the first answer (iteration 0) and after each "
            f"answer, with {confidence:.0%} confidence bands.</p>"
        )
        parts.append(figures.html(payload, height=420))
        last = curves.loc[
            curves.groupby(["condition", "category"], sort=False)["iteration"].idxmax()
        ]
        parts.append(
            _table(
                last,
                [
                    ("condition", "Condition", None),
                    ("category", "Category", None),
                    ("iteration", "Last iteration", _int),
                    ("n", "n", _int),
                    ("mean", "M p(preferred)", _num(3)),
                    ("ci_low", "CI low", _num(3)),
                    ("ci_high", "CI high", _num(3)),
                ],
                left=("condition", "category"),
            )
        )
    parts.append("</section>")
    return "adaptation", "Adaptation", "".join(parts)


def _questionnaires(result: StudyAnalysis, figures: _FigureCounter) -> tuple[str, str, str]:
    parts = ['<section id="questionnaires"><h2>Questionnaire scores</h2>']
    scores = result.person_scores
    if scores.empty:
        parts.append("<p>No once-only questionnaire has been answered.</p>")
    else:
        labels = {s.name: s.label or s.name for s in result.dataset.scales}
        summary = result.person_summary.assign(label=lambda d: d["scale"].map(labels))
        parts.append(
            _table(
                summary,
                [
                    ("label", "Scale", None),
                    ("condition", "Condition", None),
                    ("n", "n", _int),
                    ("mean", "M", _num(2)),
                    ("sd", "SD", _num(2)),
                ],
                left=("label", "condition"),
            )
        )
        by_instrument = {s.name: s.instrument for s in result.dataset.scales}
        for instrument in dict.fromkeys(by_instrument[s] for s in scores["scale"].unique()):
            subset = scores[scores["scale"].map(by_instrument) == instrument]
            payload = score_distribution_payload(
                subset,
                scale_labels={k: v.split(" (")[0] for k, v in labels.items()},
                title=f"{instrument.upper()} scores by condition",
                colors=result.colors,
            )
            parts.append(figures.html(payload, height=420))
    parts.append("</section>")
    return "questionnaires", "Questionnaire scores", "".join(parts)


def _manifest(result: StudyAnalysis, confidence: float) -> tuple[str, str, str]:
    manifest = {
        "provided": dict(result.dataset.manifest),
        "protocol": result.dataset.protocol,
        "analysis": {
            **analysis_provenance(result.ss_type, confidence),
            "excluded_statuses": sorted(result.dataset.excluded_statuses),
        },
    }
    text = json.dumps(manifest, indent=2, sort_keys=True, ensure_ascii=False, default=str)
    content = (
        '<section id="manifest"><h2>Manifest</h2><p>What produced this report: the manifest '
        "supplied with the data (data hash, software versions, checkpoint hashes, seeds), the "
        "protocol summary, and the analysis settings and package versions.</p>"
        f"<pre>{html.escape(text)}</pre></section>"
    )
    return "manifest", "Manifest", content
