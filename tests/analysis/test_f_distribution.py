"""The pure-Python F distributions against SciPy's (scipy.stats.f and ncf, SciPy 1.17) on a grid.

The grid spans what power questions reach and beyond: df1 from 0.5 to 20, ε-scaled
(non-integer) ones included, df2 from 1 to 10,000, λ from 0 to 2,000, x from deep in the lower
tail to deep in the upper one (the central quantiles of p = 1e-12 … 1 − 1e-12, and three times
either side of them), probabilities from 1e-12 to 1 − 1e-12.

Bounds reached (relative unless said): every tail, central and noncentral, within 1e-9 of
SciPy's (the worst seen is 6e-11); the quantile's tail within 1e-9 of p.
Each tail is compared on the side where it is the smaller: SciPy's ``f.sf`` returns 1.0 where
the upper tail is 1 − 1e-9 (F(1, 1) at x = 2.5e-18), which this module gets right, so the larger
side is checked as the complement, to 1e-15 absolute. The quantile is checked through SciPy's
tail at it rather than against ``f.isf`` alone: with df2 = 1 and p = 1e-12 ``scipy.stats.f.isf``
is off by 4e-5 relative (its own ``f.sf`` there gives 9.99978e-13), so the comparison with
``f.isf`` is made where SciPy's quantile passes that same check.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy import stats

from analysis.f_distribution import beta_inc, f_cdf, f_isf, f_sf, ncf_sf

DF1 = (0.5, 0.6, 1.0, 1.8, 2.7, 5.4, 20.0)
"""Numerators: integer ones and ε-scaled ones ((k − 1)(m − 1)ε with ε = .3, .6, .9)."""
DF2 = (1.0, 1.5, 3.0, 22.4, 50.4, 1000.0, 3333.3, 10_000.0)
PROBABILITIES = (1e-12, 1e-9, 1e-6, 1e-3, 0.05, 0.5, 0.8, 0.999, 1 - 1e-6, 1 - 1e-12)
NONCENTRALITIES = (0.01, 0.5, 5.0, 37.3, 250.0, 2000.0)
RELATIVE = 1e-9
SMALLEST = 1e-290
"""Below this SciPy's and this module's tails are compared absolutely (subnormal territory)."""


def _close(ours: float, theirs: float, what: str) -> None:
    if abs(theirs) < SMALLEST:
        assert abs(ours - theirs) <= SMALLEST, what
    else:
        assert abs(ours - theirs) <= RELATIVE * abs(theirs), f"{what}: {ours!r} vs {theirs!r}"


def _points(df1: float, df2: float) -> list[float]:
    quantiles = [float(stats.f.isf(p, df1, df2)) for p in PROBABILITIES]
    return [q * s for q in quantiles for s in (1 / 3, 1.0, 3.0)]


@pytest.mark.parametrize("df1", DF1)
def test_central_tails_agree_with_scipy(df1: float) -> None:
    for df2 in DF2:
        for x in _points(df1, df2):
            upper, lower = f_sf(x, df1, df2), f_cdf(x, df1, df2)
            what = f"F({df1}, {df2}) at {x!r}"
            if upper <= 0.5:
                _close(upper, float(stats.f.sf(x, df1, df2)), "sf of " + what)
            else:
                _close(lower, float(stats.f.cdf(x, df1, df2)), "cdf of " + what)
            assert abs(upper + lower - 1) <= 1e-15, what


@pytest.mark.parametrize("df1", DF1)
def test_central_quantile_has_the_asked_tail(df1: float) -> None:
    for df2, p in itertools.product(DF2, PROBABILITIES):
        x = f_isf(p, df1, df2)
        upper = p <= 0.5

        def tail(at: float, df2: float = df2, upper: bool = upper) -> float:
            return float(stats.f.sf(at, df1, df2) if upper else stats.f.cdf(at, df1, df2))

        target = p if upper else 1 - p
        what = f"isf({p}) of F({df1}, {df2})"
        _close(tail(x), target, what)
        theirs = float(stats.f.isf(p, df1, df2))
        if abs(tail(theirs) - target) <= 1e-12 * target:  # where SciPy's quantile is exact
            _close(x, theirs, what + " vs scipy.stats.f.isf")


@pytest.mark.parametrize("df1", DF1)
def test_noncentral_upper_tail_agrees_with_scipy(df1: float) -> None:
    for df2 in DF2:
        points = _points(df1, df2)
        for nc in NONCENTRALITIES:
            theirs = stats.ncf.sf(np.array(points), df1, df2, nc)
            for x, expected in zip(points, theirs, strict=True):
                _close(
                    ncf_sf(x, df1, df2, nc), float(expected), f"ncf({df1}, {df2}, {nc}) at {x!r}"
                )


def test_zero_noncentrality_is_the_central_tail() -> None:
    assert ncf_sf(2.5, 1.8, 50.4, 0.0) == f_sf(2.5, 1.8, 50.4)
    assert ncf_sf(2.5, 1.8, 50.4, 1e-9) == pytest.approx(f_sf(2.5, 1.8, 50.4), rel=1e-8)


def test_small_powers_keep_their_digits() -> None:
    # A power just above alpha (λ small): the tail is computed on its own side, not as 1 − cdf.
    critical = f_isf(0.05, 3, 66)
    assert critical == pytest.approx(float(stats.f.isf(0.05, 3, 66)), rel=1e-12)
    _close(ncf_sf(critical, 3, 66, 1e-4), float(stats.ncf.sf(critical, 3, 66, 1e-4)), "power")
    _close(ncf_sf(critical * 40, 3, 66, 2.0), float(stats.ncf.sf(critical * 40, 3, 66, 2.0)), "")


def test_edges() -> None:
    assert (f_sf(0, 2, 3), f_cdf(0, 2, 3), f_sf(math.inf, 2, 3)) == (1.0, 0.0, 0.0)
    assert (f_isf(0.0, 2, 3), f_isf(1.0, 2, 3)) == (math.inf, 0.0)
    assert (ncf_sf(0, 2, 3, 4.0), ncf_sf(math.inf, 2, 3, 4.0)) == (1.0, 0.0)
    assert beta_inc(2.0, 3.0, 0.0, 1.0) == (0.0, 1.0)
    assert beta_inc(2.0, 3.0, 1.0, 0.0) == (1.0, 0.0)
    for bad in (lambda: f_sf(1, 0, 3), lambda: f_isf(1.5, 2, 3), lambda: ncf_sf(1, 2, 3, -1)):
        with pytest.raises(ValueError):
            bad()
