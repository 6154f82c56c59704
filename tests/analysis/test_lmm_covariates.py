"""A participant-level covariate in the linear mixed model (a study run in several languages):
type III F tests with Satterthwaite df and the estimated marginal means, against lmerTest and
emmeans on the same data (tests/analysis/data/lmm_language_covariate.R), and the refusals."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pandas as pd
import pytest

from analysis.errors import InvalidInputError
from analysis.exports.tables import long_table
from analysis.lmm import linear_mixed_models
from analysis.mixed_models import analyse_mixed_models
from analysis.study import analyse_study
from analysis.synthetic import synthetic_study

DATA = Path(__file__).parent / "data" / "lmm_language_covariate.csv"

R_TESTS = {  # effect: (F, numerator df, denominator df, p) from anova(m, type = 3)
    "condition": (1.31035, 1, 19.99999986, 0.2658456),
    "session": (4.62574, 3, 66.00000005, 0.0053611),
    "language": (0.63336, 2, 19.99999986, 0.5411192),
    "condition × session": (1.70484, 3, 66.00000005, 0.1745358),
}
R_EMMEANS = [  # condition, session, emmean, SE, df (averaged over the languages)
    ("C1", 1, 2.994750, 0.22885317, 31.97),
    ("C2", 1, 3.165167, 0.22885317, 31.97),
    ("C1", 2, 3.002333, 0.22885317, 31.97),
]


def _fit(data: pd.DataFrame, covariates: tuple[str, ...] = ("language",)):  # type: ignore[no-untyped-def]
    return linear_mixed_models(
        data,
        dv="trust",
        within="session",
        between="condition",
        subject="participant",
        random_slope=False,
        covariates=covariates,
    )


def test_a_language_covariate_matches_lmertest_and_emmeans() -> None:
    fit = _fit(pd.read_csv(DATA)).intercept
    tests = fit.tests.set_index("Source")
    for source, (f, df1, df2, p) in R_TESTS.items():
        row = tests.loc[source]
        assert row["F"] == pytest.approx(f, abs=1e-4), source
        assert row["df1"] == df1
        assert row["df2"] == pytest.approx(df2, abs=1e-3), source
        assert row["p"] == pytest.approx(p, abs=1e-6), source
    assert fit.formula.startswith("trust ~ condition * session + language")
    emmeans = fit.emmeans.set_index(["condition", "session"])
    for condition, session, mean, se, df in R_EMMEANS:
        cell = emmeans.loc[(condition, session)]
        assert cell["emmean"] == pytest.approx(mean, abs=1e-5)
        assert cell["se"] == pytest.approx(se, abs=1e-5)
        assert cell["df"] == pytest.approx(df, abs=0.01)


def test_the_covariate_changes_the_model() -> None:
    """Without it, the language's variance goes to the participants' and the F tests move."""
    data = pd.read_csv(DATA)
    with_it, without = _fit(data).intercept, _fit(data, ()).intercept
    assert "language" not in set(without.tests["Source"])
    assert with_it.n_params == without.n_params + 2


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda d: d.drop(columns="language"), "no covariate column 'language'"),
        (lambda d: d.assign(language="en"), "covariate 'language' has one level"),
        (
            lambda d: d.assign(language=[("en", "sv")[i % 2] for i in range(len(d))]),
            "must have one value per participant",
        ),
        (lambda d: d.assign(language=None), "covariate 'language' has missing values"),
    ],
    ids=["absent", "one-level", "varies-within", "missing"],
)
def test_a_covariate_the_model_cannot_use_is_refused(change, reason: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InvalidInputError, match=reason):
        _fit(change(pd.read_csv(DATA)))


def test_a_study_run_in_several_languages_adjusts_its_mixed_models_for_language() -> None:
    """The protocol's languages decide the covariate (analysis.specification), as registered:
    a study in three languages adjusts for language; when everyone who rated used one of them
    the models cannot, and say which covariate they left out and why; a study in one language
    has no language term whatever the participants' column holds."""
    study = synthetic_study(24, seed=3)
    protocol = {**study.protocol, "languages": ["en", "sv", "de"]}
    languages = ["en", "sv", "de"] * 8
    several = dataclasses.replace(
        study, protocol=protocol, participants=study.participants.assign(language=languages)
    )
    fitted = analyse_mixed_models(analyse_study(several), keys=["trust_1"], random_slope=False)
    lmm = fitted.outcome("trust_1").lmm
    assert lmm is not None and "language" in set(lmm.intercept.tests["Source"])
    assert fitted.outcome("trust_1").covariates == ("language",)
    one = dataclasses.replace(several, participants=study.participants.assign(language="en"))
    plain = analyse_mixed_models(analyse_study(one), keys=["trust_1"], random_slope=False)
    single = plain.outcome("trust_1").lmm
    assert single is not None and "language" not in set(single.intercept.tests["Source"])
    assert plain.outcome("trust_1").covariates_left_out == {
        "language": "every participant who rated it has the same language (en)"
    }
    english = dataclasses.replace(
        study,
        protocol={**study.protocol, "languages": ["en"]},
        participants=study.participants.assign(language=languages),
    )
    unplanned = analyse_mixed_models(analyse_study(english), keys=["trust_1"], random_slope=False)
    assert unplanned.outcome("trust_1").covariates == ()
    assert unplanned.outcome("trust_1").covariates_left_out == {}


def test_a_multi_site_study_adjusts_its_mixed_models_for_site_and_exports_it() -> None:
    """The site is a participant attribute like the language: the linear mixed models add it
    as a sum-coded fixed effect when the analysed participants come from several sites, and the
    long table carries it in every row."""
    study = synthetic_study(24, seed=3)  # conditions alternate: sites by pairs, not confounded
    several = dataclasses.replace(
        study,
        protocol={**study.protocol, "languages": ["en"], "sites": ["kth", "uu"]},
        participants=study.participants.assign(language="en", site=["kth", "kth", "uu", "uu"] * 6),
    )
    fitted = analyse_mixed_models(analyse_study(several), keys=["trust_1"], random_slope=False)
    lmm = fitted.outcome("trust_1").lmm
    assert lmm is not None and "site" in set(lmm.intercept.tests["Source"])
    assert "language" not in set(lmm.intercept.tests["Source"])  # one language: no term
    long = long_table(several)
    assert list(long.columns[:4]) == ["participant", "condition", "language", "site"]
    sites = dict(
        zip(several.participants["participant"], several.participants["site"], strict=True)
    )
    assert (long["site"] == long["participant"].map(sites)).all()
    # the same model from the exported long file, as `trustlab mixed --covariate site` fits it
    scored = long[long["item"] == "trust_1"].rename(columns={"scored": "trust_1"})
    refit = linear_mixed_models(
        scored,
        dv="trust_1",
        within="session",
        between="condition",
        subject="participant",
        random_slope=False,
        covariates=("site",),
    )
    site_test = refit.intercept.tests.set_index("Source").loc["site"]
    assert site_test["F"] == pytest.approx(
        lmm.intercept.tests.set_index("Source").loc["site"]["F"], rel=1e-6
    )
