"""APA formatting of statistics."""

from __future__ import annotations

import pandas as pd
import pytest

from analysis.anova import mixed_anova
from analysis.apa import (
    anova_sentences,
    format_df,
    format_p,
    format_proportion,
    sentence_f,
    sentence_t,
    sphericity_sentence,
)
from analysis.errors import InvalidInputError
from tests.analysis.conftest import load_reference, make_mixed


def test_the_issue_example() -> None:
    assert sentence_f(4.794, 1, 22, 0.0394, 0.179) == "F(1, 22) = 4.79, p = .039, ηp² = .18"


@pytest.mark.parametrize(
    ("p", "text"),
    [
        (0.0394, "p = .039"),
        (0.00099, "p < .001"),
        (0.001, "p = .001"),
        (0.0, "p < .001"),
        (0.5, "p = .500"),
        (0.99951, "p > .999"),
        (1.0, "p > .999"),
        (None, "p = —"),
    ],
)
def test_format_p(p: float | None, text: str) -> None:
    assert format_p(p) == text


def test_format_p_refuses_impossible_values() -> None:
    with pytest.raises(InvalidInputError):
        format_p(1.2)


def test_proportions_and_df() -> None:
    assert format_proportion(0.179) == ".18"
    assert format_proportion(-0.25) == "-.25"
    assert format_proportion(-0.001) == ".00"
    assert format_proportion(1.0) == "1.00"
    assert format_df(22.0) == "22"
    assert format_df(63.8508) == "63.85"
    assert sentence_t(-2.8723, 12, 0.014, -0.77) == "t(12) = -2.87, p = .014, d = -0.77"


def test_anova_sentences_uncorrected_when_sphericity_holds() -> None:
    # Values: R afex 1.2-1 type III, reference case pingouin_mixed_anova_unbalanced.
    data, _, _ = load_reference("pingouin_mixed_anova_unbalanced")
    result = mixed_anova(data, dv="dv", within="within", between="between", subject="subject")
    out = anova_sentences(result).set_index("effect")
    assert out.loc["between", "text"] == "between: F(2, 23) = 2.30, p = .123, ηp² = .17"
    assert out.loc["within", "text"] == "within: F(3, 69) = 1.54, p = .212, ηp² = .06"
    assert not out["corrected"].any()
    assert sphericity_sentence(result) == "Mauchly's W = .89, p = .754, ε = .93"


def test_anova_sentences_use_greenhouse_geisser_when_violated() -> None:
    data, _, _ = load_reference("pingouin_mixed_anova_unbalanced")
    result = mixed_anova(data, dv="dv", within="within", between="between", subject="subject")
    out = anova_sentences(result, sphericity_alpha=0.8).set_index("effect")
    # GG df = 3 × .925374 = 2.78 and 69 × .925374 = 63.85; p_GG = .215 (R afex 1.2-1).
    assert out.loc["within", "text"] == (
        "within: F(2.78, 63.85) = 1.54, p = .215, ηp² = .06, ε = .93 (Greenhouse–Geisser)"
    )
    assert out.loc["within", "corrected"]
    assert not out.loc["between", "corrected"]


def test_two_levels_and_undefined_sphericity_sentences() -> None:
    kw = {"dv": "y", "within": "time", "between": "group", "subject": "subject"}
    two = mixed_anova(make_mixed((4, 5), 2), **kw)
    assert "two levels" in sphericity_sentence(two)
    singular = mixed_anova(make_mixed((2, 2), 4), **kw)
    assert "could not be computed" in sphericity_sentence(singular)
    assert anova_sentences(singular).set_index("effect").loc["within", "corrected"]


def test_sentences_table_shape() -> None:
    data, _, _ = load_reference("pingouin_mixed_anova")
    out = anova_sentences(
        mixed_anova(data, dv="dv", within="within", between="between", subject="subject")
    )
    assert isinstance(out, pd.DataFrame)
    assert list(out.columns) == ["effect", "Source", "corrected", "text"]
    assert list(out["effect"]) == ["between", "within", "interaction"]
