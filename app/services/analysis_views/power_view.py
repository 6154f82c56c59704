"""The analysis page's "Plan the next study": the form, its answer and the power curve.

The page asks the questions ``trustlab power`` answers (the power at N, the N for a target power,
the smallest detectable effect), with :mod:`analysis.power`'s formulas, so the page and the
command line give the same numbers; it shows the command that gives them again. The form starts
from the study's own data where it has enough complete participants (ρ, ε and each effect's f as
``trustlab power --pilot`` estimates them, without the bootstrap, which the command line adds),
and says so; otherwise from the seed paper's design and a medium effect, and says why.

The form's values arrive as text and are read here, so that every bad value is refused in one
line naming the field, the same words whether the page is loaded whole or its answer by htmx.

Where the values come from. A prefilled form carries the study's estimates in a hidden field
(``study``), so each answer says which values are still the study's, and recomputes those
derived from what the person changed (:func:`reconciled`), once, in the form it gives back:

- the effect size: the study's f is an effect's (between, within, interaction) and is typed as
  f or as η²; switching the effect or the kind of size gives the study's value for the new one;
- ε: the study's was estimated for its m sessions, so another number of sessions starts from 1;
  and a partial η² of one's own read "as in SPSS" carries the df of the test it came from
  (λ = F · df1 for a published one, the PI guide's example), so it starts from ε = 1 too: the
  answer is then the documented one, not one silently corrected by this study's sphericity;
- ρ is a property of the ratings, kept (and shown as not used by the SPSS convention).

A value recomputed leaves the ``study`` field, so typing it back applies it as one's own.
"""

from __future__ import annotations

import math
import re
import shlex
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

from analysis.apa import format_number
from analysis.errors import AnalysisError, InvalidInputError
from analysis.power import (
    EFFECTS,
    PowerAnswer,
    PowerDesign,
    detectable_effect,
    eta2_from_f,
    f_from_eta2,
    n_for_power,
    power_for_n,
)
from analysis.power_figures import power_curve_payload
from analysis.power_pilot import estimate_pilot
from analysis.study import StudyAnalysis
from app.services.analysis_views.dashboard import json_safe

__all__ = ["PlanAnswer", "PlanForm", "PlanView", "answer_plan", "plan_view", "prefilled"]

QUESTIONS = {
    "n": "the N for a target power",
    "power": "the power at N",
    "effect": "the smallest effect detectable at N",
}
"""The form's questions, by their value."""

MAX_LEVELS = 50
"""More groups or sessions than this is a typing slip, not a design."""

_WHOLE = re.compile(r"[0-9]{1,9}")


@dataclass(frozen=True)
class PlanForm:
    """The form's fields as typed (text): what the page shows back, and what is read."""

    effect: str = "interaction"
    groups: str = "2"
    sessions: str = "4"
    size: str = "f"
    value: str = "0.25"
    convention: str = "gpower"
    rho: str = "0.5"
    epsilon: str = "1"
    alpha: str = "0.05"
    question: str = "n"
    n: str = "24"
    target: str = "0.8"
    study: str = ""
    """The study's estimates the form was prefilled with, still unchanged (``rho=0.41;…``):
    hidden, carried with the form so that an answer knows which values are the study's."""

    @classmethod
    def from_query(cls, query: Mapping[str, str]) -> PlanForm | None:
        """The form a request carries, or None when it carries none of its fields (the page
        was opened, not submitted). A field left out keeps its default."""
        names = [f.name for f in fields(cls)]
        given = {name: query[name].strip() for name in names if name in query}
        return cls(**given) if given else None


@dataclass(frozen=True)
class PlanAnswer:
    """One answer, ready to show."""

    headline: str
    rows: list[tuple[str, str]]
    figure: dict[str, Any]
    command: str
    result: dict[str, Any]


@dataclass(frozen=True)
class PlanView:
    """The section: the form (as typed, with the study's values the change made stale
    recomputed), what it was prefilled from, the answer or the refusal."""

    form: PlanForm
    basis: str
    answer: PlanAnswer | None
    error: str
    questions: Mapping[str, str]
    effects: tuple[str, ...] = EFFECTS
    from_study: frozenset[str] = frozenset()
    """The fields still holding the study's value."""
    recomputed: tuple[str, ...] = ()
    """One sentence per value recomputed from what the person changed."""

    @property
    def provenance(self) -> str:
        """Which of the answer's values are the study's, in one sentence ('' when none is)."""
        if not self.from_study:
            return ""
        labels = FROM_STUDY_LABELS.items()
        named = [label for name, label in labels if name in self.from_study]
        yours = [label for name, label in labels if name not in self.from_study]
        return f"From this study's data: {', '.join(named)}" + (
            f"; yours (or the defaults): {', '.join(yours)}." if yours else "."
        )


