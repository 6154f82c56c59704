"""Linear mixed models against lme4/lmerTest values and against the mixed ANOVA."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from analysis import lmm
from analysis.anova import mixed_anova
from analysis.descriptives import cell_descriptives
from analysis.errors import CannotComputeError, InvalidInputError
from analysis.lmm import fit_mixed_model, linear_mixed_models
from analysis.mixed_prose import comparison_sentence
from tests.analysis.conftest import DATA, make_mixed

KW = {"dv": "y", "within": "time", "between": "group", "subject": "subject"}


@pytest.fixture(scope="module")
def sleepstudy_fit() -> lmm.MixedModelFit:
    data = pd.read_csv(DATA / "sleepstudy.csv")
    return fit_mixed_model(data, formula="Reaction ~ Days", subject="Subject", re_formula="~Days")


def test_sleepstudy_matches_lme4(sleepstudy_fit: lmm.MixedModelFit) -> None:
    # lme4 1.1 / lmerTest 3.1: lmer(Reaction ~ Days + (Days | Subject), sleepstudy), REML.
    # Fixed 251.405 (SE 6.825, df 17.000, t 36.838), 10.467 (SE 1.546, df 17.000, t 6.771);
    # SDs 24.741, 5.922, corr .066, residual 25.592; REML criterion 1743.6.
    # The REML optimum itself is SD 24.7405 (lme4 prints 24.741 from its own stopping point),
    # so values are compared to within 0.001.
    fit = sleepstudy_fit
    assert fit.converged and fit.problem == ""
    fixed = fit.fixed.set_index("term")
    assert fixed.loc["Intercept", "estimate"] == pytest.approx(251.405, abs=1e-3)
    assert fixed.loc["Days", "estimate"] == pytest.approx(10.467, abs=1e-3)
    assert fixed.loc["Intercept", "se"] == pytest.approx(6.825, abs=1e-3)
    assert fixed.loc["Days", "se"] == pytest.approx(1.546, abs=1e-3)
    assert fixed.loc["Days", "t"] == pytest.approx(6.771, abs=1e-3)
    assert fixed.loc["Intercept", "t"] == pytest.approx(36.838, abs=1e-3)
    assert fixed["df"].to_numpy() == pytest.approx([17.0, 17.0], abs=0.01)
    assert fit.df_method == "Satterthwaite"
    variance = fit.variance.set_index("component")
    assert variance["sd"].to_numpy() == pytest.approx([24.741, 5.922, 25.592], abs=1e-3)
    assert variance.loc["Subject: Days", "corr"] == pytest.approx(0.066, abs=1e-3)
    assert -2 * fit.loglik == pytest.approx(1743.6, abs=0.05)


def test_random_intercept_reproduces_the_anova_f_on_balanced_data() -> None:
    data = make_mixed((9, 11), 4, seed=3, effect=0.4)
    result = linear_mixed_models(data, **KW, random_slope=False)
    anova = mixed_anova(data, **KW).table.set_index("effect")
    tests = result.intercept.tests.set_index("effect")
    for effect in ("between", "within", "interaction"):
        assert tests.loc[effect, "F"] == pytest.approx(anova.loc[effect, "F"], rel=1e-6)
        assert tests.loc[effect, "df1"] == anova.loc[effect, "DF1"]
        # Satterthwaite reproduces the ANOVA's error strata: N − 2 and (N − 2)(S − 1).
        assert tests.loc[effect, "df2"] == pytest.approx(anova.loc[effect, "DF2"], abs=1e-3)
        assert tests.loc[effect, "p"] == pytest.approx(anova.loc[effect, "p_unc"], abs=1e-6)
    assert result.kept.empty and result.slope is None and result.comparison is None


def test_marginal_means_of_balanced_data_are_the_cell_means() -> None:
    data = make_mixed((6, 6), 3, seed=5)
    fit = linear_mixed_models(data, **KW, random_slope=False).intercept
    cells = cell_descriptives(data, dv="y", within="time", between="group")
    merged = fit.emmeans.merge(cells[["group", "time", "mean"]], on=["group", "time"])
    assert len(merged) == 6
    assert merged["emmean"].to_numpy() == pytest.approx(merged["mean"].to_numpy(), abs=1e-8)
    assert (merged["ci_low"] < merged["emmean"]).all()
    assert (merged["emmean"] < merged["ci_high"]).all()


def test_a_participant_with_a_missing_session_is_kept_and_listed() -> None:
    data = pd.read_csv(DATA / "mixed_2x4_dropouts.csv")
    kw = {"dv": "trust", "within": "session", "between": "condition", "subject": "participant"}
    anova = mixed_anova(data, **kw)
    result = linear_mixed_models(data, **kw)
    partial = set(anova.excluded["subject"])
    assert partial, "the fixture has incomplete participants"
    assert set(result.kept["subject"]) == partial
    assert result.n_subjects == anova.n_subjects_used + len(partial)
    assert result.n_obs == int(data["trust"].notna().sum())
    assert result.kept["reason"].str.startswith("incomplete").all()


def test_random_slope_is_compared_with_a_boundary_lrt_and_aic() -> None:
    rng = np.random.default_rng(11)
    rows = []
    for i in range(40):
        intercept, slope = rng.normal(0, 1), rng.normal(0, 0.8)
        for t in range(4):
            rows.append((i, "AB"[i % 2], t + 1, intercept + slope * t + rng.normal(0, 0.3)))
    data = pd.DataFrame(rows, columns=["subject", "group", "time", "y"])
    result = linear_mixed_models(data, **KW)
    assert result.slope is not None and result.comparison is not None
    comparison = result.comparison
    assert comparison["df"] == 2
    assert comparison["chi2"] == pytest.approx(2 * (result.slope.loglik - result.intercept.loglik))
    assert comparison["p"] < 1e-6 and comparison["aic_slope"] < comparison["aic_intercept"]
    assert result.preferred is result.slope
    sd = result.slope.variance.set_index("component")["sd"]
    assert sd["subject: time_step"] == pytest.approx(0.8, abs=0.3)


def test_a_participant_variance_of_zero_is_reported_as_a_boundary_fit() -> None:
    rng = np.random.default_rng(2)
    noise = rng.normal(0, 1, size=(30, 3))
    noise -= noise.mean(axis=1, keepdims=True)  # every participant has the same mean
    rows = [(i, "AB"[i % 2], t + 1, noise[i, t]) for i in range(30) for t in range(3)]
    data = pd.DataFrame(rows, columns=["subject", "group", "time", "y"])
    fit = linear_mixed_models(data, **KW, random_slope=False).intercept
    assert fit.converged
    assert fit.variance.set_index("component").loc["subject: (Intercept)", "sd"] < 1e-3
    assert any("boundary (singular) fit" in note for note in fit.notes)
    assert "random-intercept variance is estimated at zero" in fit.status


def test_a_model_that_does_not_converge_says_so_in_one_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(lmm, "_GRADIENT_TOL", -1.0)  # no fit is ever close enough
    data = make_mixed((8, 8), 4, seed=1)
    result = linear_mixed_models(data, **KW)
    for fit in result.models:
        assert not fit.converged
        assert "did not converge" in fit.problem and "\n" not in fit.problem
        assert "bfgs" in fit.problem
        assert fit.fixed.empty and fit.tests.empty and fit.emmeans.empty
        assert fit.status == fit.problem
    assert result.comparison is None
    json.dumps(result.to_dict(), allow_nan=False)


def test_to_dict_is_json_without_nan() -> None:
    data = pd.read_csv(DATA / "mixed_2x4_dropouts.csv")
    kw = {"dv": "trust", "within": "session", "between": "condition", "subject": "participant"}
    payload = linear_mixed_models(data, **kw).to_dict()
    text = json.dumps(payload, allow_nan=False)
    assert '"Satterthwaite"' in text
    assert {m["name"] for m in payload["models"]} == {"random intercept", "random slope"}
    assert payload["kept_by_mixed_model"]


def test_bad_input_is_refused_with_a_clear_message() -> None:
    data = make_mixed((5, 5), 3)
    with pytest.raises(InvalidInputError, match="no column 'y'"):
        linear_mixed_models(data.drop(columns="y"), **KW)
    with pytest.raises(CannotComputeError, match="two or more levels"):
        linear_mixed_models(data[data["group"] == "G1"], **KW)
    with pytest.raises(CannotComputeError, match="two or more levels"):
        linear_mixed_models(data[data["time"] == 1], **KW)


def test_an_empty_cell_is_named_instead_of_a_rank_deficient_fit() -> None:
    data = make_mixed((6, 6), 4, seed=4)
    interim = data[~((data["group"] == "G2") & (data["time"] == 4))]
    with pytest.raises(CannotComputeError, match=r"no one has a rating in 1 cell\(s\) \(G2 × 4\)"):
        linear_mixed_models(interim, **KW)


def test_two_sessions_fit_no_random_slope_and_say_why() -> None:
    data = make_mixed((8, 8), 2, seed=6)
    result = linear_mixed_models(data, **KW, random_slope=True)
    assert result.slope is None and result.comparison is None
    assert "a random slope needs three or more levels of 'time'" in result.slope_skipped
    assert comparison_sentence(result).startswith("No random-slope model: a random slope needs")
    assert result.within_levels == (1, 2)


def test_text_levels_keep_their_numbers_in_order() -> None:
    data = make_mixed((5, 5), 3, seed=2)
    data["time"] = data["time"].map({1: "S1", 2: "S2", 3: "S10"})
    result = linear_mixed_models(data, **KW)
    assert result.within_levels == ("S1", "S2", "S10")  # not S1, S10, S2
    assert list(result.intercept.emmeans["time"][:3]) == ["S1", "S2", "S10"]


# --- boundary (singular) fits against lmerTest --------------------------------------------------
# R 4.2.2, lme4 1.1.31, lmerTest 3.1.3: tests/analysis/data/lmm_boundary.R fits each CSV with
# lmer(trust ~ condition * session_f + (1 | participant)) and (1 + step | participant), REML,
# contr.sum, and prints isSingular, logLik, VarCorr and anova(m, type = 3) (Satterthwaite).
# sd: participant SDs then the residual SD; corr: the intercept–slope correlation.
LMERTEST = {
    ("lmm_boundary_intercept", "random intercept"): {
        # the participant variance is estimated at zero: the model is OLS, df = 48 − 8 = 40
        "singular": True,
        "loglik": -38.33533776,
        "sd": [0.0, 0.4591581971],
        "F": [23.223003540, 2.146247996, 1.607178502],
        "df2": [40.0, 40.0, 40.0],
        "p": [2.103940894e-05, 1.095311676e-01, 2.028439823e-01],
        "coef_df": [40.0] * 8,  # summary(m): every coefficient's t test
    },
    ("lmm_boundary_intercept", "random slope"): {
        # the intercept–slope correlation at −1 (lme4's θ[2] = 3e-5, below isSingular's 1e-4)
        "singular": True,
        "loglik": -36.46167769,
        "sd": [0.2804424592, 0.2140849730, 0.3897176640],
        "corr": -0.9999999983,
        "F": [30.889525822, 1.454598475, 1.166821767],
        "df2": [24.53390212, 21.81094335, 21.81094335],
        "p": [9.457276521e-06, 2.544197762e-01, 3.450725867e-01],
    },
    ("lmm_boundary_slope", "random slope"): {
        # the correlation at +1, where statsmodels stops short (.99…, REML logLik 0.0012 lower)
        "singular": True,
        "loglik": -56.91137869,
        "sd": [0.59272337399, 0.02380859827, 0.58965294187],
        "corr": 1.0,
        "F": [0.2866797679, 1.5560727978, 1.5302657291],
        "df2": [10.00035813, 29.90702012, 29.90702012],
        "p": [0.6040582473, 0.2205982820, 0.2269775375],
    },
    ("lmm_flat_intercept", "random intercept"): {
        # statsmodels "converges" with the REML logLik 0.156 short of this optimum
        "singular": False,
        "loglik": -43.66933153,
        "sd": [0.08813338431, 0.51750765474],
        "F": [8.3729209569, 0.5141521109, 4.9096646547],
        "df2": [9.999998085, 29.999996731, 29.999996731],
        "p": [0.016008142266, 0.675654653436, 0.006813144557],
    },
    ("lmm_boundary_slope", "random intercept"): {
        "singular": False,
        "loglik": -56.9466944,
        "sd": [0.6282040119, 0.5905006110],
        "F": [0.2867046221, 1.5576093155, 1.5287394350],
        "df2": [9.999999923, 30.000000034, 30.000000034],
        "p": [0.6040431973, 0.2201565562, 0.2272935747],
    },
    ("lmm_flat_intercept", "random slope"): {
        # not on the boundary, but the session df depend on lmerTest's basis of the hypothesis
        "singular": False,
        "loglik": -43.58127133,
        "sd": [0.2242877781, 0.1034439553, 0.4999793401],
        "corr": -0.8929865261,
        "F": [8.372903498, 0.539108081, 4.587569458],
        "df2": [10.00001494, 22.31090032, 22.31090032],
        "p": [0.01600819865, 0.66040147435, 0.01201951801],
    },
}
STUDY = {"dv": "trust", "within": "session", "between": "condition", "subject": "participant"}


@pytest.fixture(scope="module")
def boundary_fits() -> dict[str, lmm.LinearMixedModels]:
    cases = {case for case, _ in LMERTEST}
    return {case: linear_mixed_models(pd.read_csv(DATA / f"{case}.csv"), **STUDY) for case in cases}


@pytest.mark.parametrize(("case", "model"), list(LMERTEST))
def test_boundary_fits_match_lmertest(
    boundary_fits: dict[str, lmm.LinearMixedModels], case: str, model: str
) -> None:
    expected = LMERTEST[(case, model)]
    result = boundary_fits[case]
    fit = result.intercept if model == "random intercept" else result.slope
    assert fit is not None and fit.converged
    assert fit.loglik == pytest.approx(expected["loglik"], abs=1e-5)
    assert fit.variance["sd"].to_numpy() == pytest.approx(expected["sd"], abs=1e-4)
    if "corr" in expected:
        assert fit.variance["corr"].iloc[1] == pytest.approx(expected["corr"], abs=1e-4)
    assert fit.tests["F"].to_numpy() == pytest.approx(expected["F"], rel=1e-4)
    assert fit.tests["df2"].to_numpy() == pytest.approx(expected["df2"], abs=0.01)
    assert fit.tests["p"].to_numpy() == pytest.approx(expected["p"], abs=1e-4)
    assert ("boundary (singular) fit" in fit.status) == expected["singular"]
    if "coef_df" in expected:
        assert fit.fixed["df"].to_numpy() == pytest.approx(expected["coef_df"], abs=0.01)


def test_a_fit_that_approaches_the_boundary_is_reported_on_it(
    boundary_fits: dict[str, lmm.LinearMixedModels],
) -> None:
    # lmerTest (as above): REML logLik −56.9466944 (intercept) and −56.91137869 (slope, singular)
    result = boundary_fits["lmm_boundary_slope"]
    assert result.slope is not None and result.comparison is not None
    assert (
        result.slope.status == "boundary (singular) fit: the intercept–slope correlation is +1.000"
    )
    assert result.comparison["chi2"] == pytest.approx(2 * (56.9466944 - 56.91137869), abs=1e-4)
    assert result.preferred is result.intercept


def _noiseless(per_session_change: bool) -> pd.DataFrame:
    """Each rating = its condition × session cell + the participant's level (+ their own
    linear change per session): nothing is left for the residual."""
    rng = np.random.default_rng(7)
    rows = []
    for i in range(10):
        level, change = rng.normal(0, 0.5), rng.normal(0, 0.2) * per_session_change
        for t in range(4):
            cell = 3 + (0.3 if i % 2 else -0.1) * t
            rows.append((i, "AB"[i % 2], t + 1, cell + level + change * t))
    return pd.DataFrame(rows, columns=["subject", "group", "time", "y"])


def test_data_without_residual_variation_are_refused_in_one_line() -> None:
    with pytest.raises(
        CannotComputeError, match="reproduce every value to rounding error"
    ) as caught:
        linear_mixed_models(_noiseless(per_session_change=False), **KW)
    assert "\n" not in str(caught.value)
    assert str(caught.value).startswith("the mixed model y ~ group * time + (1 | subject)")


def test_only_the_slope_model_is_refused_when_it_alone_leaves_no_residual() -> None:
    result = linear_mixed_models(_noiseless(per_session_change=True), **KW)
    assert result.intercept.converged and result.intercept.variance["sd"].iloc[-1] > 0.01
    assert result.slope is not None and not result.slope.converged
    assert "reproduce every value to rounding error (no residual variation)" in result.slope.problem
    assert result.slope.tests.empty and result.comparison is None
    assert result.preferred is result.intercept
    assert comparison_sentence(result) == (
        f"The random-slope comparison could not be made: {result.slope.problem}."
    )


def test_the_fit_needs_no_statsmodels() -> None:
    # The fit is lme4's profiled REML (analysis.reml); statsmodels' MixedLM, used before, cost
    # seconds to minutes at 1,000 participants and its import a second of every command's start.
    script = (
        "import sys, pandas as pd\n"
        "from analysis.lmm import fit_mixed_model, linear_mixed_models\n"
        f"data = pd.read_csv({str(DATA / 'mixed_2x4_dropouts.csv')!r})\n"
        "kw = dict(dv='trust', within='session', between='condition', subject='participant')\n"
        "result = linear_mixed_models(data, **kw, random_slope=True)\n"
        "assert result.slope is not None and result.slope.converged\n"
        "fit_mixed_model(pd.read_csv(" + repr(str(DATA / "sleepstudy.csv")) + "),\n"
        "    formula='Reaction ~ Days', subject='Subject', re_formula='~Days')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'statsmodels'))\n"
    )
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        check=True,
        cwd=root,
        env={**os.environ, "PYTHONPATH": str(root)},
    )
    assert done.stdout.strip() == "[]"
