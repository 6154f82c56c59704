"""Adaptation measures per session, the within/between trust models, and the study runner."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from analysis.adaptation_trust import adaptation_trust, session_adaptation
from analysis.figures import trust_confidence_payload
from analysis.mixed_models import analyse_mixed_models
from analysis.mixed_prose import adaptation_sentences, lmm_sentences, ordinal_sentences
from analysis.study import StudyAnalysis, analyse_study
from analysis.synthetic import synthetic_study

PREFERRED = {"cognition": 1}


def _step(
    session: int,
    iteration: int,
    action: int,
    before: list[float],
    after: list[float],
    answer: bool,
    level: int,
) -> dict[str, object]:
    return {
        "participant": "P1",
        "condition": "C1",
        "category": "cognition",
        "session": session,
        "run": 1,
        "iteration": iteration,
        "action": action,
        "probs_before": before,
        "probs_after": after,
        "answer": answer,
        "reward": float(answer),
        "reply_probability": before[action],
        "reply_level": level,
    }


def test_session_measures_by_hand() -> None:
    steps = pd.DataFrame(
        [
            _step(1, 1, 1, [0.25, 0.25, 0.25, 0.25], [0.2, 0.4, 0.2, 0.2], True, 0),
            _step(1, 2, 0, [0.2, 0.4, 0.2, 0.2], [0.1, 0.6, 0.15, 0.15], False, 0),
            _step(2, 3, 1, [0.1, 0.6, 0.15, 0.15], [0.01, 0.97, 0.01, 0.01], True, 1),
            _step(2, 4, 1, [0.01, 0.97, 0.01, 0.01], [0.0, 0.99, 0.005, 0.005], True, 2),
        ]
    )
    measures = session_adaptation(steps, PREFERRED, reply_levels=["low", "mid", "high"])
    one, two = measures.iloc[0], measures.iloc[1]
    assert list(measures["session"]) == [1, 2]
    assert one["n_answers"] == 2 and one["confidence"] == pytest.approx((0.25 + 0.2) / 2)
    assert one["p_accepted"] == pytest.approx(0.25)  # only the yes counts
    assert two["p_accepted"] == pytest.approx((0.6 + 0.97) / 2)
    assert one["share_low"] == 1.0 and two["share_mid"] == 0.5 and two["share_high"] == 0.5
    assert two["share_top"] == 0.5
    # The preferred question first reached .95 after the third answer.
    assert (measures["answers_to_95"] == 3.0).all()


def test_never_learned_counts_as_one_more_answer_than_given() -> None:
    flat = [0.25, 0.25, 0.25, 0.25]
    steps = pd.DataFrame([_step(1, i, 0, flat, flat, False, 0) for i in (1, 2, 3)])
    steps = steps.drop(columns=["reply_probability", "reply_level"])
    measures = session_adaptation(steps, PREFERRED)
    assert measures.loc[0, "answers_to_95"] == 4.0
    assert np.isnan(measures.loc[0, "p_accepted"])  # no yes in the session
    assert measures.loc[0, "confidence"] == 0.25  # the asked question's probability
    assert "share_top" not in measures.columns


def _mechanism(seed: int = 7, n: int = 60) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Trust that rises with a participant's overall confidence (between, +2) but falls in the
    sessions where it is above their own average (within, −3)."""
    rng = np.random.default_rng(seed)
    measure_rows, trust_rows = [], []
    for i in range(n):
        mean = rng.uniform(0.3, 0.9)
        person = rng.normal(0, 0.2)
        deviations = rng.normal(0, 0.1, 4)
        deviations -= deviations.mean()
        for s in range(4):
            c = mean + deviations[s]
            measure_rows.append(
                {
                    "participant": f"P{i}",
                    "condition": "AB"[i % 2],
                    "session": s + 1,
                    "confidence": c,
                    "p_accepted": c,
                    "answers_to_95": 13 - 10 * mean,
                }
            )
            trust = 3 + 2 * (mean - 0.6) - 3 * deviations[s] + person + rng.normal(0, 0.1)
            trust_rows.append(
                {"participant": f"P{i}", "condition": "AB"[i % 2], "session": s + 1, "trust": trust}
            )
    return pd.DataFrame(measure_rows), pd.DataFrame(trust_rows)


