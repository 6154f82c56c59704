"""The linear mixed models against lmerTest at full precision: estimates, SEs, Satterthwaite df,
t and F tests, p values, variance components and marginal means, to 1e-5 relative.

Reference values: tests/analysis/data/lmm_lmertest.json, written by lmm_lmertest.R (R 4.2.2,
lme4 1.1.31, lmerTest 3.1.3) for five data sets × two models: boundary fits (a participant
variance of zero, correlations of −1 and +1), a flat likelihood, unbalanced data with missing
sessions (mixed_2x4_dropouts, and 95 synthetic participants of whom 7 missed sessions).
lme4 fits each model twice: with its default optimiser settings, which stop up to 4e-5 (relative)
away from the REML optimum on flat likelihoods (and, on mixed_2x4_dropouts' random-slope model,
at a saddle point lme4 itself reports as not converged), and with tolerances tightened to the
optimum's own precision. trustlab must equal the second to 1e-5 and never find a worse
likelihood than the first.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pandas as pd
import pytest

from analysis.lmm import LinearMixedModels, MixedModelFit, linear_mixed_models
from tests.analysis.conftest import DATA

REFERENCE = json.loads((DATA / "lmm_lmertest.json").read_text())
STUDY = {"dv": "trust", "within": "session", "between": "condition", "subject": "participant"}
REL = 1e-5
"""The tolerance the issue asks for (issue 49): relative to lmerTest's value."""


def _cases(optimizer: str) -> list[dict[str, Any]]:
    return [r for r in REFERENCE if r["optimizer"] == optimizer]


@pytest.fixture(scope="module")
def fits() -> dict[str, LinearMixedModels]:
    cases = {r["case"] for r in REFERENCE}
    return {case: linear_mixed_models(pd.read_csv(DATA / f"{case}.csv"), **STUDY) for case in cases}


def _fit(fits: dict[str, LinearMixedModels], reference: dict[str, Any]) -> MixedModelFit:
    result = fits[reference["case"]]
    fit = result.intercept if reference["model"] == "intercept" else result.slope
    assert fit is not None and fit.converged, fit
    return fit


def _same(ours: Any, theirs: Any) -> None:
    """Equal to ``REL`` relative; a value lmerTest gives as exactly zero (a variance on the
    boundary) to 1e-7 absolute."""
    ours = np.atleast_1d(np.asarray(ours, float))
    theirs = np.atleast_1d(np.asarray(theirs, float))
    assert ours.shape == theirs.shape
    zero = theirs == 0
    assert ours[~zero] == pytest.approx(theirs[~zero], rel=REL, abs=0)
    assert np.all(np.abs(ours[zero]) < 1e-7)


@pytest.mark.parametrize("reference", _cases("tight"), ids=lambda r: f"{r['case']}-{r['model']}")
def test_every_number_equals_lmertest(
    fits: dict[str, LinearMixedModels], reference: dict[str, Any]
) -> None:
    fit = _fit(fits, reference)
    assert fit.loglik == pytest.approx(reference["loglik"], rel=1e-9)
    assert ("boundary (singular) fit" in fit.status) == reference["singular"]
    _same(fit.variance["sd"], reference["sd"])
    if reference["model"] == "slope":
        _same(fit.variance["corr"].iloc[1], reference["corr"])
    fixed = reference["fixed"]
    for column in ("estimate", "se", "df", "t", "p"):
        _same(fit.fixed[column], fixed[column])
    tests = reference["tests"]
    assert list(fit.tests["effect"]) == ["between", "within", "interaction"]
    for ours, theirs in (("F", "F"), ("df1", "df1"), ("df2", "df2"), ("p", "p")):
        _same(fit.tests[ours], tests[theirs])
    emmeans = reference["emmeans"]
    assert list(fit.emmeans["condition"]) == emmeans["condition"]
    assert [str(s) for s in fit.emmeans["session"]] == emmeans["session"]
    for column in ("emmean", "se", "df"):
        _same(fit.emmeans[column], emmeans[column])


@pytest.mark.parametrize("reference", _cases("default"), ids=lambda r: f"{r['case']}-{r['model']}")
def test_the_likelihood_is_never_below_lme4s_default_fit(
    fits: dict[str, LinearMixedModels], reference: dict[str, Any]
) -> None:
    fit = _fit(fits, reference)
    assert fit.loglik >= reference["loglik"] - 1e-9
    if reference["converged"]:  # lme4 stopped at the optimum, to its default tolerance
        assert fit.loglik == pytest.approx(reference["loglik"], rel=1e-9)
        _same(fit.fixed["estimate"], reference["fixed"]["estimate"])


def test_lme4s_default_fit_of_the_dropouts_slope_model_is_a_saddle_point(
    fits: dict[str, LinearMixedModels],
) -> None:
    # lme4 1.1.31 with its defaults warns "Model failed to converge: degenerate Hessian with 1
    # negative eigenvalues" at REML logLik −119.7032; tightened, it reaches −119.6835, as we do.
    (default,) = [
        r for r in _cases("default") if (r["case"], r["model"]) == ("mixed_2x4_dropouts", "slope")
    ]
    assert not default["converged"] and "negative eigenvalue" in default["messages"]
    fit = _fit(fits, default)
    assert fit.loglik - default["loglik"] == pytest.approx(0.0196, abs=1e-4)
