"""One exclusion list (issue 48, item 17): the methods, the exclusions section, each analysis's
note and N analysed all come from :meth:`analysis.study.StudyAnalysis.exclusions`, and an
enrolled participant without a single rating is excluded from every analysis with that reason
instead of being counted as analysed."""

from __future__ import annotations

import dataclasses
import html
import re

import pandas as pd
import pytest

from analysis.dataset import StudyDataset
from analysis.errors import InvalidInputError
from analysis.prereg import (
    build_registration,
    check_registration,
    registered_plan,
    registration_markdown,
)
from analysis.report import build_report
from analysis.study import ALL_ANALYSES, NO_DATA_REASON, StudyAnalysis, analyse_study
from analysis.synthetic import synthetic_study

COMPLETE, INCOMPLETE, NO_DATA = "P00001", "P00002", "P00003"


@pytest.fixture(scope="module")
def dataset() -> StudyDataset:
    """A complete participant (C1), an incomplete one (C2: sessions 1 and 2 only) and one with
    no data at all (C1: enrolled, nothing answered)."""
    study = synthetic_study(4, seed=11)
    keep = {COMPLETE, INCOMPLETE, NO_DATA}
    responses = study.responses
    late = (responses["participant"] == INCOMPLETE) & (responses["session"].fillna(0) > 2)
    responses = responses[
        responses["participant"].isin({COMPLETE, INCOMPLETE}) & ~late
    ].reset_index(drop=True)
    steps = study.steps
    steps = steps[steps["participant"].isin({COMPLETE, INCOMPLETE})].reset_index(drop=True)
    participants = study.participants[study.participants["participant"].isin(keep)]
    return dataclasses.replace(
        study,
        participants=participants.reset_index(drop=True),
        responses=responses,
        steps=steps,
    )


@pytest.fixture(scope="module")
def result(dataset: StudyDataset) -> StudyAnalysis:
    return analyse_study(dataset)


def _section(report: str, anchor: str) -> str:
    start = report.index(f'<section id="{anchor}">')
    return report[start : report.index("</section>", start)]


def _text(fragment: str) -> str:
    return html.unescape(re.sub(r"<[^>]+>", " ", fragment))


def test_the_list_holds_the_participant_without_data_and_the_incomplete_one(
    result: StudyAnalysis,
) -> None:
    exclusions = result.exclusions()
    everywhere = exclusions[exclusions["analysis"] == ALL_ANALYSES]
    assert everywhere[["participant", "reason"]].values.tolist() == [[NO_DATA, NO_DATA_REASON]]
    per_measure = exclusions[exclusions["analysis"] != ALL_ANALYSES]
    assert set(per_measure["participant"]) == {INCOMPLETE}
    assert list(per_measure["analysis"]) == [o.key for o in result.outcomes]
    assert per_measure["reason"].str.contains(r"value for session 3, 4 \(needs all").all()
    # N analysed: the two who rated, not the one with nothing to analyse.
    assert list(result.participants["participant"]) == [COMPLETE, INCOMPLETE]
    assert result.sample["n"] == 2
    for outcome in result.outcomes:  # the ANOVA cannot run (one complete case) yet lists them
        assert outcome.anova is None and list(outcome.excluded["subject"]) == [INCOMPLETE]


def test_every_place_in_the_report_says_the_same(result: StudyAnalysis) -> None:
    report = build_report(result)
    methods = _text(_section(report, "methods"))
    participants = _text(_section(report, "participants"))
    assert "N = 2 participants were analysed (C1, Exp3: 1; C2, meta-learned policy: 1)" in methods
    assert "N = 2 participants were analysed" in participants
    sentence = (
        f"1 enrolled participant was excluded from every analysis ({NO_DATA_REASON}: 1) and "
        "1 analysed participant was excluded from the ANOVA of one or more measures for "
        "incomplete data (the mixed models use every rating they gave); each is listed with "
        "the reason below."
    )
    assert sentence in methods
    assert "No participant was excluded" not in report
    # The exclusions table: the participant without data, and the incomplete one.
    rows = re.findall(
        r"<tr><td[^>]*>(P\d+)</td><td[^>]*>(C\d)</td><td[^>]*>([^<]*)</td>"
        r"<td[^>]*>([^<]*)</td></tr>",
        _section(report, "participants"),
    )
    listed = {(code, html.unescape(what), html.unescape(why)) for code, _, what, why in rows}
    keys = ", ".join(o.key for o in result.outcomes)
    assert listed == {
        (NO_DATA, "all", NO_DATA_REASON),
        (INCOMPLETE, keys, "incomplete: no value for session 3, 4 (needs all of 1, 2, 3, 4)"),
    }
    for outcome in result.outcomes:  # each analysis's note counts the same one participant
        section = _text(_section(report, f"outcome-{outcome.key}"))
        assert "1 excluded as incomplete (listed under Exclusions)" in section
        assert not re.search(r"\((?!1 )\d+ excluded as incomplete\)", section)


