"""One analysis specification (issue 48, item 16): what ``trustlab prereg`` registers, what the
analysis fits and what the report describes derive from :mod:`analysis.specification`.

The sweep enumerates the specification's analyses, finds each one's fits in a fully analysed
multi-language study, and checks that the registered plan describes the same formulas and
covariates; a second sweep fails when a fitted result is added to the analysis objects without
an entry in the specification."""

from __future__ import annotations

import dataclasses
import html
import re

import pytest

from analysis.mixed_models import OutcomeMixedModels, StudyMixedModels, analyse_mixed_models
from analysis.prereg import check_registration, registered_plan
from analysis.report import build_report
from analysis.specification import analysis_specification, study_covariates
from analysis.study import OutcomeAnalysis, StudyAnalysis, analyse_study
from analysis.synthetic import synthetic_study
from app.services.analysis_views.mixed_view import mixed_view

NOT_FITS = {
    "OutcomeAnalysis": {
        "key",
        "label",
        "instrument",
        "kind",
        "value_range",
        "reverse_keyed",
        "data",
        "problem",
        "descriptives",
        "excluded",
        # read off the ANOVA's design (its marginal means and sentences), not fits of their own
        "marginal_conditions",
        "marginal_sessions",
        "sentences",
    },
    "OutcomeMixedModels": {
        "key",
        "label",
        "lmm_problem",
        "ordinal_problem",
        "adaptation_problem",
        "anova_excluded",
        "covariates",
        "covariates_left_out",
    },
}
"""Fields of the per-measure results that are not fits (data, labels, problems, notes). A new
field must be added here or be the ``result`` of a planned analysis."""

FITTED = {"OutcomeAnalysis": OutcomeAnalysis, "OutcomeMixedModels": OutcomeMixedModels}


@pytest.fixture(scope="module")
def fitted() -> tuple[StudyAnalysis, StudyMixedModels]:
    """The seed paper's study run in English and Swedish, every model fitted."""
    study = synthetic_study(16, seed=4)
    languages = ["en", "en", "sv", "sv"] * 4  # conditions alternate: not confounded
    dataset = dataclasses.replace(
        study,
        protocol={**study.protocol, "languages": ["en", "sv"]},
        participants=study.participants.assign(language=languages),
    )
    plan = registered_plan(dataset)
    dataset = dataclasses.replace(
        dataset, registration={"created_at": "2025-01-01T00:00:00", "analysis_plan": plan}
    )
    result = analyse_study(dataset)
    return result, analyse_mixed_models(result, keys=["trust_1", "trust_2"])


def test_every_fitted_result_is_a_planned_analysis() -> None:
    """Adding e.g. ``bayes: BayesFit | None`` to OutcomeMixedModels without a PlannedAnalysis
    whose ``result`` names it fails here."""
    planned = {a.result for a in analysis_specification({})}
    for name, cls in FITTED.items():
        for field in dataclasses.fields(cls):
            where = f"{name}.{field.name}"
            assert where in planned or field.name in NOT_FITS[name], (
                f"{where} is neither a planned analysis (analysis.specification) nor declared "
                "not a fit in NOT_FITS"
            )
    for where in planned:  # and every planned analysis lands in a field that exists
        cls_name, attribute = where.split(".")
        assert attribute in {f.name for f in dataclasses.fields(FITTED[cls_name])}


