"""The rule that chooses the shipped C2 checkpoints among seeds (issue 36 item 2): a candidate
qualifies when it meets every target on validation draws; the best filter objective among the
qualifiers wins; when none qualifies, the shipped checkpoint stays."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from bench.robust import SCENARIOS
from models.checkpoints import PRETRAINED_DIR, load_checkpoint, shipped_checkpoint, trained_feedback
from models.feedback import FeedbackModel
from models.seed_selection import (
    ISSUE_TARGETS,
    Candidate,
    TargetFigures,
    select_by_targets,
    shortfalls,
    target_validation,
    validation_scenarios,
)


def _figures(
    wrong5: float = 1.0,
    wrong10: float = 1.0,
    answers: float = 1.0,
    recovered: float = 0.9,
    filter_recovered: float = 0.88,
) -> TargetFigures:
    return TargetFigures(
        wrong_ratio={"5 % slips": wrong5, "10 % slips": wrong10},
        answers_ratio={"consistent yes/no": answers, "5 % slips": answers, "10 % slips": answers},
        recovered=recovered,
        filter_recovered=filter_recovered,
    )


TABLE = [
    Candidate("calibrated, slower to recover", -0.4030, _figures(0.9, 1.0, 1.06, 0.86)),
    Candidate("on every target", -0.4020, _figures(1.25, 1.2, 1.1, 0.85)),
    Candidate("best objective, wrong at 10 %", -0.3990, _figures(1.1, 1.26)),
    Candidate("good objective, wrong at 5 %", -0.3995, _figures(2.43, 1.2)),
    Candidate("slow", -0.4000, _figures(answers=1.11)),
    Candidate(
        "as the filter recovers, below .85",
        -0.4001,
        _figures(recovered=0.84, filter_recovered=0.84),
    ),
]


def test_the_best_objective_among_the_candidates_on_every_target_wins() -> None:
    assert [c.name for c in TABLE if not shortfalls(c.figures)] == [
        "calibrated, slower to recover",
        "on every target",
    ]
    chosen = select_by_targets(TABLE)
    assert chosen is not None and chosen.name == "on every target"
    # Without it, the other qualifier, though three candidates score better.
    rest = [c for c in TABLE if c.name != "on every target"]
    chosen = select_by_targets(rest)
    assert chosen is not None and chosen.name == "calibrated, slower to recover"


def test_when_none_qualifies_nothing_is_chosen_and_the_shipped_one_stays() -> None:
    assert select_by_targets(TABLE[2:]) is None
    assert select_by_targets([]) is None


def test_each_missed_target_is_named_with_its_figure() -> None:
    assert shortfalls(TABLE[2].figures) == ["wrong 1.26 × at 10 % slips"]
    assert shortfalls(TABLE[3].figures) == ["wrong 2.43 × at 5 % slips"]
    assert shortfalls(TABLE[4].figures) == [
        "answers 1.110 × at consistent yes/no",
        "answers 1.110 × at 5 % slips",
        "answers 1.110 × at 10 % slips",
    ]
    # Recovery is the issue's absolute share: recovering as the filter does is not enough.
    assert shortfalls(TABLE[5].figures) == ["recovered 0.840"]
    assert shortfalls(_figures(wrong5=math.inf)) == ["wrong inf × at 5 % slips"]
    assert shortfalls(_figures(wrong10=math.nan)) == ["wrong nan × at 10 % slips"]


def test_the_targets_are_the_issues() -> None:
    assert (ISSUE_TARGETS.wrong_ratio, ISSUE_TARGETS.answers_ratio) == (1.25, 1.1)
    assert ISSUE_TARGETS.recovered == 0.85
    loose = replace(ISSUE_TARGETS, recovered=0.8)
    assert shortfalls(TABLE[5].figures, loose) == []


def test_validation_runs_the_benchs_scenarios_against_the_filter_for_the_trained_model() -> None:
    """Only the draws differ from the bench's: the same participants' models, the same change,
    and the reference is the filter for the model C2 was trained for."""
    model = FeedbackModel(slips=(0.0, 0.05, 0.1), slip_weights=(0.4, 0.3, 0.3), hazard=0.02)
    scenarios = validation_scenarios(model)
    assert set(scenarios) <= set(SCENARIOS)
    for title, scenario in scenarios.items():
        bench = SCENARIOS[title][0]
        assert (scenario.feedback, scenario.change_after) == (bench.feedback, bench.change_after)
        assert scenario.assumed == model
    assert {"5 % slips", "10 % slips"} <= set(scenarios)
    assert any(s.change_after is not None for s in scenarios.values())


def test_target_validation_reports_the_issues_figures_against_the_filter() -> None:
    checkpoint = load_checkpoint(shipped_checkpoint(4, "cognition", directory=PRETRAINED_DIR), 4)
    assert trained_feedback(checkpoint).hazard > 0
    figures = target_validation(checkpoint, participants=400, seed=3)
    assert set(figures.wrong_ratio) == {"5 % slips", "10 % slips"}
    assert set(figures.answers_ratio) == {"consistent yes/no", "5 % slips", "10 % slips"}
    assert all(0.5 < ratio < 2 for ratio in figures.answers_ratio.values())
    assert all(ratio >= 0 for ratio in figures.wrong_ratio.values())
    assert 0 < figures.recovered <= 1 and 0 < figures.filter_recovered <= 1
    assert target_validation(checkpoint, participants=400, seed=3) == figures
    assert target_validation(checkpoint, participants=400, seed=4) != figures


@pytest.mark.parametrize("title", ["5 % slips", "10 % slips"])
def test_a_candidate_wrong_at_either_slip_rate_does_not_qualify(title: str) -> None:
    figures = _figures()
    figures.wrong_ratio[title] = 1.2501
    assert select_by_targets([Candidate("x", 0.0, figures)]) is None
