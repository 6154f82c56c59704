"""The whole-study analysis: outcomes, exclusions, scores, adaptation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from analysis.anova import mixed_anova
from analysis.dataset import StudyDataset
from analysis.errors import InvalidInputError
from analysis.instruments import DEFAULT_INSTRUMENTS
from analysis.scoring import TIPI_SCALES, ScaleSpec
from analysis.study import EXCLUSION_LIST_COLUMNS, StudyAnalysis, analyse_study
from analysis.synthetic import synthetic_study


@pytest.fixture(scope="module")
def dataset() -> StudyDataset:
    return synthetic_study(40, seed=5, dropout_rate=0.2)


@pytest.fixture(scope="module")
def result(dataset: StudyDataset) -> StudyAnalysis:
    return analyse_study(dataset)


def test_one_outcome_per_trust_item(result: StudyAnalysis) -> None:
    assert [o.key for o in result.outcomes] == [f"trust_{i}" for i in range(1, 6)]
    assert result.outcome("trust_5").reverse_keyed
    assert result.outcome("trust_1").value_range == (1.0, 5.0)
    assert all(o.anova is not None and o.problem == "" for o in result.outcomes)
    with pytest.raises(InvalidInputError, match="no outcome"):
        result.outcome("trust_9")


def test_outcome_anova_equals_direct_call_on_scored_values(
    dataset: StudyDataset, result: StudyAnalysis
) -> None:
    # trust_5 is analysed after reversal: 6 − raw.
    withdrawn = set(
        dataset.participants.loc[dataset.participants.status == "withdrawn", "participant"]
    )
    raw = dataset.responses[
        (dataset.responses["item"] == "trust_5") & ~dataset.responses["participant"].isin(withdrawn)
    ]
    condition = dataset.participants.set_index("participant")["condition"]
    direct = mixed_anova(
        raw.assign(y=6 - raw["value"], condition=raw["participant"].map(condition)),
        dv="y",
        within="session",
        between="condition",
        subject="participant",
        within_levels=[1, 2, 3, 4],
    )
    ours = result.outcome("trust_5").anova
    assert ours is not None
    np.testing.assert_allclose(ours.table["F"], direct.table["F"], rtol=1e-12)
    assert ours.n_subjects_used == direct.n_subjects_used


def test_status_and_incomplete_exclusions(dataset: StudyDataset, result: StudyAnalysis) -> None:
    statuses = dataset.participants.set_index("participant")["status"]
    n_withdrawn = int((statuses == "withdrawn").sum())
    assert n_withdrawn > 0
    assert len(result.status_exclusions) == n_withdrawn
    assert set(result.status_exclusions["reason"]) == {"status: withdrawn"}
    assert len(result.participants) == 40 - n_withdrawn
    exclusions = result.exclusions()
    assert tuple(exclusions.columns) == EXCLUSION_LIST_COLUMNS
    incomplete = exclusions[exclusions["analysis"] == "trust_1"]
    # Active dropouts (not withdrawn) are kept but miss later sessions → excluded per outcome.
    active_dropouts = set(statuses[statuses == "active"].index)
    assert set(incomplete["participant"]) == active_dropouts
    assert incomplete["reason"].str.startswith("incomplete: no trust_1 value for session").all()
    anova = result.outcome("trust_1").anova
    assert anova is not None
    assert anova.n_subjects_used == 40 - n_withdrawn - len(active_dropouts)


def test_descriptives_describe_the_anova_sample(result: StudyAnalysis) -> None:
    outcome = result.outcome("trust_2")
    assert outcome.anova is not None
    assert outcome.descriptives.groupby("condition")["n"].first().sum() == (
        outcome.anova.n_subjects_used
    )
    assert outcome.marginal_conditions is not None
    assert list(outcome.marginal_conditions["condition"]) == ["C1", "C2"]
    assert outcome.posthoc is not None
    assert len(outcome.posthoc) == 2 * 6 + 4
    assert outcome.sentences is not None
    assert outcome.sentences["text"].str.contains(r"F\(1, \d+\)").any()


def test_person_scores_and_sample(result: StudyAnalysis) -> None:
    assert set(result.person_scores["scale"]) == {s.name for s in result.dataset.scales}
    summary = result.person_summary.set_index(["scale", "condition"])
    assert summary.loc[("tipi_openness", "C1"), "n"] > 0
    assert result.sample["n"] == len(result.participants)
    assert sum(result.sample["by_condition"].values()) == result.sample["n"]
    assert sum(result.sample["gender"].values()) == result.sample["n"]
    assert 18 <= result.sample["age"]["min"] <= result.sample["age"]["mean"]


def test_adaptation_curves_use_analysed_participants(result: StudyAnalysis) -> None:
    curves = result.adaptation
    assert set(curves["category"]) == {"conation", "affection", "cognition"}
    first = curves[curves["iteration"] == 0].groupby("condition")["n"].sum()
    assert first.sum() == 3 * len(result.participants)
    assert result.adaptation_problem == ""
    c1 = curves[(curves.condition == "C1") & (curves.category == "conation")]["mean"].to_numpy()
    c2 = curves[(curves.condition == "C2") & (curves.category == "conation")]["mean"].to_numpy()
    assert c2[-1] > c1[-1]  # the synthetic C2 learns faster


def test_degenerate_outcome_reports_problem_not_crash(dataset: StudyDataset) -> None:
    flat = dataset.responses.copy()
    flat.loc[flat["item"] == "trust_3", "value"] = 4.0
    result = analyse_study(dataclasses.replace(dataset, responses=flat))
    outcome = result.outcome("trust_3")
    assert outcome.anova is None
    assert "cannot be computed because all" in outcome.problem
    assert len(outcome.descriptives) == 8  # still described
    assert result.outcome("trust_1").anova is not None


def test_bad_step_log_reports_problem(dataset: StudyDataset) -> None:
    steps = dataset.steps.copy()
    steps.loc[steps.index[0], "iteration"] = 99
    result = analyse_study(dataclasses.replace(dataset, steps=steps))
    assert "without gaps" in result.adaptation_problem
    assert result.adaptation.empty


def test_per_session_scale_gets_its_own_anova(dataset: StudyDataset) -> None:
    # A protocol-defined composite of items 2, 4 and 5 (reversed) analysed like an item.
    composite = ScaleSpec(
        "robot_trust_in_me", "trust", ("trust_2", "trust_4", "trust_5"),
        frozenset({"trust_5"}), 1, 5, "mean", "Robot's trust in me (composite)",
    )  # fmt: skip
    result = analyse_study(
        dataclasses.replace(dataset, scales=(*TIPI_SCALES, composite)), ss_type=2
    )
    outcome = result.outcome("robot_trust_in_me")
    assert outcome.kind == "scale"
    assert outcome.anova is not None
    assert outcome.anova.ss_type == 2
    assert result.ss_type == 2
    assert "robot_trust_in_me" not in set(result.person_scores["scale"])


def test_responses_must_match_the_instruments(dataset: StudyDataset) -> None:
    bad = dataclasses.replace(dataset, instruments=DEFAULT_INSTRUMENTS[1:])  # no demographics
    with pytest.raises(InvalidInputError, match="demographics"):
        analyse_study(bad)


def test_empty_steps_give_empty_curves() -> None:
    result = analyse_study(synthetic_study(6, seed=2, with_steps=False))
    assert result.adaptation.empty
    assert result.adaptation_problem == ""
    assert isinstance(result.adaptation, pd.DataFrame)


def test_settings_are_checked_up_front(dataset: StudyDataset) -> None:
    with pytest.raises(InvalidInputError, match="ss_type"):
        analyse_study(dataset, ss_type=1)  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="confidence"):
        analyse_study(dataset, confidence=95)