FROM_STUDY_LABELS = {
    "groups": "groups",
    "sessions": "sessions",
    "value": "the effect size",
    "rho": "ρ",
    "epsilon": "ε",
    "n": "N",
}
"""The fields a study prefills, as the answer names them."""


def plan_view(form: PlanForm, basis: str = "") -> PlanView:
    """The form answered, or refused in one line (``error``)."""
    form, from_study, recomputed = reconciled(form)
    try:
        answer, error = answer_plan(form), ""
    except AnalysisError as refused:
        answer, error = None, str(refused)
    return PlanView(
        form, basis, answer, error, QUESTIONS, from_study=from_study, recomputed=recomputed
    )


def _study_values(text: str) -> dict[str, str]:
    values = {}
    for pair in text.split(";"):
        key, _, value = pair.partition("=")
        if key.strip() and value.strip():
            values[key.strip()] = value.strip()
    return values


def _same(typed: str, value: str) -> bool:
    """Whether the form's text is the study's value (as numbers: '.5' is '0.5')."""
    try:
        return math.isclose(float(typed.replace("−", "-")), float(value), abs_tol=5e-4)
    except ValueError:
        return False


def _study_size(study: Mapping[str, str], effect: str, size: str) -> str | None:
    """The study's effect size for ``effect``, typed as ``size`` (f or η²), G*Power's."""
    f = study.get(f"f_{effect}")
    if f is None:
        return None
    return f if size == "f" else _typed(eta2_from_f(float(f)))


def reconciled(form: PlanForm) -> tuple[PlanForm, frozenset[str], tuple[str, ...]]:
    """``form`` with the study's values the change made stale recomputed (the module's notes),
    the fields still holding the study's value, and a sentence per value recomputed."""
    study = _study_values(form.study)
    if not study:
        return form, frozenset(), ()
    changes: dict[str, str] = {}
    notes: list[str] = []
    kept = dict(study)
    sizes = {
        _study_size(study, effect, size)
        for effect in EFFECTS
        for size in ("f", "eta2")
        if study.get(f"f_{effect}")
    }
    own_size = not any(s is not None and _same(form.value, s) for s in sizes)
    wanted = _study_size(study, form.effect, form.size)
    if own_size:
        for effect in EFFECTS:
            kept.pop(f"f_{effect}", None)
    elif wanted is not None and not _same(form.value, wanted):
        changes["value"] = wanted
        name = "f" if form.size == "f" else "partial η²"
        notes.append(
            f"{name} = {wanted}: this study's for the {form.effect} effect, recomputed for the "
            "effect and size you chose."
        )
    if "epsilon" in study and _same(form.epsilon, study["epsilon"]):
        why = ""
        if study.get("sessions") and form.sessions != study["sessions"]:
            why = (
                f"this study's ε = {study['epsilon']} was estimated over its "
                f"{study['sessions']} sessions, not {form.sessions[:12]}"
            )
        elif own_size and form.convention == "spss":
            why = (
                f"a partial η² of your own, read as in SPSS, comes with the df of its own test, "
                f"so this study's ε = {study['epsilon']} is not applied to it (type it again to "
                "apply it)"
            )
        if why:
            changes["epsilon"] = "1"
            kept.pop("epsilon")
            notes.append(f"ε = 1: {why}.")
    if changes:
        form = replace(form, **changes)
    form = replace(form, study=";".join(f"{key}={value}" for key, value in kept.items()))
    from_study: set[str] = {
        name
        for name in ("groups", "sessions", "rho", "epsilon", "n")
        if name in kept and _same(getattr(form, name), kept[name])
    }
    if not own_size and _same(form.value, wanted or "nan") and form.convention == "gpower":
        from_study.add("value")
    return form, frozenset(from_study), tuple(notes)


