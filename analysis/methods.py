"""The methods section of the report, written from the protocol, sample and analysis settings.

A reviewer should be able to read what was done without opening the protocol file, and the
text must never drift from the numbers: everything here is generated from the same objects the
statistics use.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from analysis.dataset import ProtocolSummary
from analysis.instruments import InstrumentSpec
from analysis.prose import count, gender_word, value_range

__all__ = [
    "analysis_paragraph",
    "design_paragraph",
    "exclusion_sentence",
    "languages_paragraph",
    "participants_paragraph",
    "population_sentence",
    "translation_references",
]

_NUMBER_WORDS = {
    1: "one",
    2: "two",
    3: "three",
    4: "four",
    5: "five",
    6: "six",
    7: "seven",
    8: "eight",
    9: "nine",
}


def _count(n: int) -> str:
    return _NUMBER_WORDS.get(n, str(n))


_IRREGULAR = {"category": "categories"}


def _plural(n: int, word: str) -> str:
    return f"{_count(n)} " + (word if n == 1 else _IRREGULAR.get(word, word + "s"))


def _join(parts: Sequence[str]) -> str:
    if len(parts) <= 1:
        return "".join(parts)
    return ", ".join(parts[:-1]) + " and " + parts[-1]


def participants_paragraph(protocol: ProtocolSummary, sample: Mapping[str, Any]) -> str:
    """Sample size per condition, gender and age, e.g. "N = 24 participants (12 in C1 …)"."""
    labels = {c["code"]: c["label"] for c in protocol["conditions"]}
    by_condition = sample.get("by_condition", {})
    groups = [f"{code}, {labels[code]}: {by_condition.get(code, 0)}" for code in labels]
    n = sample.get("n", 0)
    verb = "was" if n == 1 else "were"
    text = f"N = {count(n, 'participant')} {verb} analysed ({'; '.join(groups)})"
    gender = sample.get("gender")
    if gender:
        text += "; " + ", ".join(f"{n} {gender_word(label)}" for label, n in gender.items())
    age = sample.get("age")
    if age:
        sd = age["sd"]
        sd_text = f", SD = {sd:.2f}" if isinstance(sd, float) and math.isfinite(sd) else ""
        text += (
            f"; aged {value_range(age['min'], age['max'], 'years')} (M = {age['mean']:.2f}{sd_text}"
            + (f", n = {age['n']}" if age["n"] != sample.get("n") else "")
            + ")"
        )
    return text + "."


def exclusion_sentence(exclusions: Sequence[Mapping[str, Any]], *, everywhere: str = "all") -> str:
    """What the exclusion list holds, in one sentence for the methods: how many enrolled
    participants were left out of every analysis and why, how many of the analysed were left
    out of an ANOVA as incomplete. Written from the list the report prints
    (:meth:`analysis.study.StudyAnalysis.exclusions`, rows with ``participant``, ``analysis``
    and ``reason``; ``everywhere`` is the ``analysis`` of an exclusion from every analysis), so
    the methods, the list, the ANOVAs' notes and N analysed say the same."""
    if not exclusions:
        return "No participant was excluded."
    reasons: dict[str, set[Any]] = {}
    incomplete: set[Any] = set()
    for row in exclusions:
        if row["analysis"] == everywhere:
            reasons.setdefault(str(row["reason"]), set()).add(row["participant"])
        else:
            incomplete.add(row["participant"])
    parts = []
    if reasons:
        n = len(set().union(*reasons.values()))
        why = "; ".join(f"{reason}: {len(who)}" for reason, who in reasons.items())
        parts.append(
            f"{count(n, 'enrolled participant')} {'was' if n == 1 else 'were'} excluded from "
            f"every analysis ({why})"
        )
    if incomplete:
        n = len(incomplete)
        parts.append(
            f"{count(n, 'analysed participant')} {'was' if n == 1 else 'were'} excluded from "
            "the ANOVA of one or more measures for incomplete data (the mixed models use every "
            "rating they gave)"
        )
    text = _join(parts)
    return text[0].upper() + text[1:] + "; each is listed with the reason below."


NO_SOURCE = "the protocol does not say where it comes from"


def languages_paragraph(protocol: ProtocolSummary) -> str:
    """Which languages the study ran in and where each translation comes from ('' for a study
    in one language): a questionnaire answered in a translation is that translation's
    instrument, so a reader must know which was used."""
    languages = protocol.get("languages", [])
    if len(languages) < 2:
        return ""
    translations = protocol.get("translations", {})
    sources = [
        f"{code}: {(translations.get(code) or {}).get('source') or NO_SOURCE}"
        for code in languages[1:]
    ]
    return (
        f"Each participant took part in one of {_count(len(languages))} languages: "
        f"{_join(languages)} (ISO 639 codes; {languages[0]} is the protocol's own). Every text "
        "a participant read or heard (consent, rules, questions, replies, questionnaires) was "
        "given in their language, from the protocol's translations. Translations: "
        + "; ".join(sources)
        + ". The codebook lists each item's wording per language (label_<code>)."
    )


def translation_references(protocol: ProtocolSummary) -> list[str]:
    """The translated instruments' citations, as the protocol's translations name them."""
    found = []
    for code, translation in protocol.get("translations", {}).items():
        for instrument in translation.get("instruments", {}).values():
            if instrument.get("citation"):
                found.append(f"{instrument['citation']} [{code}]")
    return found


