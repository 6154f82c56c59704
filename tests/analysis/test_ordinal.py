"""Proportional-odds models against R's ordinal::clm and the Brant check's behaviour."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from statsmodels.miscmodels.ordinal_model import OrderedModel

from analysis.errors import CannotComputeError, InvalidInputError
from analysis.ordinal import brant_test, fit_proportional_odds, ordinal_model
from tests.analysis.conftest import DATA

KW = {"dv": "rating", "within": "session", "between": "condition", "subject": "participant"}


@pytest.fixture(scope="module")
def wine() -> pd.DataFrame:
    return pd.read_csv(DATA / "wine.csv")


def _wine_exog(wine: pd.DataFrame) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "tempwarm": (wine["temp"] == "warm").astype(float),
            "contactyes": (wine["contact"] == "yes").astype(float),
        }
    )


def test_wine_matches_r_ordinal_clm(wine: pd.DataFrame) -> None:
    # R ordinal 2019.12 (Christensen): summary(clm(rating ~ temp + contact, data = wine))
    # tempwarm 2.5031 (SE 0.5287), contactyes 1.5278 (0.4766); thresholds -1.3444 (0.5171),
    # 1.2508 (0.4379), 3.4669 (0.5978), 5.0064 (0.7309); logLik -86.49, AIC 184.98.
    fit = fit_proportional_odds(wine["rating"], _wine_exog(wine), check_po=False)
    coefficients = fit.coefficients.set_index("term")
    assert coefficients["estimate"].to_numpy() == pytest.approx([2.5031, 1.5278], abs=1e-3)
    assert coefficients["se"].to_numpy() == pytest.approx([0.5287, 0.4766], abs=1e-3)
    thresholds = fit.thresholds.set_index("threshold")
    assert list(thresholds.index) == ["1|2", "2|3", "3|4", "4|5"]
    assert thresholds["estimate"].to_numpy() == pytest.approx(
        [-1.3444, 1.2508, 3.4669, 5.0064], abs=1e-3
    )
    assert thresholds["se"].to_numpy() == pytest.approx([0.5171, 0.4379, 0.5978, 0.7309], abs=1e-3)
    assert fit.loglik == pytest.approx(-86.492, abs=1e-3)
    assert fit.aic == pytest.approx(184.98, abs=1e-2)
    assert fit.se_type == "model-based"


def test_cluster_robust_errors_agree_with_statsmodels_up_to_its_small_sample_factor(
    wine: pd.DataFrame,
) -> None:
    exog = _wine_exog(wine)
    ours = fit_proportional_odds(wine["rating"], exog, groups=wine["judge"], check_po=False)
    theirs = OrderedModel(pd.Categorical(wine["rating"], ordered=True), exog, distr="logit").fit(
        method="bfgs", disp=False, cov_type="cluster", cov_kwds={"groups": wine["judge"]}
    )
    # statsmodels also multiplies by (N − 1)/(N − K) (Stata's regress); we use G/(G − 1) only,
    # as Stata's ologit does.
    n, k = len(wine), len(theirs.params)
    expected = np.asarray(theirs.bse[:2]) / np.sqrt((n - 1) / (n - k))
    assert ours.coefficients["se"].to_numpy() == pytest.approx(expected, rel=1e-4)
    assert ours.se_type == "cluster-robust (9 clusters)"


def _simulated(po_holds: bool, n: int = 600, seed: int = 4) -> tuple[np.ndarray, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    x = rng.integers(0, 2, size=n).astype(float)
    if po_holds:
        latent = 1.0 * x + rng.logistic(size=n)
        codes = np.digitize(latent, [-1.0, 0.0, 1.0, 2.0])
    else:
        # x spreads the ratings out (both tails grow): slopes have opposite signs at the ends.
        latent = rng.logistic(size=n) * (1 + 1.5 * x)
        codes = np.digitize(latent, [-2.0, -0.5, 0.5, 2.0])
    return codes, pd.DataFrame({"x": x})


def test_brant_check_flags_a_violation_and_passes_proportional_data() -> None:
    codes, exog = _simulated(po_holds=False)
    table, skipped = brant_test(codes, exog)
    assert skipped == []
    assert table.iloc[0]["Source"] == "omnibus" and table.iloc[0]["df"] == 3
    assert table.iloc[0]["p"] < 1e-6
    codes, exog = _simulated(po_holds=True)
    table, _ = brant_test(codes, exog)
    assert table.iloc[0]["p"] > 0.01


def _study(seed: int = 3, n: int = 30) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        condition = "C1" if i % 2 else "C2"
        person = rng.normal(0, 0.7)
        for session in range(1, 5):
            value = 3 + 0.5 * (condition == "C2") + 0.2 * session + person + rng.normal(0, 0.7)
            rows.append((f"P{i}", condition, session, int(np.clip(np.round(value), 1, 5))))
    return pd.DataFrame(rows, columns=["participant", "condition", "session", "rating"])


def test_study_model_keeps_incomplete_participants_and_tests_each_term() -> None:
    data = _study()
    data = data.drop(index=data.index[(data["participant"] == "P3") & (data["session"] == 2)])
    fit = ordinal_model(data, **KW)
    assert fit.converged, fit.problem
    assert fit.n_obs == len(data) and fit.n_clusters == 30
    assert fit.se_type == "cluster-robust (30 clusters)"
    assert list(fit.tests["effect"]) == ["between", "within", "interaction"]
    assert list(fit.tests["df"]) == [1, 3, 3]
    terms = set(fit.coefficients["term"])
    assert {"condition[C1]", "session[1]", "condition[C1]:session[1]"} <= terms
    # C2 rates higher, so the C1 deviation is negative.
    c1 = fit.coefficients.set_index("term").loc["condition[C1]"]
    assert c1["estimate"] < 0 and c1["odds_ratio"] == pytest.approx(np.exp(c1["estimate"]))
    assert fit.po_problem == "" and fit.po_check.iloc[0]["Source"] == "omnibus"
    assert set(fit.po_check["Source"]) == {"omnibus", "condition", "session"}
    json.dumps(fit.to_dict(), allow_nan=False)


def test_study_model_refuses_averages_and_single_category_items() -> None:
    data = _study()
    averaged = data.assign(rating=data["rating"] + 0.5)
    with pytest.raises(InvalidInputError, match="not a whole-number rating"):
        ordinal_model(averaged, **KW)
    with pytest.raises(CannotComputeError, match="every rating is the same"):
        ordinal_model(data.assign(rating=4), **KW)
    with pytest.raises(CannotComputeError, match="two or more levels"):
        ordinal_model(data[data["condition"] == "C1"], **KW)
    interim = data[~((data["condition"] == "C1") & (data["session"] == 4))]
    with pytest.raises(CannotComputeError, match=r"1 cell\(s\) \(C1 × 4\)"):
        ordinal_model(interim, **KW)


def test_sparse_categories_are_named_in_the_po_check_notes() -> None:
    data = _study(seed=8, n=24)
    data.loc[data["rating"] == 1, "rating"] = 2
    data.loc[0, "rating"] = 1  # one lonely rating of 1: the 1|2 split is separated
    fit = ordinal_model(data, **KW)
    assert fit.converged and fit.po_problem == ""
    assert "the proportional-odds check leaves out the sparse cut-point(s) 1|2" in fit.notes
    assert fit.po_check.iloc[0]["df"] == 8  # 3 usable cuts → 2 differences × 4 slopes
