"""A pre-registration of a study's analyses, and the check that the report ran what it registered.

Before the first participant, a PI registers (e.g. on OSF) what will be measured, how it will be
analysed, with what α, whom the analysis leaves out and why N is what it is. trustlab knows all
of it: the frozen protocol (and its SHA-256), the measures it defines, the models the report
fits, the exclusion rules :func:`analysis.study.analyse_study` applies, and a power analysis
(:mod:`analysis.power`). :func:`build_registration` writes them down as one JSON-ready dict;
:func:`registration_markdown` and :func:`registration_html` render it for people.

The *plan* part of a registration (:func:`analysis_plan`: protocol hash, measures, models, α,
sums of squares, exclusions) is the part a report can check: :func:`check_registration`
computes the same plan from the analysis it reports and lists every difference, so the report
says "as registered" or names each deviation. The models are the analysis specification
(:func:`analysis.specification.analysis_specification`, covariates included) that the fitting
code reads too, so a change to trustlab's analysis shows up as a deviation, and a covariate a
measure's models had to leave out is named as one.

A registration also records how much data there was when it was made
(:func:`data_at_registration`: participants enrolled, and those who had answered anything), so
a registration written after data collection began says so, and so does every report checked
against it.
"""

from __future__ import annotations

import html
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from analysis.dataset import StudyDataset
from analysis.mixed_models import StudyMixedModels
from analysis.power_simulation import SIMULATED_MODEL_NAMES
from analysis.specification import PlannedAnalysis, analysis_specification
from analysis.study import StudyAnalysis

__all__ = [
    "ALPHA",
    "FORMAT",
    "RegistrationCheck",
    "analysis_plan",
    "build_registration",
    "check_registration",
    "data_at_registration",
    "data_sentence",
    "plan_of",
    "planned_measures",
    "quality_rules",
    "registered_plan",
    "registration_html",
    "registration_markdown",
]

FORMAT = "trustlab-prereg/1"
"""The registration's format name (``prereg.json``'s ``format``)."""

ALPHA = 0.05
"""The level trustlab's reports test at: p < .05 is called significant, Mauchly's test at .05
decides the Greenhouse–Geisser correction, post-hoc tests are Holm-corrected to .05."""


