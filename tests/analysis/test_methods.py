"""Methods text generated from the protocol summary."""

from __future__ import annotations

import math

from analysis.instruments import DEFAULT_INSTRUMENTS
from analysis.methods import (
    analysis_paragraph,
    design_paragraph,
    participants_paragraph,
    population_sentence,
)
from analysis.synthetic import SEED_PAPER_PROTOCOL


def test_participants_paragraph_from_the_papers_sample() -> None:
    # The seed paper: N = 24 (11 female, 13 male), age 22–48 (M 27.04, SD 5.42), 12 per condition.
    sample = {
        "n": 24,
        "by_condition": {"C1": 12, "C2": 12},
        "gender": {"Female": 11, "Male": 13},
        "age": {"n": 24, "mean": 27.04, "sd": 5.42, "min": 22.0, "max": 48.0},
    }
    assert participants_paragraph(SEED_PAPER_PROTOCOL, sample) == (
        "N = 24 participants were analysed (C1, Exp3: 12; C2, meta-learned policy: 12); "
        "11 female, 13 male; aged 22–48 years (M = 27.04, SD = 5.42)."
    )


def test_participants_paragraph_partial_information() -> None:
    sample = {
        "n": 3,
        "by_condition": {"C1": 3},
        "age": {"n": 1, "mean": 30.0, "sd": math.nan, "min": 30.0, "max": 30.0},
    }
    assert participants_paragraph(SEED_PAPER_PROTOCOL, sample) == (
        "N = 3 participants were analysed (C1, Exp3: 3; C2, meta-learned policy: 0); "
        "aged 30 years (M = 30.00, n = 1)."
    )


def test_design_paragraph_describes_the_protocol() -> None:
    text = design_paragraph(SEED_PAPER_PROTOCOL, DEFAULT_INSTRUMENTS)
    assert "allocated to two conditions, C1 (Exp3) and C2 (meta-learned policy)" in text
    assert "After one familiarisation run not used for adaptation" in text
    assert "four sessions of three runs" in text
    assert (
        "one of 4 questions in each of three categories (conation, affection and cognition)" in text
    )
    assert "12 adaptation iterations per category" in text
    assert (
        "“Per-session bi-directional trust” (five items, 5-point scale; reverse-keyed: trust_5)"
        in text
    )
    assert "Ten-Item Personality Inventory (TIPI)" in text


def test_design_paragraph_other_protocol() -> None:
    protocol = {
        **SEED_PAPER_PROTOCOL,
        "sessions": 1,
        "runs_per_session": 12,
        "familiarisation_runs": 0,
        "categories": {"cognition": ["a", "b", "c"]},
        "preferred_arms": {"cognition": 2},
    }
    text = design_paragraph(protocol, ())  # type: ignore[arg-type]
    assert text.count("Each participant completed one session of 12 runs") == 0
    assert "each participant completed one session of 12 runs" in text
    assert "one of 3 questions in each of one category (cognition)" in text


def test_analysis_paragraph_names_the_sums_of_squares() -> None:
    three = analysis_paragraph(SEED_PAPER_PROTOCOL, 2, 3, 0.95)
    assert "2 (condition, between subjects) × 4 (session, within subjects) mixed ANOVA" in three
    assert "type III sums of squares" in three
    assert "95% t confidence intervals" in three
    two = analysis_paragraph(SEED_PAPER_PROTOCOL, 2, 2, 0.9)
    assert "type II sums of squares (as pingouin" in two
    assert "90% t" in two


def test_population_sentence_names_the_source_n_and_the_fitted_figures() -> None:
    population = {
        "sha256": "ab" * 32,
        "source": "pilot-2026",
        "categories": {
            "conation": {
                "participants": 1,
                "prior": [0.7, 0.3],
                "prior_ci": [[0.52, 0.85], [0.15, 0.48]],
                "slip": 0.04,
                "slip_ci": [0.0, 0.09],
                "hazard": 0.011,
            },
            "cognition": {},  # its checkpoint was lost: only the hash was recorded
        },
        "enrolling_reason": "pilot left open by mistake",
    }
    text = population_sentence(population)
    assert text.startswith(
        "The meta-learned policy was meta-trained on the population fitted from 1 earlier "
        "participant of pilot-2026 (population file SHA-256 abababababab)"
    )
    assert "conation: .70 [.52, .85], .30 [.15, .48] for questions 1–2" in text
    assert "slip rate .04 [.00, .09], hazard .01" in text
    assert "cognition: not recorded (its checkpoint is missing)" in text
    assert text.endswith("for this recorded reason: pilot left open by mistake.")
    protocol = dict(SEED_PAPER_PROTOCOL) | {"population": population}
    assert text in design_paragraph(protocol, DEFAULT_INSTRUMENTS)  # type: ignore[arg-type]
    assert "meta-trained on the population" not in design_paragraph(
        SEED_PAPER_PROTOCOL, DEFAULT_INSTRUMENTS
    )