def test_person_mean_centring_separates_within_from_between() -> None:
    measures, trust = _mechanism()
    result = adaptation_trust(measures, trust, dv="trust")
    effects = result.effects.set_index(["measure", "part"])
    assert effects.loc[("confidence", "within"), "estimate"] == pytest.approx(-3, abs=0.3)
    assert effects.loc[("confidence", "between"), "estimate"] == pytest.approx(2, abs=0.6)
    assert effects.loc[("confidence", "within"), "p"] < 1e-6
    # answers_to_95 is a property of the participant: only its between part is modelled.
    assert list(effects.loc["answers_to_95"].index) == ["between"]
    assert set(result.data.columns) >= {"confidence_within", "confidence_between"}
    within_means = result.data.groupby("participant")["confidence_within"].mean()
    assert within_means.abs().max() < 1e-12
    assert result.fits["confidence"].formula == (
        "trust ~ condition + session + confidence_within + confidence_between + (1 | participant)"
    )
    sentences = adaptation_sentences(result)
    assert sentences[0].startswith("The robot's confidence (probability behind its reply): within")
    json.dumps(result.to_dict(), allow_nan=False)


def test_a_measure_that_does_not_vary_is_named_not_modelled() -> None:
    measures, trust = _mechanism(n=20)
    measures["p_accepted"] = 0.5
    result = adaptation_trust(measures, trust, dv="trust")
    assert "p_accepted" not in set(result.effects["measure"])
    assert "does not vary" in result.problems["p_accepted"]


def test_trust_confidence_figure_has_points_and_a_line_per_condition() -> None:
    measures, trust = _mechanism(n=10)
    data = adaptation_trust(measures, trust, dv="trust").data
    payload = trust_confidence_payload(data, dv="trust", colors={"A": "#000000"})
    modes = [(t["name"], t["mode"]) for t in payload["data"]]
    assert modes == [
        ("A", "markers"),
        ("A (least squares)", "lines"),
        ("B", "markers"),
        ("B (least squares)", "lines"),
    ]
    assert payload["data"][1]["line"]["color"] == "#000000"
    assert len(payload["data"][0]["x"]) == 20
    json.dumps(payload, allow_nan=False)


@pytest.fixture(scope="module")
def study() -> StudyAnalysis:
    return analyse_study(synthetic_study(24, seed=2, dropout_rate=0.15))


def test_the_study_runner_fits_every_per_session_measure(study: StudyAnalysis) -> None:
    mixed = analyse_mixed_models(study)
    assert [o.key for o in mixed.outcomes] == [f"trust_{i}" for i in range(1, 6)]
    first = mixed.outcome("trust_1")
    assert first.lmm is not None and first.lmm.slope is not None
    assert first.ordinal is not None and first.ordinal.converged
    assert first.adaptation is not None and not first.adaptation.effects.empty
    assert len(first.lmm.kept) == first.anova_excluded > 0
    assert "excluded for a missing session" in lmm_sentences(first.lmm)[0]
    assert ordinal_sentences(first.ordinal)[0].startswith("A proportional-odds")
    json.dumps(mixed.to_dict(), allow_nan=False)


def test_withheld_steps_leave_the_trust_models_and_say_why(study: StudyAnalysis) -> None:
    sealed = replace(
        study.dataset,
        steps=study.dataset.steps.iloc[0:0],
        steps_withheld="the study is blinded",
    )
    mixed = analyse_mixed_models(analyse_study(sealed), keys=["trust_2"], random_slope=False)
    (outcome,) = mixed.outcomes
    assert outcome.adaptation is None and outcome.adaptation_problem == "the study is blinded"
    assert outcome.lmm is not None and outcome.lmm.slope is None
    with pytest.raises(ValueError, match="no per-session measure"):
        analyse_mixed_models(analyse_study(sealed), keys=["nope"])