def test_a_complete_study_says_nobody_was_excluded() -> None:
    result = analyse_study(synthetic_study(6, seed=2))
    assert result.exclusions().empty
    report = build_report(result)
    assert "No participant was excluded." in _text(_section(report, "methods"))
    assert "No participant was excluded." in _text(_section(report, "participants"))
    assert "6 participants with complete data, none excluded as incomplete." in report


def test_a_participant_who_answered_the_robot_but_rated_nothing_is_analysed(
    dataset: StudyDataset,
) -> None:
    """Answers to the robot are data (the adaptation curves use them): only a participant with
    neither a rating nor an answer is 'no data'; one without ratings is incomplete per outcome."""
    study = synthetic_study(4, seed=11)
    answered_only = study.steps[study.steps["participant"] == NO_DATA]
    assert len(answered_only)
    result = analyse_study(
        dataclasses.replace(
            dataset, steps=pd.concat([dataset.steps, answered_only], ignore_index=True)
        )
    )
    exclusions = result.exclusions()
    assert NO_DATA_REASON not in set(exclusions["reason"])
    assert NO_DATA in set(result.participants["participant"]) and result.sample["n"] == 3
    for outcome in result.outcomes:
        assert NO_DATA in set(outcome.excluded["subject"])


QUALITY = {
    "min_seconds_per_item": 2.0,
    "straightlining_min_items": 5,
    "max_away_seconds": 120.0,
    "attention_failures_allowed": 0,
    "exclude": ["attention"],
}


def _flagged_study(exclude: list[str]) -> StudyDataset:
    """Six participants with data-quality columns: one failed an attention check, one sped."""
    study = synthetic_study(6, seed=5)
    participants = study.participants.copy()
    participants["quality_flags"] = ["", "attention", "speeding", "", "attention;away", ""]
    return dataclasses.replace(
        study,
        participants=participants,
        protocol={**study.protocol, "quality": {**QUALITY, "exclude": exclude}},
        excluded_flags=frozenset(exclude),
    )


def test_a_protocols_excluding_flags_leave_participants_out_with_the_reason() -> None:
    study = _flagged_study(["attention"])
    result = analyse_study(study)
    codes = list(study.participants["participant"])
    everywhere = result.exclusions()
    everywhere = everywhere[everywhere["analysis"] == ALL_ANALYSES]
    assert dict(zip(everywhere["participant"], everywhere["reason"], strict=True)) == {
        codes[1]: "data quality (protocol's exclusion rule): attention",
        codes[4]: "data quality (protocol's exclusion rule): attention",
    }
    assert result.sample["n"] == 4 and codes[2] in set(result.participants["participant"])
    methods = _text(_section(build_report(result), "methods"))
    assert "data quality (protocol's exclusion rule): attention: 2" in methods
    # flags that exclude nothing are still exported: the column stays as it was
    kept = analyse_study(_flagged_study([]))
    assert kept.exclusions().empty and kept.sample["n"] == 6


def test_excluding_by_flag_needs_the_flags_column() -> None:
    study = synthetic_study(4, seed=1)
    with pytest.raises(InvalidInputError, match="needs a 'quality_flags' column"):
        dataclasses.replace(study, excluded_flags=frozenset({"attention"}))


def test_the_registered_plan_holds_the_quality_rules_and_a_change_is_a_deviation() -> None:
    registered = build_registration(
        study={"name": "s", "title": "S"},
        protocol_source="",
        plan=registered_plan(_flagged_study(["attention"])),
        hypotheses=[],
        power=None,
        software={},
        seeds={},
        created_at="2026-12-07",
        data={"participants_enrolled": 0, "participants_answered": 0},
    )
    rules = registered["analysis_plan"]["exclusions"]["rules"]
    assert any("'speeding': a questionnaire page answered in less than 2.0 s" in r for r in rules)
    assert "participants with the flag(s) 'attention' are left out of every analysis" in " ".join(
        rules
    )
    assert "Exclusion rules" in registration_markdown(registered)

    def exclusion_deviations(exclude: list[str]) -> list[str]:
        checked = check_registration(registered, analyse_study(_flagged_study(exclude)))
        return [d for d in checked.deviations if d.startswith("exclusion rules")]

    assert exclusion_deviations(["attention"]) == []
    assert len(exclusion_deviations(["speeding"])) == 1