def prefilled(result: StudyAnalysis | None, problem: str = "") -> tuple[PlanForm, str]:
    """The form from the study's first per-session measure (the trust item the paper tests),
    and a sentence saying where its values come from.

    ``problem`` is why there is no analysis (``result`` None), for that sentence."""
    defaults = PlanForm()
    fallback = (
        "The fields hold the seed paper's design (2 groups × 4 sessions) with a medium "
        "interaction (f = 0.25) and ρ = .5: change them to what you expect."
    )
    if result is None or not result.outcomes:
        why = problem or "no participant has rated the robot after a session yet"
        return defaults, f"Not prefilled from this study: {why.rstrip('.')}. {fallback}"
    outcome = result.outcomes[0]
    try:
        estimate = estimate_pilot(
            outcome.data,
            dv="value",
            within="session",
            between="condition",
            subject="participant",
            replicates=0,
        )
    except AnalysisError as error:
        return defaults, f"Not prefilled from this study: {str(error).rstrip('.')}. {fallback}"
    values = estimate.estimates
    m = estimate.sessions
    epsilon = max(values["epsilon"], 1 / (m - 1)) if math.isfinite(values["epsilon"]) else 1.0
    rho = values["rho"]
    if not (math.isfinite(rho) and math.isfinite(values["f_interaction"])):
        return defaults, (
            f"Not prefilled from this study: {outcome.key}'s ratings do not vary within its "
            f"conditions. {fallback}"
        )
    n = sum(estimate.group_sizes)
    typed = {
        "groups": str(estimate.groups),
        "sessions": str(m),
        "rho": _typed(min(max(rho, -0.99), 0.99)),
        "epsilon": _typed(math.floor(epsilon * 1000) / 1000 if epsilon < 1 else 1.0),
        "n": str(n),
    }
    effect_sizes = {
        f"f_{effect}": _typed(values[f"f_{effect}"])
        for effect in EFFECTS
        if math.isfinite(values[f"f_{effect}"])
    }
    form = replace(
        defaults,
        value=effect_sizes.get("f_interaction", defaults.value),
        study=";".join(f"{key}={value}" for key, value in {**typed, **effect_sizes}.items()),
        **typed,
    )
    sizes = ", ".join(
        f"{level} {size}"
        for level, size in zip(estimate.group_levels, estimate.group_sizes, strict=True)
    )
    basis = (
        f"Prefilled from this study's own data: {n} complete participants ({sizes}) over {m} "
        f"sessions on {outcome.key} (“{outcome.label.rstrip('.')}”): ρ = {format_number(rho, 3)}, "
        f"ε = {format_number(values['epsilon'], 3)}, f = "
        f"{format_number(values['f_between'], 3)} (between), "
        f"{format_number(values['f_within'], 3)} (within), "
        f"{format_number(values['f_interaction'], 3)} (interaction, in the form). Point "
        f"estimates: on the command line, trustlab power --pilot adds their bootstrap "
        f"intervals and the answer at both ends of f's."
    )
    return form, basis


def _typed(value: float) -> str:
    """A number as a person would type it into the form (three decimals, no trailing zeros)."""
    return f"{value:.3f}".rstrip("0").rstrip(".") or "0"


def _number(text: str, name: str, *, optional: bool = False) -> float | None:
    if not text:
        if optional:
            return None
        raise InvalidInputError(f"{name}: a number is needed")
    try:
        value = float(text.replace("−", "-"))
    except ValueError:
        raise InvalidInputError(f"{name}: {text[:40]!r} is not a number") from None
    if not math.isfinite(value):
        raise InvalidInputError(f"{name}: {text[:40]!r} is not a finite number")
    return value


def _whole(text: str, name: str, high: int) -> int:
    if not _WHOLE.fullmatch(text) or not 1 <= int(text) <= high:
        raise InvalidInputError(
            f"{name}: a whole number from 1 to {high:,} is needed, got {text[:40]!r}"
        )
    return int(text)


def _choice(text: str, name: str, allowed: tuple[str, ...]) -> str:
    if text not in allowed:
        raise InvalidInputError(f"{name}: one of {', '.join(allowed)}, got {text[:40]!r}")
    return text


