"""The central and noncentral F distributions in pure Python (standard library only).

Why not SciPy: ``trustlab power`` answers an analytic question in a few milliseconds, but
importing ``scipy.stats`` costs it most of a second (issue 49: a command that opens no database
gets 0.3 s). Power needs only three functions of the F distribution (the central upper tail
and its inverse for the critical F, the noncentral upper tail for the power), and each is a
regularised incomplete beta function, which a continued fraction and :func:`math.lgamma`
give to about twelve digits. The analysis page, the command line and the benchmark all call
these through :mod:`analysis.power`.

Each function works on the side of the distribution whose probability is the smaller, and
forms both ``y`` and ``1 − y`` of the beta variable directly from x, so a tail of 1e-300 keeps
its digits, as does a power of .051.

Notes
-----
``I_y(a, b)`` is the regularised incomplete beta; for F with ``df1 = 2a``, ``df2 = 2b``:
``cdf(x) = I_y(a, b)`` and ``sf(x) = I_z(b, a)`` with ``y = df1·x / (df1·x + df2)`` and
``z = df2 / (df1·x + df2) = 1 − y``. The noncentral upper tail with noncentrality λ is the
Poisson(λ/2) mixture ``Σ_j w_j · I_z(b, a + j)``, summed outwards from the Poisson mode with
the recurrence ``I_z(b, a + j + 1) = I_z(b, a + j) + T_j`` (AS 226, Lenth 1987; Ding 1992).
Agreement with ``scipy.stats.f`` and ``scipy.stats.ncf`` is tested on a grid
(tests/analysis/test_f_distribution.py).

References
----------
Press, Teukolsky, Vetterling & Flannery (2007). Numerical Recipes (3rd ed.), §6.4 (the
continued fraction, by the modified Lentz method).
Lenth (1987). Algorithm AS 226: computing noncentral beta probabilities. Applied Statistics
36, 241–244. Ding (1992). Algorithm AS 275. Applied Statistics 41, 478–482.
"""

from __future__ import annotations

import math

__all__ = ["beta_inc", "f_cdf", "f_isf", "f_sf", "ncf_sf"]

_EPS = 1e-16
"""Relative size of the last continued-fraction step, and of a mixture term, at which to stop."""
_TINY = 1e-300
_MAX_TERMS = 100_000
"""Continued-fraction steps and mixture terms at most (neither comes near it on the tested grid)."""


def _check_df(df1: float, df2: float) -> None:
    if not (df1 > 0 and df2 > 0 and math.isfinite(df1) and math.isfinite(df2)):
        raise ValueError(f"degrees of freedom must be positive and finite, got {df1}, {df2}")


def _log_beta(a: float, b: float) -> float:
    return math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)