def test_the_registered_plan_describes_what_each_analysis_fits(
    fitted: tuple[StudyAnalysis, StudyMixedModels],
) -> None:
    result, mixed = fitted
    specification = analysis_specification(result.dataset.protocol)
    assert study_covariates(result.dataset.protocol) == ("language",)
    registered = {a["name"]: a for a in registered_plan(result.dataset)["analyses"]}
    assert list(registered) == [a.name for a in specification]
    outcomes = {o.key: o for o in result.outcomes}
    seen = set()
    for analysis in specification:
        entry = registered[analysis.name]
        assert entry["formulas"] == list(analysis.formulas)
        assert entry["covariates"] == list(analysis.covariates)
        owner, attribute = analysis.result.split(".")
        for models in mixed.outcomes:
            holder = outcomes[models.key] if owner == "OutcomeAnalysis" else models
            fit = getattr(holder, attribute)
            assert fit is not None, f"{analysis.name} of {models.key} was not fitted"
            seen.add(analysis.name)
            expected = [f.replace("{dv}", models.key) for f in entry["formulas"]]
            if analysis.name == "lmm":
                assert models.covariates == tuple(entry["covariates"]) == ("language",)
                assert [m.formula for m in fit.models] == expected
                assert "language" in set(fit.intercept.tests["Source"])
            elif analysis.name == "ordinal":
                assert [fit.formula] == expected
            elif analysis.name == "adaptation_trust":
                allowed = set(_terms(expected[0]))
                for measure, model in fit.fits.items():
                    terms = _terms(model.formula)
                    planned = {t.replace("{measure}", measure) for t in allowed}
                    assert set(terms) <= planned, (measure, model.formula)
            elif analysis.name == "mixed_anova":
                design = fit.design
                assert (design.between, design.within) == ("condition", "session")
                assert expected == [f"{models.key} ~ condition * session (complete cases)"]
            else:
                assert analysis.name == "posthoc" and len(fit)
    assert seen == {a.name for a in specification}
    check = check_registration(result.dataset.registration or {}, result, mixed=mixed)
    assert check.deviations == []


def _terms(formula: str) -> list[str]:
    rhs = formula.split("~", 1)[1]
    return [t.strip() for t in re.split(r" \+ (?![^(]*\))", rhs)]


def test_the_report_describes_the_specified_models(
    fitted: tuple[StudyAnalysis, StudyMixedModels],
) -> None:
    result, mixed = fitted
    page = build_report(result, mixed=mixed)
    for analysis in analysis_specification(result.dataset.protocol):
        if analysis.result.startswith("OutcomeMixedModels."):
            assert html.escape(analysis.description) in page
    assert "<strong>As registered.</strong>" in page


def test_a_registration_without_the_covariate_is_a_deviation(
    fitted: tuple[StudyAnalysis, StudyMixedModels],
) -> None:
    """What the issue found: the plan registered without ``language``, the models fitted with
    it — the report must not say "As registered"."""
    result, mixed = fitted
    english = {**result.dataset.protocol, "languages": ["en"]}
    plan = registered_plan(dataclasses.replace(result.dataset, protocol=english))
    check = check_registration({"analysis_plan": plan}, result, mixed=mixed)
    assert "linear mixed models: registered covariates none, fitted language" in check.deviations
    # and a covariate the models of a measure had to leave out is named too
    one = dataclasses.replace(
        result.dataset, participants=result.dataset.participants.assign(language="sv")
    )
    again = analyse_study(one)
    left = analyse_mixed_models(again, keys=["trust_1"], random_slope=False)
    deviations = check_registration(
        {"analysis_plan": registered_plan(one)}, again, mixed=left
    ).deviations
    assert deviations == [
        "linear mixed models: the random-slope model was not fitted",
        "trust_1: the linear mixed models left out the registered covariate language (every "
        "participant who rated it has the same language (sv))",
    ]
    # a report without its mixed models fitted none of the registered ones
    assert (
        "linear mixed models: registered, not fitted in this report"
        in check_registration({"analysis_plan": registered_plan(one)}, again).deviations
    )


def test_the_report_and_the_page_say_which_covariate_a_measure_left_out(
    fitted: tuple[StudyAnalysis, StudyMixedModels],
) -> None:
    result, _ = fitted
    one = dataclasses.replace(
        result.dataset, participants=result.dataset.participants.assign(language="sv")
    )
    again = analyse_study(one)
    left = analyse_mixed_models(again, keys=["trust_1"], random_slope=False)
    sentence = (
        "The linear mixed models leave out the specified covariate language: every participant "
        "who rated it has the same language (sv)."
    )
    assert html.escape(sentence) in build_report(again, mixed=left)
    view = mixed_view(again, left.outcome("trust_1"), random_slope=False)
    assert sentence in view.lmm_sentences