def answer_plan(form: PlanForm) -> PlanAnswer:
    """The question the form asks, answered (:class:`InvalidInputError` in one line)."""
    effect = _choice(form.effect, "effect", EFFECTS)
    question = _choice(form.question, "question", tuple(QUESTIONS))
    size_kind = _choice(form.size, "effect size", ("f", "eta2"))
    convention = _choice(form.convention, "convention", ("gpower", "spss"))
    rho = _number(form.rho, "rho", optional=convention == "spss")
    epsilon = _number(form.epsilon, "epsilon", optional=True)
    alpha = _number(form.alpha, "alpha")
    assert alpha is not None
    design = PowerDesign(
        effect,  # type: ignore[arg-type]
        _whole(form.groups, "groups", MAX_LEVELS),
        _whole(form.sessions, "sessions", MAX_LEVELS),
        rho,
        epsilon=1.0 if epsilon is None else epsilon,
        alpha=alpha,
        convention=convention,  # type: ignore[arg-type]
    )
    if question == "effect":
        target = _number(form.target, "target power")
        answer = detectable_effect(
            design, n_total=_whole(form.n, "N", 10_000_000), target=target or 0.0
        )
    else:
        value = _number(form.value, "f" if size_kind == "f" else "eta²")
        assert value is not None
        f = f_from_eta2(value) if size_kind == "eta2" else value
        if question == "power":
            answer = power_for_n(design, f=f, n_total=_whole(form.n, "N", 10_000_000))
        else:
            target = _number(form.target, "target power")
            answer = n_for_power(design, f=f, target=target or 0.0)
    return PlanAnswer(
        headline=_headline(answer),
        rows=_rows(answer),
        figure=json_safe(
            power_curve_payload(
                design, answer.f, n_total=answer.n_total, target=answer.target_power
            )
        ),
        command=_command(answer, form),
        result=answer.to_dict(),
    )


_WHAT = {
    "between": "the between-groups effect",
    "within": "the within (session) effect",
    "interaction": "the group × session interaction",
}


def _headline(answer: PowerAnswer) -> str:
    what = _WHAT[answer.design.effect]
    power = format_number(answer.power, 3)
    if answer.question == "power":
        return f"Power {power} to detect {what} with N = {answer.n_total}."
    if answer.question == "sample size":
        per_group = answer.n_total // answer.design.groups
        return (
            f"N = {answer.n_total} ({per_group} per group) reaches power {power} "
            f"(target {answer.target_power:g}) for {what}."
        )
    return (
        f"With N = {answer.n_total}, the smallest {what.removeprefix('the ')} detected with "
        f"power {answer.target_power:g} is f = {format_number(answer.f, 3)} "
        f"(partial η² = {format_number(answer.eta2, 3)}, {answer.design.convention} convention)."
    )


def _rows(answer: PowerAnswer) -> list[tuple[str, str]]:
    design = answer.design
    used = design.to_dict()
    return [
        ("power", format_number(answer.power, 4)),
        ("N in total", f"{answer.n_total} ({answer.n_total / design.groups:g} per group)"),
        (
            "effect size",
            f"f = {format_number(answer.f, 4)}, η² = {format_number(answer.eta2, 4)} "
            f"({design.convention} convention)",
        ),
        ("noncentrality λ", format_number(answer.lam, 4)),
        ("df", f"{format_number(answer.df1, 3)}, {format_number(answer.df2, 3)}"),
        ("critical F", format_number(answer.f_critical, 4)),
        (
            "ρ",
            ("—" if design.rho is None else format_number(design.rho, 3))
            + ("" if used["rho_used"] else " (not used by this convention)"),
        ),
        (
            "ε",
            format_number(design.epsilon, 3)
            + ("" if design.uses_epsilon else " (not used by the between effect)"),
        ),
        ("α", f"{design.alpha:g}"),
    ]


def _command(answer: PowerAnswer, form: PlanForm) -> str:
    """The ``trustlab power`` command that gives this answer again."""
    design = answer.design
    words = [
        "trustlab",
        "power",
        "--effect",
        design.effect,
        "--groups",
        str(design.groups),
        "--sessions",
        str(design.sessions),
    ]
    if answer.question != "detectable effect":
        words += ["--eta2" if form.size == "eta2" else "--f", form.value]
    if design.convention != "gpower":
        words += ["--convention", design.convention]
    if design.rho is not None:
        words += ["--rho", f"{design.rho:g}"]
    if design.uses_epsilon and design.epsilon != 1:
        words += ["--epsilon", form.epsilon]
    if design.alpha != 0.05:
        words += ["--alpha", f"{design.alpha:g}"]
    if answer.question != "sample size":
        words += ["--n", str(answer.n_total)]
    if answer.target_power is not None:
        words += ["--target-power", f"{answer.target_power:g}"]
    return shlex.join(words)