def analysis_plan(
    *,
    protocol_sha256: str,
    measures: Sequence[Mapping[str, Any]],
    ss_type: int,
    confidence: float,
    excluded_statuses: Sequence[str],
    analyses: Sequence[PlannedAnalysis],
    alpha: float = ALPHA,
    quality: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The checkable part of a registration: what a report must have run to be "as registered".

    Parameters
    ----------
    measures : sequence of mapping
        ``{"key", "label", "reverse_keyed"}`` of each per-session measure, in report order.
    analyses : sequence of PlannedAnalysis
        The analysis specification (:func:`analysis.specification.analysis_specification`):
        ``models`` holds their descriptions, ``analyses`` their formulas and covariates.
    quality : mapping or None
        The data-quality rules (:class:`analysis.dataset.ProtocolSummary`'s ``quality``), when
        the study has them: their thresholds and excluding flags become exclusion rules.
    """
    exclusions: dict[str, Any] = {
        "statuses": sorted(excluded_statuses),
        "rules": [
            "participants whose status is "
            + (" or ".join(sorted(excluded_statuses)) or "(none)")
            + " are left out of every analysis and listed with the reason",
            "the mixed ANOVA of a measure keeps participants with a value in every session "
            "(complete cases); the others are listed with the reason",
            "participants without a single per-session rating or answer to the robot are "
            "left out of every analysis (no data) and listed with the reason",
            "the mixed models keep every participant with at least one value",
            "reverse-keyed items are reverse-scored before any analysis",
        ],
    }
    if quality is not None:
        exclusions["quality"] = dict(quality)
        exclusions["rules"] += quality_rules(quality)
    return {
        "protocol_sha256": protocol_sha256,
        "measures": [
            {
                "key": str(m["key"]),
                "label": str(m["label"]),
                "reverse_keyed": bool(m["reverse_keyed"]),
            }
            for m in measures
        ],
        "primary_measure": str(measures[0]["key"]) if measures else None,
        "models": [analysis.description for analysis in analyses],
        "analyses": [analysis.to_dict() for analysis in analyses],
        "alpha": alpha,
        "ss_type": ss_type,
        "confidence": confidence,
        "exclusions": exclusions,
    }


def quality_rules(quality: Mapping[str, Any]) -> list[str]:
    """The data-quality rules in words: how each flag is raised, and which exclude."""
    away = quality.get("max_away_seconds")
    flags = [
        f"'attention': more than {quality.get('attention_failures_allowed', 0)} attention "
        "check(s) answered otherwise than expected",
        f"'speeding': a questionnaire page answered in less than "
        f"{quality.get('min_seconds_per_item')} s per item",
        f"'straightlining': the same answer to every Likert item of a page with at least "
        f"{quality.get('straightlining_min_items')} of them",
        "'away': "
        + (f"the study's page hidden for more than {away} s in all" if away is not None else "off"),
        "'second_id_same_browser': an online participant's browser had joined under another "
        "recruitment ID",
    ]
    excluded = list(quality.get("exclude", []))
    consequence = (
        "participants with the flag(s) "
        + ", ".join(f"'{flag}'" for flag in excluded)
        + " are left out of every analysis and listed with the reason"
        if excluded
        else "no flag excludes a participant: the flags are reported and exported only"
    )
    return ["data-quality flags: " + "; ".join(flags), consequence]


def planned_measures(dataset: StudyDataset) -> list[dict[str, Any]]:
    """Every measure the report will analyse per session, as :func:`analysis.study.analyse_study`
    picks them (Likert and numeric items of per-session instruments, then the scales scored
    from them), whether or not anyone has answered yet: a registration comes before the data."""
    per_session = [spec for spec in dataset.instruments if spec.per_session]
    items = [
        {"key": item.key, "label": item.text, "reverse_keyed": item.reverse}
        for spec in per_session
        for item in spec.items
        if item.is_measure
    ]
    names = {spec.name for spec in per_session}
    scales = [
        {"key": scale.name, "label": scale.label or scale.name, "reverse_keyed": False}
        for scale in dataset.scales
        if scale.instrument in names
    ]
    return items + scales


def registered_plan(
    dataset: StudyDataset, *, ss_type: int = 3, confidence: float = 0.95
) -> dict[str, Any]:
    """The plan to register for ``dataset``'s study (its protocol's measures, with or without
    data), with the analysis settings the report uses by default."""
    return analysis_plan(
        protocol_sha256=str(dataset.manifest.get("protocol_sha256", "")),
        measures=planned_measures(dataset),
        ss_type=ss_type,
        confidence=confidence,
        excluded_statuses=sorted(dataset.excluded_statuses),
        analyses=analysis_specification(dataset.protocol),
        quality=dataset.protocol.get("quality"),
    )


def data_at_registration(dataset: StudyDataset) -> dict[str, int]:
    """How much data the study had when it was registered: ``participants_enrolled`` (every
    participant stored, whatever their status) and ``participants_answered`` (those with any
    questionnaire answer or any answer to the robot). Both 0 for a registration made before
    data collection, as a pre-registration should be."""
    answered = set(dataset.responses["participant"].dropna()) | set(
        dataset.steps["participant"].dropna()
    )
    return {
        "participants_enrolled": len(dataset.participants),
        "participants_answered": len(answered),
    }


def data_sentence(registration: Mapping[str, Any]) -> str:
    """When the registration was made, against the data: "Registered on DATE, before any
    participant was enrolled." or "…, after 12 participants had been enrolled and 9 had
    answered (data collection had begun)."; a registration that did not record it says so."""
    when = str(registration.get("created_at") or "an unknown date")
    data = registration.get("data_at_registration")
    if not isinstance(data, Mapping):
        return f"Registered on {when}; the registration does not record how much data there was."
    enrolled = int(data.get("participants_enrolled", 0))
    answered = int(data.get("participants_answered", 0))
    if enrolled == 0:
        return f"Registered on {when}, before any participant was enrolled."
    people = "participant" if enrolled == 1 else "participants"
    return (
        f"Registered on {when}, after {enrolled} {people} had been enrolled and {answered} "
        "had answered"
        + (" (data collection had begun)." if answered else " (no one had answered yet).")
    )


def plan_of(result: StudyAnalysis) -> dict[str, Any]:
    """The plan the analysis ``result`` carried out (to compare with a registered one)."""
    return analysis_plan(
        protocol_sha256=str(result.dataset.manifest.get("protocol_sha256", "")),
        measures=[
            {"key": o.key, "label": o.label, "reverse_keyed": o.reverse_keyed}
            for o in result.outcomes
        ],
        ss_type=result.ss_type,
        confidence=result.confidence,
        excluded_statuses=sorted(result.dataset.excluded_statuses),
        analyses=analysis_specification(result.dataset.protocol),
        quality=result.dataset.protocol.get("quality"),
    )


def build_registration(
    *,
    study: Mapping[str, Any],
    protocol_source: str,
    plan: Mapping[str, Any],
    hypotheses: Sequence[str],
    power: Mapping[str, Any] | None,
    software: Mapping[str, str],
    seeds: Mapping[str, Any],
    created_at: str,
    data: Mapping[str, int],
) -> dict[str, Any]:
    """The whole registration (``prereg.json``), JSON-ready; ``data`` is
    :func:`data_at_registration` of the study when it was registered."""
    return {
        "format": FORMAT,
        "created_at": created_at,
        "data_at_registration": dict(data),
        "study": dict(study),
        "protocol": {"sha256": plan["protocol_sha256"], "source": protocol_source},
        "hypotheses": list(hypotheses),
        "analysis_plan": dict(plan),
        "power_analysis": dict(power) if power is not None else None,
        "software": dict(software),
        "seeds": dict(seeds),
    }


@dataclass(frozen=True)
class RegistrationCheck:
    """How an analysis compares with its registration.

    Attributes
    ----------
    deviations : list of str
        One sentence per difference; empty when the analysis is as registered.
    registered_at : str
    source : str
        Where the registration came from (a file and its SHA-256, or the audit log).
    """

    deviations: list[str]
    registered_at: str
    source: str

    @property
    def as_registered(self) -> bool:
        return not self.deviations


def check_registration(
    registration: Mapping[str, Any],
    result: StudyAnalysis,
    *,
    mixed: StudyMixedModels | None = None,
    source: str = "",
) -> RegistrationCheck:
    """Compare the registered plan with the one ``result`` carried out: protocol hash,
    measures, models (formulas and covariates), α, sums of squares, confidence level and
    exclusion rules; then what was fitted: ``mixed`` are the mixed models of the report (None:
    the report has none, so the registered mixed models were not fitted), and a covariate a
    measure's models had to leave out is a deviation of that measure."""
    registered = registration.get("analysis_plan") or {}
    actual = plan_of(result)
    deviations = []
    if registered.get("protocol_sha256") != actual["protocol_sha256"]:
        deviations.append(
            f"protocol: registered SHA-256 {str(registered.get('protocol_sha256'))[:12]}…, "
            f"the study's is {actual['protocol_sha256'][:12]}… (the protocol changed)"
        )
    keys = [m["key"] for m in registered.get("measures", [])]
    ran = [m["key"] for m in actual["measures"]]
    missing = [k for k in keys if k not in ran]
    added = [k for k in ran if k not in keys]
    if missing:
        deviations.append(f"measures registered but not analysed: {', '.join(missing)}")
    if added:
        deviations.append(f"measures analysed but not registered: {', '.join(added)}")
    if registered.get("primary_measure") != actual["primary_measure"]:
        deviations.append(
            f"primary measure: registered {registered.get('primary_measure')}, "
            f"reported first {actual['primary_measure']}"
        )
    specification = analysis_specification(result.dataset.protocol)
    if isinstance(registered.get("analyses"), list):
        deviations += _model_deviations(registered["analyses"], specification)
    else:  # a registration written before the plan named formulas: its model sentences
        for model in registered.get("models", []):
            if model not in actual["models"]:
                deviations.append(f"model registered but not fitted: {model}")
        for model in actual["models"]:
            if model not in registered.get("models", []):
                deviations.append(f"model fitted but not registered: {model}")
    deviations += _fitted_deviations(specification, mixed)
    for name, what in (
        ("alpha", "α"),
        ("ss_type", "type of sums of squares"),
        ("confidence", "confidence level"),
    ):
        if registered.get(name) != actual[name]:
            deviations.append(f"{what}: registered {registered.get(name)}, used {actual[name]}")
    if registered.get("exclusions") != actual["exclusions"]:
        deviations.append(
            "exclusion rules: registered "
            + json.dumps(registered.get("exclusions"), ensure_ascii=False)
            + ", applied "
            + json.dumps(actual["exclusions"], ensure_ascii=False)
        )
    return RegistrationCheck(deviations, str(registration.get("created_at", "")), source)


def _model_deviations(
    registered: Sequence[Mapping[str, Any]], specification: Sequence[PlannedAnalysis]
) -> list[str]:
    """Each registered analysis against the specification's of the same name: formulas and
    covariates."""
    planned = {analysis.name: analysis for analysis in specification}
    named = {str(entry.get("name")): entry for entry in registered}
    deviations = []
    for name, entry in named.items():
        if name not in planned:
            deviations.append(f"model registered but not fitted: {name}")
            continue
        analysis = planned[name]
        if list(entry.get("formulas", [])) != list(analysis.formulas):
            deviations.append(
                f"{analysis.title}: registered {'; '.join(entry.get('formulas', []))}, "
                f"fitted {'; '.join(analysis.formulas)}"
            )
        if list(entry.get("covariates", [])) != list(analysis.covariates):
            deviations.append(
                f"{analysis.title}: registered covariates "
                f"{', '.join(entry.get('covariates', [])) or 'none'}, fitted "
                f"{', '.join(analysis.covariates) or 'none'}"
            )
    for name, analysis in planned.items():
        if name not in named:
            deviations.append(f"model fitted but not registered: {analysis.description}")
    return deviations


def _fitted_deviations(
    specification: Sequence[PlannedAnalysis], mixed: StudyMixedModels | None
) -> list[str]:
    """What the report did not fit of the specification: its mixed models when it has none,
    the random-slope model when it was not asked for, a covariate a measure left out."""
    in_mixed = [a for a in specification if a.result.startswith("OutcomeMixedModels.")]
    if mixed is None:
        return [f"{a.title}: registered, not fitted in this report" for a in in_mixed]
    deviations = []
    if not mixed.random_slope:
        deviations.append("linear mixed models: the random-slope model was not fitted")
    for outcome in mixed.outcomes:
        for covariate, why in outcome.covariates_left_out.items():
            deviations.append(
                f"{outcome.key}: the linear mixed models left out the registered covariate "
                f"{covariate} ({why})"
            )
    return deviations


# ------------------------------------------------------------------------------ rendering


def _power_lines(power: Mapping[str, Any] | None) -> list[str]:
    if not power:
        return ["No power analysis was registered."]
    design = power.get("design", {})
    lines = [
        f"Question: {power.get('question')}; effect: {design.get('effect')} "
        f"({design.get('groups')} groups × {design.get('sessions')} sessions), "
        f"convention {design.get('convention')}.",
        f"Inputs: f = {_num(power.get('f'))} (partial η² = {_num(power.get('eta2'))}), "
        f"ρ = {_num(design.get('rho'))}, ε = {_num(design.get('epsilon'))}, "
        f"α = {design.get('alpha')}"
        + (
            f", target power {power.get('target_power')}"
            if power.get("target_power") is not None
            else ""
        )
        + ".",
        f"Answer: N = {power.get('n_total')} in total, power {_num(power.get('power'))} "
        f"(λ = {_num(power.get('lambda'))}, df = {_num(power.get('df1'))}, "
        f"{_num(power.get('df2'))}, critical F = {_num(power.get('f_critical'))}).",
    ]
    if power.get("pilot"):
        pilot = power["pilot"]
        lines.append(
            f"Inputs estimated from the pilot {pilot.get('source')!r} ({pilot.get('dv')}, "
            f"n per group {pilot.get('n_per_group')}; bootstrap "
            f"{pilot.get('bootstrap', {}).get('replicates')} resamples, seed "
            f"{pilot.get('bootstrap', {}).get('seed')})."
        )
    if power.get("simulation"):
        sim = power["simulation"]
        fitted = SIMULATED_MODEL_NAMES.get(sim.get("kind", "lmm"), "mixed model")
        lines.append(
            f"Simulated power of the {fitted} at N = {sim.get('n_total')}: "
            f"{_num(sim.get('power'))} [{_num(sim.get('ci_low'))}, {_num(sim.get('ci_high'))}] "
            f"({sim.get('replicates')} datasets, seed {sim.get('seed')})."
        )
    return lines


def _num(value: Any) -> str:
    if value is None:
        return "—"
    return f"{value:.4g}" if isinstance(value, int | float) else str(value)


def _sections(registration: Mapping[str, Any]) -> list[tuple[str, list[str], str | None]]:
    """(heading, paragraphs or items, preformatted text) of each part, for both renderings."""
    plan = registration["analysis_plan"]
    study = registration["study"]
    measures = [
        f"{m['key']}: {m['label']}"
        + (" (reverse-keyed)" if m["reverse_keyed"] else "")
        + (" — primary" if m["key"] == plan["primary_measure"] else "")
        for m in plan["measures"]
    ]
    return [
        (
            "Study",
            [
                f"{study.get('title')} (trustlab study {study.get('name')!r}).",
                data_sentence(registration),
                f"Protocol SHA-256: {registration['protocol']['sha256']} (the protocol as "
                "trustlab stores and runs it, in full below).",
            ],
            None,
        ),
        ("Hypotheses", list(registration["hypotheses"]), None),
        ("Measures", measures, None),
        (
            "Planned analyses",
            [
                *plan["models"],
                f"α = {plan['alpha']}; type {plan['ss_type']} sums of squares; "
                f"{plan['confidence']:.0%} confidence intervals.",
            ],
            None,
        ),
        ("Exclusion rules", list(plan["exclusions"]["rules"]), None),
        ("Sample size and power", _power_lines(registration.get("power_analysis")), None),
        (
            "Software and seeds",
            [f"{name} {version}" for name, version in registration["software"].items()]
            + [f"seed {name}: {value}" for name, value in registration["seeds"].items()],
            None,
        ),
        ("Protocol", [], registration["protocol"]["source"]),
    ]


def registration_markdown(registration: Mapping[str, Any]) -> str:
    """The registration as Markdown (to paste into an OSF form)."""
    title = registration["study"].get("title")
    parts = [f"# Pre-registration: {title}", ""]
    for heading, items, pre in _sections(registration):
        parts += [f"## {heading}", ""]
        parts += [f"- {item}" for item in items]
        if pre is not None:
            parts += ["```toml", pre.rstrip("\n"), "```"]
        parts.append("")
    return "\n".join(parts)


def registration_html(registration: Mapping[str, Any]) -> str:
    """The registration as one self-contained HTML page."""
    title = html.escape(f"Pre-registration: {registration['study'].get('title')}")
    body = [f"<h1>{title}</h1>"]
    for heading, items, pre in _sections(registration):
        body.append(f"<h2>{html.escape(heading)}</h2>")
        if items:
            body.append("<ul>" + "".join(f"<li>{html.escape(i)}</li>" for i in items) + "</ul>")
        if pre is not None:
            body.append(f"<pre>{html.escape(pre)}</pre>")
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{title}</title>\n<style>body{{font-family:system-ui,sans-serif;max-width:"
        "900px;margin:0 auto;padding:1.5rem;line-height:1.45}pre{background:#f6f6f6;"
        "padding:.8rem;overflow-x:auto;font-size:.82rem}</style>\n</head>\n<body>\n"
        + "\n".join(body)
        + "\n</body>\n</html>\n"
    )