def _continued_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of ``I_x(a, b)`` (modified Lentz), for ``x < (a + 1)/(a + b + 2)``
    where it converges fast."""
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c = 1.0
    d = 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > _TINY else _TINY)
    h = d
    for m in range(1, _MAX_TERMS):
        m2 = 2 * m
        for aa in (
            m * (b - m) * x / ((qam + m2) * (a + m2)),
            -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2)),
        ):
            d = 1.0 + aa * d
            d = 1.0 / (d if abs(d) > _TINY else _TINY)
            c = 1.0 + aa / c
            if abs(c) < _TINY:
                c = _TINY
            step = d * c
            h *= step
        if abs(step - 1.0) < _EPS:
            return h
    raise ArithmeticError(f"the incomplete beta's continued fraction did not converge ({a}, {b})")


def beta_inc(a: float, b: float, x: float, y: float) -> tuple[float, float]:
    """``(I_x(a, b), 1 − I_x(a, b))``, the regularised incomplete beta and its complement.

    ``y`` is ``1 − x`` formed by the caller without subtracting (e.g. ``d2 / (d1·t + d2)``), so
    that neither side loses digits when x is near 1. The side computed by the continued
    fraction is the one where it converges (Numerical Recipes), the other is 1 minus it.
    """
    if x <= 0.0:
        return 0.0, 1.0
    if y <= 0.0:
        return 1.0, 0.0
    if x < (a + 1.0) / (a + b + 2.0):
        front = math.exp(a * math.log(x) + b * math.log(y) - _log_beta(a, b))
        lower = front * _continued_fraction(a, b, x) / a
        return lower, 1.0 - lower
    front = math.exp(b * math.log(y) + a * math.log(x) - _log_beta(a, b))
    upper = front * _continued_fraction(b, a, y) / b
    return 1.0 - upper, upper


def _beta_variables(x: float, df1: float, df2: float) -> tuple[float, float]:
    """``y = df1·x / (df1·x + df2)`` and ``z = 1 − y``, each formed without cancellation."""
    scaled = df1 * x
    total = scaled + df2
    return scaled / total, df2 / total


def f_sf(x: float, df1: float, df2: float) -> float:
    """``P(F > x)`` of the central F distribution (``scipy.stats.f.sf``)."""
    _check_df(df1, df2)
    if x <= 0:
        return 1.0
    if math.isinf(x):
        return 0.0
    y, z = _beta_variables(x, df1, df2)
    return beta_inc(df1 / 2, df2 / 2, y, z)[1]


def f_cdf(x: float, df1: float, df2: float) -> float:
    """``P(F ≤ x)`` of the central F distribution (``scipy.stats.f.cdf``)."""
    _check_df(df1, df2)
    if x <= 0:
        return 0.0
    if math.isinf(x):
        return 1.0
    y, z = _beta_variables(x, df1, df2)
    return beta_inc(df1 / 2, df2 / 2, y, z)[0]


def f_isf(p: float, df1: float, df2: float) -> float:
    """The x with ``P(F > x) = p`` (``scipy.stats.f.isf``): the critical F at level p.

    Solved on ``t = ln x`` by Newton's method on the log of the smaller tail (``ln sf`` for
    p ≤ ½, ``ln cdf`` with 1 − p, exact in floating point, otherwise), which is nearly linear
    in t in both tails, inside a bracket that falls back to bisection whenever a Newton step
    would leave it.
    """
    _check_df(df1, df2)
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"a probability must be in [0, 1], got {p}")
    if p == 0.0:
        return math.inf
    if p == 1.0:
        return 0.0
    a, b = df1 / 2, df2 / 2
    upper = p <= 0.5
    log_target = math.log(p if upper else 1.0 - p)
    log_beta = _log_beta(a, b)

    def residual(t: float) -> tuple[float, float]:
        """``ln tail(e^t) − ln target`` and its derivative in t (the tail is sf or cdf)."""
        y, z = _beta_variables(math.exp(t), df1, df2)
        lower, tail = beta_inc(a, b, y, z)
        if not upper:
            tail = lower
        if tail <= 0.0:
            return -math.inf, 0.0
        density = math.exp(a * math.log(y) + b * math.log(z) - log_beta)  # x · pdf(x)
        slope = density / tail
        return math.log(tail) - log_target, -slope if upper else slope

    # The residual falls with t for the upper tail and rises for the lower: keep a bracket
    # [low, high] of t with the root inside, as far as it is known.
    low, high = -math.inf, math.inf
    t = 0.0
    for _ in range(400):
        value, slope = residual(t)
        if value == 0.0:
            return math.exp(t)
        beyond = (value < 0.0) if upper else (value > 0.0)  # t is past the root
        if beyond:
            high = t
        else:
            low = t
        if math.isfinite(value) and slope != 0.0:
            new = t - value / slope
            if math.isinf(low) or math.isinf(high):
                new = max(t - 16.0, min(t + 16.0, new))
        else:
            new = math.nan
        if not low < new < high:
            if math.isinf(low):
                new = high - max(1.0, 2.0 * (high - t) if t < high else 1.0)
            elif math.isinf(high):
                new = low + max(1.0, 2.0 * (t - low) if t > low else 1.0)
            else:
                new = 0.5 * (low + high)
        if abs(new - t) <= 1e-15 * max(1.0, abs(t)) or (high - low) <= 1e-15 * max(1.0, abs(t)):
            return math.exp(new)
        t = new
    raise ArithmeticError(f"the F quantile did not converge (p = {p}, df = {df1}, {df2})")


def ncf_sf(x: float, df1: float, df2: float, nc: float) -> float:
    """``P(F' > x)`` of the noncentral F distribution with noncentrality ``nc`` (λ)
    (``scipy.stats.ncf.sf``): the power of an F test whose critical value is x.

    The Poisson(λ/2) mixture of central upper tails ``I_z(b, a + j)``, started at the Poisson
    mode with one continued fraction and carried to both sides by the incomplete beta's
    recurrence in a; each direction stops when what it could still add, bounded by the
    Poisson tail's geometric ratio, is below 1e-16 of the sum.
    """
    _check_df(df1, df2)
    if not (nc >= 0 and math.isfinite(nc)):
        raise ValueError(f"the noncentrality must be 0 or more and finite, got {nc}")
    if x <= 0:
        return 1.0
    if math.isinf(x):
        return 0.0
    if nc == 0:
        return f_sf(x, df1, df2)
    a, b, mu = df1 / 2, df2 / 2, nc / 2
    y, z = _beta_variables(x, df1, df2)
    mode = int(mu)
    weight0 = math.exp(-mu + mode * math.log(mu) - math.lgamma(mode + 1.0))
    start = a + mode
    tail0 = beta_inc(start, b, y, z)[1]  # I_z(b, a + mode), computed on its own side
    # T_j = y^(a+j) z^b / ((a + j) B(a + j, b)), so that I_z(b, a+j+1) = I_z(b, a+j) + T_j.
    step0 = math.exp(start * math.log(y) + b * math.log(z) - _log_beta(start, b)) / start
    total = weight0 * tail0

    # Upwards: the tails grow (by positive steps: stable) towards 1, the weights fall.
    j, weight, tail, step = mode, weight0, tail0, step0
    while j < mode + _MAX_TERMS:
        tail += step
        step *= y * (a + b + j) / (a + j + 1)
        j += 1
        weight *= mu / j
        total += weight * min(tail, 1.0)
        ratio = mu / (j + 1)
        if weight == 0.0 or (ratio < 1 and weight * ratio / (1 - ratio) <= _EPS * total):
            break

    # Downwards: the weights and the tails both fall; what is left is below the term times
    # the geometric sum of the weights' ratio j/μ.
    j, weight, tail, step = mode, weight0, tail0, step0
    while j > 0:
        step *= (a + j) / (y * (a + b + j - 1))  # T_(j−1)
        tail = max(tail - step, 0.0)
        weight *= j / mu
        j -= 1
        term = weight * tail
        total += term
        ratio = j / mu
        if term == 0.0 or term * ratio / (1 - ratio) <= _EPS * total:
            break
    return min(total, 1.0)
