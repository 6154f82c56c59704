"""Cell descriptives and estimated marginal means."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import statsmodels.api as sm

from analysis.descriptives import (
    CELL_COLUMNS,
    cell_descriptives,
    marginal_means,
    t_interval,
)
from analysis.design import prepare_mixed_design
from analysis.errors import CannotComputeError, InvalidInputError

DKW = {"dv": "trust", "within": "session", "between": "condition"}


def test_cell_descriptives_by_hand() -> None:
    # Cell (A, 1) = 1, 2, 3, 4: M = 2.5, SD = √(5/3) = 1.2909944, SE = 0.6454972,
    # t(.975, 3) = 3.1824463 (standard t table) → CI = 2.5 ± 2.0542603.
    df = pd.DataFrame(
        {
            "g": ["A"] * 4 + ["B"] * 2 + ["A"],
            "s": [1, 1, 1, 1, 1, 1, 2],
            "y": [1.0, 2.0, 3.0, 4.0, 5.0, 5.0, 9.0],
        }
    )
    out = cell_descriptives(df, dv="y", within="s", between="g")
    assert list(out.columns) == ["g", "s", *CELL_COLUMNS]
    assert list(zip(out["g"], out["s"], strict=True)) == [("A", 1), ("A", 2), ("B", 1)]
    a1 = out.iloc[0]
    assert a1["n"] == 4
    assert a1["mean"] == 2.5
    assert a1["sd"] == pytest.approx(1.2909944487, abs=1e-9)
    assert a1["se"] == pytest.approx(0.6454972244, abs=1e-9)
    assert a1["ci_low"] == pytest.approx(2.5 - 2.0542603, abs=1e-6)
    assert a1["ci_high"] == pytest.approx(2.5 + 2.0542603, abs=1e-6)
    single = out.iloc[1]  # one value: no spread, no interval
    assert single["n"] == 1
    assert np.isnan(single["sd"])
    assert np.isnan(single["ci_low"])
    zero = out.iloc[2]  # two equal values: SD 0, CI collapses to the mean
    assert zero["sd"] == 0
    assert zero["ci_low"] == zero["ci_high"] == 5.0


def test_cell_descriptives_ignore_missing_values(dropouts: pd.DataFrame) -> None:
    out = cell_descriptives(dropouts, **DKW).set_index(["condition", "session"])
    assert out.loc[("C2", 2), "n"] == 13  # P120's NaN not counted
    assert out.loc[("C1", 4), "n"] == 9  # P103 and P110 have no session 4
    assert out.loc[("C1", 1), "n"] == 11


def test_descriptives_on_the_anova_sample(dropouts: pd.DataFrame) -> None:
    design = prepare_mixed_design(dropouts, **DKW, subject="participant")
    out = cell_descriptives(design.long(), **DKW)
    assert set(out["n"]) == {9, 13}


def test_cell_descriptives_refuse_bad_input(dropouts: pd.DataFrame) -> None:
    with pytest.raises(InvalidInputError, match="no column 'nope'"):
        cell_descriptives(dropouts, dv="nope", within="session", between="condition")
    with pytest.raises(CannotComputeError, match="no non-missing value"):
        cell_descriptives(dropouts.assign(trust=np.nan), **DKW)
    with pytest.raises(InvalidInputError, match="confidence"):
        cell_descriptives(dropouts, **DKW, confidence=95)


def test_t_interval_nan_without_df() -> None:
    low, high = t_interval(np.array([1.0]), np.array([0.5]), np.array([0]))
    assert np.isnan(low[0])
    assert np.isnan(high[0])


def test_marginal_means_by_condition_match_ols(dropouts: pd.DataFrame) -> None:
    # Independent check: statsmodels 0.15.0 OLS of participant means on condition dummies
    # (no intercept): coefficients are the condition means, bse = √(MSE / n_g), df = N − G.
    out = marginal_means(dropouts, **DKW, subject="participant").set_index("condition")
    design = prepare_mixed_design(dropouts, **DKW, subject="participant")
    means = design.values.mean(axis=1)
    dummies = np.eye(2)[design.groups]
    fit = sm.OLS(means, dummies).fit()
    np.testing.assert_allclose(out["mean"], fit.params, rtol=1e-12)
    np.testing.assert_allclose(out["se"], fit.bse, rtol=1e-12)
    assert set(out["df"]) == {20.0}
    assert list(out["n"]) == [9, 13]
    ci = fit.conf_int()
    np.testing.assert_allclose(out["ci_low"], ci[:, 0], rtol=1e-12)


def test_marginal_means_by_session_weight_conditions_equally(dropouts: pd.DataFrame) -> None:
    # Independent check: per session, OLS of the values on condition dummies; the EMM is the
    # contrast (½, ½) of the two condition means and its SE comes from statsmodels' t_test.
    out = marginal_means(dropouts, **DKW, subject="participant", by="within")
    design = prepare_mixed_design(dropouts, **DKW, subject="participant")
    dummies = np.eye(2)[design.groups]
    for s in range(4):
        test = sm.OLS(design.values[:, s], dummies).fit().t_test([0.5, 0.5])
        assert out["mean"].iloc[s] == pytest.approx(float(test.effect[0]), rel=1e-12)
        assert out["se"].iloc[s] == pytest.approx(float(test.sd[0, 0]), rel=1e-12)
    assert list(out["session"]) == [1, 2, 3, 4]
    # Unweighted: differs from the plain mean of all 22 participants (groups 9 vs 13).
    assert out["mean"].iloc[3] != pytest.approx(design.values[:, 3].mean(), rel=1e-6)


def test_marginal_means_refuse_unknown_by(dropouts: pd.DataFrame) -> None:
    with pytest.raises(InvalidInputError, match="by must be"):
        marginal_means(dropouts, **DKW, subject="participant", by="session")  # type: ignore[arg-type]