def design_paragraph(protocol: ProtocolSummary, instruments: Sequence[InstrumentSpec]) -> str:
    """Conditions, allocation, the adaptation schedule and the questionnaires."""
    conditions = protocol["conditions"]
    sentences = []
    allocation = protocol.get("allocation")
    names = _join([f"{c['code']} ({c['label']})" for c in conditions])
    sentences.append(
        f"Participants were allocated to {_plural(len(conditions), 'condition')}, {names}"
        + (f", by {allocation}" if allocation else "")
        + "."
    )
    described = [f"in {c['code']}, {c['description']}" for c in conditions if c.get("description")]
    if described:
        text = "; ".join(described)
        sentences.append(text[0].upper() + text[1:] + ".")
    categories = protocol["categories"]
    arms = sorted({len(q) for q in categories.values()})
    arms_text = " or ".join(str(a) for a in arms)
    sessions, runs = protocol["sessions"], protocol["runs_per_session"]
    familiarisation = protocol.get("familiarisation_runs", 1)
    schedule = (
        f"After {_plural(familiarisation, 'familiarisation run')} not used for adaptation, "
        if familiarisation
        else ""
    )
    sentences.append(
        f"{schedule}each participant completed {_plural(sessions, 'session')} of "
        f"{_plural(runs, 'run')}; in every run the robot asked one of {arms_text} questions in "
        f"each of {_plural(len(categories), 'category')} ({_join(list(categories))}), chosen "
        f"by a separate learner per category, giving {sessions * runs} adaptation iterations "
        "per category."
    )
    if protocol.get("feedback"):
        sentences.append(f"Answers were turned into rewards as follows: {protocol['feedback']}.")
    if protocol.get("population"):
        sentences.append(population_sentence(protocol["population"]))
    per_session = [i for i in instruments if i.per_session]
    once = [i for i in instruments if not i.per_session and not i.after_study]
    after = [i for i in instruments if i.after_study]
    for spec in per_session:
        first = spec.items[0]
        scale = (
            f"{first.maximum - first.minimum + 1:g}-point"
            if first.minimum is not None and first.maximum is not None
            else ""
        )
        reverse = [item.key for item in spec.items if item.reverse]
        sentences.append(
            f"After each session participants completed the questionnaire “{spec.label}” "
            f"({_plural(len(spec.items), 'item')}, {scale} scale"
            + (f"; reverse-keyed: {', '.join(reverse)}" if reverse else "")
            + ")."
        )
    if once:
        sentences.append(
            "Before the study they completed: " + "; ".join(spec.label for spec in once) + "."
        )
    if after:
        sentences.append(
            "After the last session they completed: "
            + "; ".join(spec.label for spec in after)
            + "."
        )
    return " ".join(sentences)


def _share(value: float) -> str:
    """A probability as APA writes it: no leading zero, two decimals."""
    return f"{value:.2f}".removeprefix("0")


def population_sentence(population: Mapping[str, Any]) -> str:
    """Where the meta-learned policy's prior came from (issue 20): the source, N, and per
    category the fitted prior with its bootstrap intervals, slip rate and hazard."""
    parts = []
    sizes = set()
    for name, fitted in population["categories"].items():
        if "prior" not in fitted:
            parts.append(f"{name}: not recorded (its checkpoint is missing)")
            continue
        sizes.add(int(fitted["participants"]))
        shares = [
            f"{_share(p)} [{_share(low)}, {_share(high)}]"
            for p, (low, high) in zip(fitted["prior"], fitted["prior_ci"], strict=True)
        ]
        parts.append(
            f"{name}: {', '.join(shares)} for questions 1–{len(shares)}, slip rate "
            f"{_share(fitted['slip'])} [{_share(fitted['slip_ci'][0])}, "
            f"{_share(fitted['slip_ci'][1])}], hazard {_share(fitted['hazard'])}"
        )
    counted = " or ".join(str(n) for n in sorted(sizes))
    plural = "" if sizes == {1} else "s"
    who = f"{counted} earlier participant{plural}" if sizes else "earlier participants"
    text = (
        "The meta-learned policy was meta-trained on the population fitted from "
        f"{who} of {population['source']} (population file SHA-256 {population['sha256'][:12]}): "
        "the prior probability that each question is the preferred one, with 95 % bootstrap "
        f"intervals, {'; '.join(parts)}; the training prior added one pseudo-participant per "
        "question to the fitted shares."
    )
    if population.get("enrolling_reason"):
        text += (
            " The population was fitted while its source study was still enrolling, for this "
            f"recorded reason: {population['enrolling_reason']}."
        )
    return text


def analysis_paragraph(
    protocol: ProtocolSummary, n_conditions: int, ss_type: int, confidence: float
) -> str:
    """How every statistic was computed (type of sums of squares, sphericity, exclusions)."""
    level = f"{confidence:.0%}"
    ss_text = (
        "type III sums of squares (as SPSS, JASP, jamovi and R's afex report by default)"
        if ss_type == 3
        else "type II sums of squares (as pingouin and R's car report by default)"
    )
    return (
        f"Each per-session item and scale was analysed with a {n_conditions} (condition, "
        f"between subjects) × {protocol['sessions']} (session, within subjects) mixed ANOVA "
        f"with {ss_text}; reverse-keyed items were reverse-scored first. Participants without a "
        "value in every session were excluded from that analysis (complete cases), and are "
        "listed below with the reason. Sphericity was tested with Mauchly's test; when it was "
        "violated (p < .05) the Greenhouse–Geisser corrected degrees of freedom and p value are "
        "reported, and both are always given in the tables. Effect sizes are partial η² (ηp²) "
        "and generalised η² (ηG²). Post-hoc tests compare sessions within each condition "
        "(paired t tests) and conditions within each session (independent t tests, Welch's "
        "when group sizes differ), Holm-corrected within each family; Cohen's d uses the pooled "
        f"SD (independent) or the average SD (paired). Error bars and bands are {level} t "
        "confidence intervals. Every p value is computed from its test statistic and degrees "
        "of freedom."
    )
