"""Property tests: random unbalanced designs against pingouin 0.7.0 and statsmodels 0.15.0."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pingouin as pg
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from analysis.anova import mixed_anova
from analysis.errors import CannotComputeError
from tests.analysis.test_anova import _statsmodels_type3_within

KW = {"dv": "y", "within": "time", "between": "group", "subject": "subject"}


@st.composite
def designs(draw: st.DrawFn) -> pd.DataFrame:
    n_groups = draw(st.integers(2, 3))
    sizes = draw(st.lists(st.integers(2, 7), min_size=n_groups, max_size=n_groups))
    n_levels = draw(st.integers(2, 5))
    likert = draw(st.booleans())
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    rows = []
    subject = 0
    for g, n in enumerate(sizes):
        for _ in range(n):
            subject += 1
            base = rng.normal(0, 1)
            for t in range(n_levels):
                value = base + 0.4 * g * t + rng.normal(0, 1)
                rows.append(
                    (
                        subject,
                        f"g{g}",
                        t,
                        float(np.clip(np.round(value + 3), 1, 5)) if likert else value,
                    )
                )
    return pd.DataFrame(rows, columns=["subject", "group", "time", "y"])


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(designs())
def test_random_designs_match_pingouin_and_statsmodels(df: pd.DataFrame) -> None:
    try:
        ours2 = mixed_anova(df, **KW, ss_type=2)
    except CannotComputeError:
        assume(False)  # zero error term with tiny Likert samples: nothing to compare
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = pg.mixed_anova(data=df, correction=True, **KW)
    # An effect with no variance at all is an exact 0 here and a rounding residue (~1e-15)
    # in pingouin: relative tolerance alone cannot compare those.
    np.testing.assert_allclose(ours2.table["F"], ref["F"], rtol=1e-7, atol=1e-10)
    # The residue's p is 1 − O(√F) (≈ 1 − 1e-7 for F ≈ 1e-14 with one df), ours exactly 1.
    no_variance = np.abs(ref["F"].to_numpy()) < 1e-10
    np.testing.assert_allclose(
        ours2.table["p_unc"][~no_variance], ref["p_unc"][~no_variance], rtol=1e-7, atol=1e-12
    )
    np.testing.assert_allclose(ours2.table["p_unc"][no_variance], 1.0, atol=1e-12)
    np.testing.assert_allclose(ref["p_unc"][no_variance], 1.0, atol=1e-6)
    np.testing.assert_allclose(ours2.table["np2"], ref["np2"], rtol=1e-7, atol=1e-12)
    if df["time"].nunique() > 2 and ours2.sphericity.p is not None:
        np.testing.assert_allclose(ours2.sphericity.eps_gg, ref["eps"].iloc[1], rtol=1e-7)
        np.testing.assert_allclose(
            ours2.sphericity.W, ref["W_spher"].iloc[1], rtol=1e-6, atol=1e-12
        )
        # Mauchly's p far in the tail: pingouin's comes out exactly 0 where ours is 1e-8
        # (a design hypothesis found in CI), so tiny p values are compared absolutely.
        np.testing.assert_allclose(ours2.sphericity.p, ref["p_spher"].iloc[1], rtol=1e-6, atol=1e-7)
        varies = ~no_variance[1:]
        np.testing.assert_allclose(
            ours2.table["p_GG_corr"][1:][varies],
            ref["p_GG_corr"][1:][varies],
            rtol=1e-7,
            atol=1e-12,
        )
    ours3 = mixed_anova(df, **KW, ss_type=3)
    assert ours3.effect("within")["F"] == pytest.approx(_statsmodels_type3_within(df), rel=1e-7)
    # Between and interaction do not depend on the type of sums of squares.
    np.testing.assert_allclose(
        ours3.table["F"].iloc[[0, 2]], ours2.table["F"].iloc[[0, 2]], rtol=1e-10, atol=1e-10
    )
    json_ready = ours3.to_dict()
    assert json_ready["n_subjects_used"] == df["subject"].nunique()
