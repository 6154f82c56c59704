"""Post-hoc pairwise comparisons with Holm correction."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pingouin as pg
import pytest

from analysis.design import prepare_mixed_design
from analysis.errors import InvalidInputError
from analysis.posthoc import POSTHOC_COLUMNS, adjust_pvalues, pairwise_comparisons

KW = {"dv": "trust", "within": "session", "between": "condition", "subject": "participant"}


def test_holm_by_hand() -> None:
    # Holm (1979): sorted p .01, .02, .03, .04 × 4, 3, 2, 1 → .04, .06, .06 (monotone), .06.
    out = adjust_pvalues([0.03, 0.01, 0.04, 0.02, np.nan])
    np.testing.assert_allclose(out[:4], [0.06, 0.04, 0.06, 0.06])
    assert np.isnan(out[4])
    np.testing.assert_allclose(adjust_pvalues([0.3, 0.6], "bonferroni"), [0.6, 1.0])
    np.testing.assert_allclose(adjust_pvalues([0.3, 0.6], "none"), [0.3, 0.6])
    with pytest.raises(InvalidInputError, match="padjust"):
        adjust_pvalues([0.1], "fdr")  # type: ignore[arg-type]


def test_known_values(dropouts: pd.DataFrame) -> None:
    # Hard-coded from pingouin 0.7.0 pairwise_tests(padjust="holm", effsize="cohen") on the
    # complete cases: within_first=False (sessions within condition, paired) and True
    # (conditions at each session, Welch because 9 ≠ 13).
    out = pairwise_comparisons(dropouts, **KW)
    assert tuple(out.columns) == POSTHOC_COLUMNS
    row = out[(out.family == "within") & (out["at"] == "C2") & (out.A == 2) & (out.B == 4)].iloc[0]
    assert row["T"] == pytest.approx(-2.8723335098, abs=1e-9)
    assert row["dof"] == 12
    assert row["p_unc"] == pytest.approx(0.0140288904, abs=1e-10)
    assert row["p_adj"] == pytest.approx(0.1683466848, abs=1e-10)
    assert row["cohen_d"] == pytest.approx(-0.7734269431, abs=1e-9)
    row = out[(out.family == "between") & (out["at"] == 4)].iloc[0]
    assert (row["A"], row["B"], bool(row["welch"])) == ("C1", "C2", True)
    assert row["T"] == pytest.approx(-3.6144993707, abs=1e-9)
    assert row["dof"] == pytest.approx(19.0355284535, abs=1e-9)
    assert row["p_adj"] == pytest.approx(0.0073681760, abs=1e-10)
    assert row["cohen_d"] == pytest.approx(-1.5197097057, abs=1e-9)
    assert len(out) == 2 * 6 + 4


@pytest.mark.filterwarnings("ignore:'str' is not supported as a fill value")  # pingouin 0.7.0
@pytest.mark.parametrize("within_first", [False, True])
def test_matches_pingouin_interaction_families(dropouts: pd.DataFrame, within_first: bool) -> None:
    # Cross-check with pingouin 0.7.0 on the ANOVA's complete cases.
    long = prepare_mixed_design(dropouts, **KW).long()
    long["trust"] = long["trust"].astype(float)
    ref = pg.pairwise_tests(
        data=long, padjust="holm", within_first=within_first, effsize="cohen", **KW
    )
    ref = ref[ref["Contrast"].str.contains(r"\*")]
    ours = pairwise_comparisons(dropouts, **KW)
    ours = ours[ours.family == ("between" if within_first else "within")]
    np.testing.assert_allclose(ours["T"], ref["T"], rtol=1e-9)
    np.testing.assert_allclose(ours["dof"], ref["dof"], rtol=1e-9)
    np.testing.assert_allclose(ours["p_adj"], ref["p_corr"], rtol=1e-9)
    np.testing.assert_allclose(ours["cohen_d"], ref["cohen"], rtol=1e-9)


def test_equal_groups_use_student_t() -> None:
    df = pd.DataFrame(
        {
            "participant": np.repeat(np.arange(6), 2),
            "condition": np.repeat(["A"] * 3 + ["B"] * 3, 2),
            "session": np.tile([1, 2], 6),
            "trust": [1, 2, 2, 3, 3, 5, 2, 2, 4, 4, 5, 4.5],
        }
    )
    out = pairwise_comparisons(df, **KW)
    between = out[out.family == "between"]
    assert not between["welch"].any()
    assert set(between["dof"]) == {4.0}


def test_undefined_comparison_has_note_not_crash() -> None:
    # Every participant in A rises by exactly 1: zero-variance differences.
    df = pd.DataFrame(
        {
            "participant": np.repeat(np.arange(6), 2),
            "condition": np.repeat(["A"] * 3 + ["B"] * 3, 2),
            "session": np.tile([1, 2], 6),
            "trust": [1, 2, 2, 3, 3, 4, 2, 2, 4, 4, 5, 4.5],
        }
    )
    out = pairwise_comparisons(df, **KW)
    a = out[(out.family == "within") & (out["at"] == "A")].iloc[0]
    assert np.isnan(a["T"])
    assert np.isnan(a["p_adj"])
    assert "zero variance" in a["note"]
