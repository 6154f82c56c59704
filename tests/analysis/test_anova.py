"""Mixed ANOVA against R (afex/car), JASP/JAMOVI-checked pingouin values and statsmodels."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pingouin as pg
import pytest

from analysis.anova import ANOVA_COLUMNS, mixed_anova, orthonormal_contrasts
from analysis.errors import CannotComputeError, DuplicateObservationError, InvalidInputError
from tests.analysis.conftest import load_reference, make_mixed

CASES = ["pingouin_mixed_anova", "pingouin_mixed_anova_unbalanced"]
KW = {"dv": "dv", "within": "within", "between": "between", "subject": "subject"}


def _close(actual: float, expected: float, tol: float | str) -> bool:
    if isinstance(tol, str):
        rel = float(tol.split(":")[1])
        return math.isclose(actual, expected, rel_tol=rel, abs_tol=0.0)
    return abs(actual - expected) <= tol + 1e-12


# ---------------------------------------------------------------- R afex 1.2-1 / car 3.1-1


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("ss_type", [2, 3])
def test_matches_r_afex_type_2_and_3(case: str, ss_type: int) -> None:
    # Expected: R 4.2.2, afex 1.2-1 aov_ez(type=2|3) / car 3.1-1 Anova (reference r/<case>.json).
    data, _, r_values = load_reference(case)
    ref = r_values[f"type{ss_type}"]
    result = mixed_anova(data, **KW, ss_type=ss_type)  # type: ignore[arg-type]
    table = result.table.set_index("effect")
    assert result.ss_type == ss_type
    assert result.n_subjects_used == ref["n_subjects"]
    for i, effect in enumerate(["between", "within", "interaction"]):
        row = table.loc[effect]
        assert row["DF1"] == ref["num_df"][i]
        assert row["DF2"] == ref["den_df"][i]
        for col, key in [("F", "F"), ("p_unc", "p"), ("np2", "pes"), ("ng2", "ges")]:
            assert row[col] == pytest.approx(ref[key][i], rel=1e-6), (effect, col)
        if effect != "between":
            assert row["p_GG_corr"] == pytest.approx(ref["p_GG"][i], rel=1e-6)
            assert row["eps"] == pytest.approx(ref["pval_adj"]["GG eps"][i - 1], rel=1e-6)
    sph = result.sphericity
    assert sph.W == pytest.approx(ref["mauchly"]["Test statistic"][0], rel=1e-6)  # noqa: SIM300
    assert sph.p == pytest.approx(ref["mauchly"]["p-value"][0], rel=1e-6)


# ------------------------------------------- expected.json (pingouin tests, JASP/JAMOVI, R)

_KEYS = {
    "F_{e}": ("F", "{e}"),
    "p_{e}": ("p_unc", "{e}"),
    "np2_{e}": ("np2", "{e}"),
    "ng2_{e}": ("ng2", "{e}"),
    "df1_{e}": ("DF1", "{e}"),
    "df2_{e}": ("DF2", "{e}"),
}


@pytest.mark.parametrize("case", CASES)
def test_matches_expected_json_within_its_tolerances(case: str) -> None:
    # expected.json values are type II (pingouin's published results, checked against JASP /
    # JAMOVI / ez::ezANOVA) and R afex 1.2-1; tolerances as declared in the file.
    data, expected, _ = load_reference(case)
    tol = expected["tolerance"]
    result = mixed_anova(data, **KW, ss_type=2)
    table = result.table.set_index("effect")
    checked = 0
    for effect in ["between", "within", "interaction"]:
        for pattern, (col, _) in _KEYS.items():
            key = pattern.format(e=effect)
            assert _close(float(table.loc[effect, col]), expected[key], tol[key]), key
            checked += 1
    for key, actual in [
        ("W_spher", result.sphericity.W),
        ("p_spher", result.sphericity.p),
        ("eps_GG", result.sphericity.eps_gg),
        ("p_GG_within", table.loc["within", "p_GG_corr"]),
        ("p_GG_interaction", table.loc["interaction", "p_GG_corr"]),
        ("n_subjects_used", result.n_subjects_used),
    ]:
        assert actual is not None
        assert _close(float(actual), expected[key], tol[key]), key
        checked += 1
    assert checked == 24


def test_unbalanced_type_3_within_differs_from_type_2() -> None:
    # expected.json notes: "afex/SPSS/JASP default type III gives F_within=1.539138, p=0.212157".
    data, _, _ = load_reference("pingouin_mixed_anova_unbalanced")
    t3 = mixed_anova(data, **KW).effect("within")
    t2 = mixed_anova(data, **KW, ss_type=2).effect("within")
    assert t3["F"] == pytest.approx(1.539138, abs=5e-7)
    assert t3["p_unc"] == pytest.approx(0.212157, abs=5e-7)
    assert t2["F"] == pytest.approx(1.707059, abs=5e-7)
    assert mixed_anova(data, **KW).ss_type == 3  # the default


# ------------------------------------------------ own case: 2 × 4, unbalanced, with dropouts

# Expected values derived WITHOUT analysis.anova by tests/analysis/data/
# derive_mixed_2x4_dropouts.py:
#   type III: statsmodels 0.15.0 OLS model comparison (participant dummies + sum-to-zero coded
#             session and session × condition; between stratum = OLS of participant means on a
#             sum-to-zero condition code); p from scipy 1.17.1 F.sf(F, df1, df2).
#   type II and sphericity: pingouin 0.7.0 mixed_anova(correction=True) on the complete cases.
#   type III GG p: scipy F.sf(F_III, 3ε, 60ε) with pingouin's ε.
# Order: F, df1, df2, p, np2, ng2.
DROPOUT_T3 = {
    "between": (
        0.8938605798719672, 1, 20, 0.3557164068669386, 0.042781015813471296, 0.03097804263380968
    ),
    "within": (
        0.11969754413491146, 3, 60, 0.9481789718118405, 0.005949271547066793, 0.0017010714636314845
    ),
    "interaction": (
        6.517267477394716, 3, 60, 0.0006867535887555387, 0.24577447442314776, 0.08490055897960147
    ),
}  # fmt: skip
DROPOUT_T2_WITHIN = (0.207842935968, 0.890584473362, 0.010285260858, 0.002950046762, 0.853119761939)
DROPOUT_SPHERICITY = (0.711767292754, 0.272826767131, 0.812438064101)
DROPOUT_P_GG = {"within": 0.9204052563890666, "interaction": 0.001723718202}
DKW = {"dv": "trust", "within": "session", "between": "condition", "subject": "participant"}


def test_own_2x4_dropouts_type_3(dropouts: pd.DataFrame) -> None:
    result = mixed_anova(dropouts, **DKW)
    table = result.table.set_index("effect")
    for effect, (f, df1, df2, p, np2, ng2) in DROPOUT_T3.items():
        row = table.loc[effect]
        assert (row["DF1"], row["DF2"]) == (df1, df2)
        assert row["F"] == pytest.approx(f, rel=1e-9)
        assert row["p_unc"] == pytest.approx(p, rel=1e-9)
        assert row["np2"] == pytest.approx(np2, rel=1e-9)
        assert row["ng2"] == pytest.approx(ng2, rel=1e-9)
    for effect, p_gg in DROPOUT_P_GG.items():
        assert table.loc[effect, "p_GG_corr"] == pytest.approx(p_gg, rel=1e-9)
    w, p, eps = DROPOUT_SPHERICITY
    sph = result.sphericity
    assert sph.W == pytest.approx(w, abs=1e-11)  # noqa: SIM300
    assert sph.p == pytest.approx(p, abs=1e-11)
    assert sph.eps_gg == pytest.approx(eps, abs=1e-11)


def test_own_2x4_dropouts_type_2(dropouts: pd.DataFrame) -> None:
    row = mixed_anova(dropouts, **DKW, ss_type=2).effect("within")
    f, p, np2, ng2, p_gg = DROPOUT_T2_WITHIN
    assert row["F"] == pytest.approx(f, abs=1e-11)
    assert row["p_unc"] == pytest.approx(p, abs=1e-11)
    assert row["np2"] == pytest.approx(np2, abs=1e-11)
    assert row["ng2"] == pytest.approx(ng2, abs=1e-11)
    assert row["p_GG_corr"] == pytest.approx(p_gg, abs=1e-11)


def test_own_2x4_dropouts_exclusions_listed_with_reason(dropouts: pd.DataFrame) -> None:
    result = mixed_anova(dropouts, **DKW)
    assert result.n_subjects_used == 22
    excluded = result.excluded.set_index("subject")
    assert list(excluded.index) == ["P103", "P110", "P120"]
    assert excluded.loc["P103", "between"] == "C1"
    assert "session 3, 4" in excluded.loc["P103", "reason"]
    assert "session 4 " in excluded.loc["P110", "reason"]
    assert "session 2 " in excluded.loc["P120", "reason"]  # a NaN value, not a missing row


# ------------------------------------------------------- live cross-checks on random data


def _statsmodels_type3_within(df: pd.DataFrame) -> float:
    """Type III within F by OLS model comparison (see derive_mixed_2x4_dropouts.py)."""
    import statsmodels.api as sm

    from tests.analysis.data.derive_mixed_2x4_dropouts import sum_codes

    y = df["y"].to_numpy()
    subj = pd.get_dummies(df["subject"]).to_numpy(float)
    w = sum_codes(df["time"])
    b = sum_codes(df["group"])
    wb = np.hstack([w * b[:, [j]] for j in range(b.shape[1])])
    full = sm.OLS(y, np.hstack([subj, w, wb])).fit()
    reduced = sm.OLS(y, np.hstack([subj, wb])).fit()
    return ((reduced.ssr - full.ssr) / w.shape[1]) / (full.ssr / full.df_resid)


@pytest.mark.filterwarnings("ignore:The inplace keyword")  # pingouin 0.7.0 on pandas 3
@pytest.mark.parametrize(
    ("sizes", "n_levels", "seed"),
    [((5, 9), 3, 1), ((4, 6, 11), 4, 2), ((12, 3), 5, 3), ((7, 7, 7), 3, 4), ((3, 8), 2, 5)],
)
def test_cross_check_pingouin_and_statsmodels(
    sizes: tuple[int, ...], n_levels: int, seed: int
) -> None:
    # Cross-check with pingouin 0.7.0 (type II) and statsmodels 0.15.0 OLS (type III).
    df = make_mixed(sizes, n_levels, seed)
    kw = {"dv": "y", "within": "time", "between": "group", "subject": "subject"}
    ours2 = mixed_anova(df, **kw, ss_type=2).table
    ref = pg.mixed_anova(data=df, correction=True, **kw)
    np.testing.assert_allclose(ours2["F"], ref["F"], rtol=1e-9)
    np.testing.assert_allclose(ours2["p_unc"], ref["p_unc"], rtol=1e-9)
    np.testing.assert_allclose(ours2["np2"], ref["np2"], rtol=1e-9)
    np.testing.assert_allclose(ours2["eps"][1:], ref["eps"][1:], rtol=1e-9)
    if n_levels > 2:
        np.testing.assert_allclose(ours2["p_GG_corr"][1:], ref["p_GG_corr"][1:], rtol=1e-9)
        np.testing.assert_allclose(ours2["W_spher"][1:], ref["W_spher"][1:], rtol=1e-9)
        np.testing.assert_allclose(ours2["p_spher"][1:], ref["p_spher"][1:], rtol=1e-9)
    ours3 = mixed_anova(df, **kw, ss_type=3).effect("within")
    assert ours3["F"] == pytest.approx(_statsmodels_type3_within(df), rel=1e-9)


def test_type_2_equals_type_3_for_equal_groups() -> None:
    df = make_mixed((6, 6, 6), 4, seed=9)
    kw = {"dv": "y", "within": "time", "between": "group", "subject": "subject"}
    t2 = mixed_anova(df, **kw, ss_type=2).table
    t3 = mixed_anova(df, **kw, ss_type=3).table
    np.testing.assert_allclose(t2["F"], t3["F"], rtol=1e-12)
    assert set(t3["ss_type"]) == {3}
    assert set(t2["ss_type"]) == {2}


def test_results_do_not_depend_on_row_order_or_labels() -> None:
    df = make_mixed((5, 8), 4, seed=11)
    kw = {"dv": "y", "within": "time", "between": "group", "subject": "subject"}
    base = mixed_anova(df, **kw).table
    shuffled = df.sample(frac=1.0, random_state=3)
    shuffled["subject"] = "s" + shuffled["subject"].astype(str)
    np.testing.assert_allclose(mixed_anova(shuffled, **kw).table["F"], base["F"], rtol=1e-12)
    scaled = df.assign(y=df["y"] * 7 + 3)
    np.testing.assert_allclose(mixed_anova(scaled, **kw).table["F"], base["F"], rtol=1e-9)


def test_orthonormal_contrasts() -> None:
    c = orthonormal_contrasts(5)
    np.testing.assert_allclose(c.T @ c, np.eye(4), atol=1e-14)
    np.testing.assert_allclose(np.ones(5) @ c, np.zeros(4), atol=1e-14)


# ----------------------------------------------------------------- shape of the result


def test_table_always_has_every_column_even_with_two_levels() -> None:
    df = make_mixed((5, 6), 2, seed=2)
    result = mixed_anova(df, dv="y", within="time", between="group", subject="subject")
    assert tuple(result.table.columns) == ANOVA_COLUMNS
    within = result.effect("within")
    assert within["eps"] == 1.0
    assert within["W_spher"] == 1.0
    assert within["p_spher"] == 1.0
    assert within["p_GG_corr"] == pytest.approx(within["p_unc"], rel=1e-12)
    assert result.table[["F", "p_unc", "np2", "ng2"]].notna().all().all()


def test_to_dict_is_the_cli_contract(dropouts: pd.DataFrame) -> None:
    out = mixed_anova(dropouts, **DKW).to_dict()
    json.dumps(out, allow_nan=False)
    assert set(out) == {"ss_type", "n_subjects_used", "excluded_subjects", "effects", "sphericity"}
    assert out["ss_type"] == 3
    assert out["n_subjects_used"] == 22
    assert [e["subject"] for e in out["excluded_subjects"]] == ["P103", "P110", "P120"]
    assert all(set(e) == {"subject", "reason"} for e in out["excluded_subjects"])
    assert set(out["effects"]["between"]) == {"F", "df1", "df2", "p", "np2", "ng2"}
    for name in ("within", "interaction"):
        assert set(out["effects"][name]) == {"F", "df1", "df2", "p", "np2", "ng2", "p_gg"}
    assert out["effects"]["interaction"]["df1"] == 3
    assert isinstance(out["effects"]["interaction"]["df2"], int)
    assert out["effects"]["interaction"]["F"] == pytest.approx(DROPOUT_T3["interaction"][0])
    assert set(out["sphericity"]) == {"W", "p", "eps_gg"}


def test_singular_sphericity_reported_not_crashing() -> None:
    # 2 groups × 2 participants → 2 error df < 3 contrasts of 4 sessions: Mauchly undefined.
    df = make_mixed((2, 2), 4, seed=5)
    result = mixed_anova(df, dv="y", within="time", between="group", subject="subject")
    assert result.sphericity.W == 0.0
    assert result.sphericity.p is None
    assert "singular" in result.sphericity.note
    assert 0 < result.sphericity.eps_gg <= 1
    assert result.to_dict()["sphericity"]["p"] is None
    assert np.isfinite(result.table["F"]).all()


# ------------------------------------------------------------------------ bad input


def test_duplicates_are_refused_and_named(dropouts: pd.DataFrame) -> None:
    dup = pd.concat(
        [dropouts, dropouts[(dropouts.participant == "P105") & (dropouts.session == 2)]]
    )
    with pytest.raises(DuplicateObservationError, match=r"\('P105', 2\)") as info:
        mixed_anova(dup, **DKW)
    assert info.value.duplicates == (("P105", 2),)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.drop(columns="trust"), "no column 'trust'"),
        (lambda d: d.assign(trust=d["trust"].astype(str).radd("x")), "must be numeric"),
        (lambda d: d.assign(session=d["session"].where(d.index != 0)), "missing value"),
        (lambda d: d.assign(trust=d["trust"].replace(3.35, np.inf)), "infinite"),
    ],
)
def test_malformed_input_is_refused(dropouts: pd.DataFrame, change, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InvalidInputError, match=message):
        mixed_anova(change(dropouts), **DKW)


def test_subject_in_two_groups_is_refused(dropouts: pd.DataFrame) -> None:
    bad = dropouts.copy()
    bad.loc[(bad.participant == "P101") & (bad.session == 4), "condition"] = "C2"
    with pytest.raises(InvalidInputError, match=r"'P101'.*more than one level"):
        mixed_anova(bad, **DKW)


def test_same_column_in_two_roles_is_refused(dropouts: pd.DataFrame) -> None:
    with pytest.raises(InvalidInputError, match="both"):
        mixed_anova(
            dropouts, dv="trust", within="session", between="session", subject="participant"
        )


def test_bad_ss_type_is_refused(dropouts: pd.DataFrame) -> None:
    with pytest.raises(InvalidInputError, match="ss_type"):
        mixed_anova(dropouts, **DKW, ss_type=1)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("frame", "because"),
    [
        (make_mixed((4, 4), 3).assign(y=3.0), "all 24 values of 'y' are equal"),
        (make_mixed((1, 1), 3), "single participant"),
        (make_mixed((6,), 3), "only one level of 'group'"),
        (make_mixed((4, 4), 1), "single level"),
        (
            make_mixed((4, 4), 3).assign(y=lambda d: d["time"] * 1.0 + (d["group"] == "G2")),
            "between-subjects error term is zero",
        ),
        (make_mixed((4, 4), 3).assign(y=lambda d: d["subject"] * 1.0), "changes identically"),
    ],
)  # fmt: skip
def test_degenerate_data_cannot_be_computed(frame: pd.DataFrame, because: str) -> None:
    with pytest.raises(CannotComputeError, match="cannot be computed because") as info:
        mixed_anova(frame, dv="y", within="time", between="group", subject="subject")
    assert because in str(info.value)


def test_no_complete_participant_cannot_be_computed() -> None:
    df = make_mixed((3, 3), 3)
    odd = df["subject"] % 2 == 1
    df = df[~((df["time"] == 3) & odd) & ~((df["time"] == 2) & ~odd)]
    with pytest.raises(CannotComputeError, match="no participant has a 'y' value for every level"):
        mixed_anova(df, dv="y", within="time", between="group", subject="subject")


def test_declared_within_levels() -> None:
    df = make_mixed((4, 5), 3, seed=4)
    kw = {"dv": "y", "within": "time", "between": "group", "subject": "subject"}
    with pytest.raises(CannotComputeError, match="no participant"):
        mixed_anova(df, **kw, within_levels=[1, 2, 3, 4])  # nobody has session 4
    with pytest.raises(InvalidInputError, match="outside the declared levels"):
        mixed_anova(df, **kw, within_levels=[1, 2])
