"""Analytic power of the mixed (between × within) RM-ANOVA, as G*Power 3.1 computes it.

Before a lab runs a study, its ethics board and its pre-registration ask how many participants
and why. G*Power answers for the RM-ANOVA but knows nothing of the lab's pilot; trustlab holds
the protocol and the pilot, so it answers itself, and agrees with G*Power where G*Power's
assumptions hold (compound symmetry with correlation ρ among the repeated measures, a
non-sphericity correction ε that scales the degrees of freedom). Pure Python (the F
distributions of :mod:`analysis.f_distribution`, Brent's root finder of :mod:`analysis.roots`;
numpy only for a means table): the command line, the analysis page and the benchmark call the
same functions, and an analytic ``trustlab power`` imports neither SciPy nor pandas (issue 49).

Three questions, for one effect of a k groups × m sessions design (``between``, ``within`` or
``interaction``): the power for a total N (:func:`power_for_n`), the smallest total N, a multiple
of k, that reaches a target power (:func:`n_for_power`), and the smallest effect detectable with
a total N (:func:`detectable_effect`).

Effect sizes. Cohen's f, or a partial η² turned into f² = η² / (1 − η²) under one of two
conventions, named as G*Power names them:

``gpower`` (G*Power's default, "as in G*Power 3.0")
    f describes the population: the SD of the effect's means over the SD of one measurement.
    Noncentrality (G*Power 3.1 manual, "ANOVA: Repeated measures, between factors / within
    factors / within-between interaction"):

    - between:     λ = f² · N · m / (1 + (m − 1) ρ),   df = (k − 1, N − k)
    - within:      λ = f² · N · m · ε / (1 − ρ),       df = ((m − 1) ε, (N − k)(m − 1) ε)
    - interaction: λ = f² · N · m · ε / (1 − ρ),       df = ((k − 1)(m − 1) ε, (N − k)(m − 1) ε)

``spss`` (G*Power's option "as in SPSS")
    f² is the partial η² an ANOVA table (SPSS, JASP, trustlab's report) prints, η²/(1 − η²),
    which already holds the correlation among the repeated measures: so ρ is not used, and the
    noncentrality is f² times the design's own error df, λ = f² · df2 (with the same df as
    above). For a published result this is the λ its F implies (λ ≈ F · df1).

Notes
-----
Power is the noncentral F's tail beyond the central F's 1 − α quantile, with the ε-scaled
(non-integer) df, as G*Power. A means table gives f as G*Power's "effect size from means": the
SD (divisor k, m or k·m) of the effect's marginal means or interaction residuals over the SD of
one measurement (:func:`effect_sizes_from_means`).

References
----------
Faul, Erdfelder, Lang & Buchner (2007). G*Power 3. Behavior Research Methods 39, 175–191.
Cohen (1988). Statistical power analysis for the behavioral sciences (2nd ed.), ch. 8.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from analysis.errors import InvalidInputError
from analysis.f_distribution import f_isf, ncf_sf
from analysis.roots import brent_root

if TYPE_CHECKING:
    import numpy as np

__all__ = [
    "CONVENTIONS",
    "EFFECTS",
    "MAX_N",
    "Convention",
    "Effect",
    "PowerAnswer",
    "PowerDesign",
    "detectable_effect",
    "effect_sizes_from_means",
    "eta2_from_f",
    "f_from_eta2",
    "n_for_power",
    "power_for_n",
]

Effect = Literal["between", "within", "interaction"]
Convention = Literal["gpower", "spss"]
EFFECTS: tuple[Effect, ...] = ("between", "within", "interaction")
CONVENTIONS: tuple[Convention, ...] = ("gpower", "spss")
_EPSILON_ROUNDING = 5e-4
"""An ε this far below 1/(m − 1) is that bound typed with three decimals, and taken as it."""
MAX_N = 10_000_000
"""The sample-size search stops here: a plan that needs more participants is not a plan."""


def f_from_eta2(eta2: float) -> float:
    """Cohen's f of a (partial) η²: ``sqrt(η² / (1 − η²))``."""
    eta2 = float(eta2)
    if not 0 <= eta2 < 1:
        raise InvalidInputError(f"eta² must be at least 0 and below 1, got {eta2:g}")
    return math.sqrt(eta2 / (1 - eta2))


def eta2_from_f(f: float) -> float:
    """The (partial) η² of Cohen's f: ``f² / (1 + f²)``."""
    return f * f / (1 + f * f)


@dataclass(frozen=True)
class PowerDesign:
    """One effect of a k × m mixed design, and how its effect size is read.

    Attributes
    ----------
    effect : {"between", "within", "interaction"}
    groups, sessions : int
        k (between levels, ≥ 2 for the between effect and the interaction) and m (sessions,
        ≥ 2 for the within effect and the interaction).
    rho : float or None
        The correlation among the repeated measures, in (−1, 1); needed by the ``gpower``
        convention (except for a between effect of one session), unused by ``spss``.
    epsilon : float
        Non-sphericity correction, in [1/(m − 1), 1]; scales the within and interaction df.
    alpha : float
    convention : {"gpower", "spss"}

    Raises
    ------
    InvalidInputError
        Any value out of range, in one line that names it.
    """

    effect: Effect
    groups: int
    sessions: int
    rho: float | None
    epsilon: float = 1.0
    alpha: float = 0.05
    convention: Convention = "gpower"

    def __post_init__(self) -> None:
        if self.effect not in EFFECTS:
            raise InvalidInputError(
                f"effect must be one of {', '.join(EFFECTS)}, got {self.effect!r}"
            )
        if self.convention not in CONVENTIONS:
            raise InvalidInputError(
                f"convention must be one of {', '.join(CONVENTIONS)}, got {self.convention!r}"
            )
        k, m = self.groups, self.sessions
        if not isinstance(k, int) or k < 1:
            raise InvalidInputError(f"groups must be a whole number ≥ 1, got {k!r}")
        if not isinstance(m, int) or m < 1:
            raise InvalidInputError(f"sessions must be a whole number ≥ 1, got {m!r}")
        if self.effect != "within" and k < 2:
            raise InvalidInputError(f"the {self.effect} effect needs 2 or more groups, got {k}")
        if self.effect != "between" and m < 2:
            raise InvalidInputError(f"the {self.effect} effect needs 2 or more sessions, got {m}")
        if not 0 < self.alpha < 1:
            raise InvalidInputError(f"alpha must be between 0 and 1, got {self.alpha:g}")
        self._check_rho()
        self._check_epsilon()

    def _check_rho(self) -> None:
        rho = self.rho
        if rho is not None and not -1 < rho < 1:
            raise InvalidInputError(
                f"rho (the correlation among repeated measures) must be between −1 and 1 "
                f"(exclusive), got {rho:g}"
            )
        if self.convention == "spss":
            return
        if rho is None:
            if self.effect == "between" and self.sessions == 1:
                return
            raise InvalidInputError(
                "rho (the correlation among repeated measures) is needed with the gpower convention"
            )
        if self.sessions > 1 and 1 + (self.sessions - 1) * rho <= 0:
            raise InvalidInputError(
                f"rho = {rho:g} is impossible for {self.sessions} sessions: equal correlations "
                f"among {self.sessions} measures must exceed −1/{self.sessions - 1}"
            )

    def _check_epsilon(self) -> None:
        eps, m = self.epsilon, self.sessions
        if m < 2:
            if eps != 1:
                raise InvalidInputError(f"epsilon must be 1 with a single session, got {eps:g}")
            return
        low = 1 / (m - 1)
        if not low - _EPSILON_ROUNDING <= eps <= 1:
            raise InvalidInputError(
                f"epsilon must be between 1/(m − 1) = {low:.4g} and 1 for {m} sessions, got {eps:g}"
            )
        if eps < low:  # the lower bound typed as a rounded decimal (.333 for 1/3)
            object.__setattr__(self, "epsilon", low)

    @property
    def uses_epsilon(self) -> bool:
        """Whether ε enters this effect's test (within and interaction)."""
        return self.effect != "between"

    def degrees_of_freedom(self, n_total: float) -> tuple[float, float]:
        """``(df1, df2)`` of the effect's F test with N participants (ε-scaled where it
        applies)."""
        k, m = self.groups, self.sessions
        if self.effect == "between":
            return float(k - 1), float(n_total - k)
        eps = self.epsilon
        df1 = (m - 1) * eps * (1 if self.effect == "within" else k - 1)
        return float(df1), float((n_total - k) * (m - 1) * eps)

    def noncentrality(self, f: float, n_total: float) -> float:
        """λ of the effect with Cohen's f and N participants (see the module notes)."""
        f2 = f * f
        if self.convention == "spss":
            return f2 * self.degrees_of_freedom(n_total)[1]
        m = self.sessions
        rho = 0.0 if self.rho is None else self.rho
        if self.effect == "between":
            return f2 * n_total * m / (1 + (m - 1) * rho)
        return f2 * n_total * m * self.epsilon / (1 - rho)

    def power(self, f: float, n_total: float) -> float:
        """The probability that the effect's F test rejects at ``alpha``."""
        df1, df2 = self.degrees_of_freedom(n_total)
        lam = self.noncentrality(f, n_total)
        if lam <= 0:
            return self.alpha
        return ncf_sf(self.critical_f(n_total), df1, df2, lam)

    def critical_f(self, n_total: float) -> float:
        """The F that the test with N participants must exceed to reject at ``alpha``."""
        return f_isf(self.alpha, *self.degrees_of_freedom(n_total))

    def to_dict(self) -> dict[str, Any]:
        """The design as understood (JSON-ready)."""
        return {
            "effect": self.effect,
            "groups": self.groups,
            "sessions": self.sessions,
            "rho": self.rho,
            "rho_used": self.convention == "gpower"
            and not (self.effect == "between" and self.sessions == 1),
            "epsilon": self.epsilon,
            "epsilon_used": self.uses_epsilon,
            "alpha": self.alpha,
            "convention": self.convention,
        }


@dataclass(frozen=True)
class PowerAnswer:
    """The answer to one question, with everything needed to reproduce it.

    Attributes
    ----------
    question : {"power", "sample size", "detectable effect"}
    design : PowerDesign
    f, eta2 : float
        The effect size used (given, or found by :func:`detectable_effect`); η² under the
        design's convention.
    n_total : int
        The total N (given, or found by :func:`n_for_power`).
    power : float
        The power at ``n_total`` and ``f``.
    target_power : float or None
    lam, df1, df2, f_critical : float
        Noncentrality, degrees of freedom and critical F of the test.
    """

    question: Literal["power", "sample size", "detectable effect"]
    design: PowerDesign
    f: float
    eta2: float
    n_total: int
    power: float
    target_power: float | None
    lam: float
    df1: float
    df2: float
    f_critical: float

    def to_dict(self) -> dict[str, Any]:
        """The ``trustlab power --json`` contract: outputs at the top, the design inside."""
        return {
            "question": self.question,
            "power": self.power,
            "n_total": self.n_total,
            "n_per_group": self.n_total / self.design.groups,
            "f": self.f,
            "eta2": self.eta2,
            "lambda": self.lam,
            "df1": self.df1,
            "df2": self.df2,
            "f_critical": self.f_critical,
            "target_power": self.target_power,
            "design": self.design.to_dict(),
        }


def _answer(
    question: Literal["power", "sample size", "detectable effect"],
    design: PowerDesign,
    f: float,
    n_total: int,
    target: float | None,
) -> PowerAnswer:
    df1, df2 = design.degrees_of_freedom(n_total)
    return PowerAnswer(
        question=question,
        design=design,
        f=f,
        eta2=eta2_from_f(f),
        n_total=n_total,
        power=design.power(f, n_total),
        target_power=target,
        lam=design.noncentrality(f, n_total),
        df1=df1,
        df2=df2,
        f_critical=design.critical_f(n_total),
    )


def _check_f(f: float) -> float:
    f = float(f)
    if not math.isfinite(f) or f < 0:
        raise InvalidInputError(f"the effect size f must be 0 or more, got {f:g}")
    return f


def _check_n(design: PowerDesign, n_total: int) -> int:
    if isinstance(n_total, bool) or not float(n_total).is_integer():
        raise InvalidInputError(f"N must be a whole number, got {n_total!r}")
    n = int(n_total)
    if n <= design.groups:
        raise InvalidInputError(
            f"N = {n} leaves no error degrees of freedom with {design.groups} group(s): "
            f"N must exceed {design.groups}"
        )
    return n


def _check_target(target: float, design: PowerDesign) -> float:
    target = float(target)
    if not 0 < target < 1:
        raise InvalidInputError(f"the target power must be between 0 and 1, got {target:g}")
    return target


def power_for_n(design: PowerDesign, *, f: float, n_total: int) -> PowerAnswer:
    """The power of the effect's test with effect size f and N participants in total."""
    return _answer("power", design, _check_f(f), _check_n(design, n_total), None)


def n_for_power(design: PowerDesign, *, f: float, target: float) -> PowerAnswer:
    """The smallest total N, a multiple of the number of groups (equal groups, as G*Power
    reports it), whose power reaches ``target``.

    Raises
    ------
    InvalidInputError
        When no N up to :data:`MAX_N` reaches the target (f = 0, or an effect too small).
    """
    f = _check_f(f)
    target = _check_target(target, design)
    k = design.groups
    if target <= design.alpha and f == 0:
        return _answer("sample size", design, f, 2 * k, target)
    if f == 0:
        raise InvalidInputError(
            f"an effect of f = 0 is rejected with probability alpha = {design.alpha:g} at any N, "
            f"never with power {target:g}"
        )
    low, high = 2, 2  # participants per group: power(low) < target ≤ power(high)
    if design.power(f, k * low) >= target:
        return _answer("sample size", design, f, k * low, target)
    while design.power(f, k * high) < target:
        low, high = high, high * 2
        if k * high > MAX_N:
            raise InvalidInputError(
                f"f = {f:.4g} does not reach power {target:g} below N = {MAX_N:,}"
            )
    while high - low > 1:
        middle = (low + high) // 2
        if design.power(f, k * middle) >= target:
            high = middle
        else:
            low = middle
    return _answer("sample size", design, f, k * high, target)


def detectable_effect(design: PowerDesign, *, n_total: int, target: float) -> PowerAnswer:
    """The smallest f (and its η² under the design's convention) that N participants detect
    with power ``target`` (G*Power's sensitivity analysis)."""
    n = _check_n(design, n_total)
    target = _check_target(target, design)
    if target <= design.alpha:
        return _answer("detectable effect", design, 0.0, n, target)
    high = 0.5
    while design.power(high, n) < target:
        high *= 2
        if high > 1e6:
            raise InvalidInputError(f"no effect size reaches power {target:g} with N = {n}")
    f = brent_root(lambda x: design.power(x, n) - target, 0.0, high, xtol=1e-10, rtol=1e-12)
    return _answer("detectable effect", design, f, n, target)


def effect_sizes_from_means(
    means: Sequence[Sequence[float]] | np.ndarray,
    sd: float | Sequence[Sequence[float]] | np.ndarray,
) -> dict[str, float]:
    """Cohen's f of each effect from a groups × sessions table of means and SDs.

    Parameters
    ----------
    means : array-like, shape (k, m)
        Cell means, one row per group.
    sd : float or array-like of shape (k, m)
        The SD of one measurement: one number, or each cell's SD (pooled as the root of the
        mean variance, equal groups).

    Returns
    -------
    dict
        ``{"between", "within", "interaction", "sd"}``: f = σ_effect / σ with σ_effect the
        population SD of the group means (averaged over sessions), of the session means
        (averaged over groups), or of the cell means' interaction residuals, as G*Power's
        "effect size from means" (equal group sizes).
    """
    import numpy as np  # here only: the other questions need no numpy (trustlab power's start)

    table = np.asarray(means, dtype=float)
    if table.ndim != 2 or table.size == 0 or not np.isfinite(table).all():
        raise InvalidInputError("the means must be a table of numbers: one row per group")
    sds = np.asarray(sd, dtype=float)
    if sds.ndim == 0:
        sigma = float(sds)
    else:
        if sds.shape != table.shape:
            raise InvalidInputError(
                f"the SDs form a {'×'.join(map(str, sds.shape))} table, the means a "
                f"{'×'.join(map(str, table.shape))} table: give one SD, or one per mean"
            )
        sigma = float(np.sqrt(np.mean(sds**2)))
    if not math.isfinite(sigma) or sigma <= 0 or (sds.ndim and (sds <= 0).any()):
        raise InvalidInputError("every SD must be a positive number")
    grand = table.mean()
    rows = table.mean(axis=1)
    columns = table.mean(axis=0)
    residual = table - rows[:, None] - columns[None, :] + grand
    return {
        "between": float(np.sqrt(np.mean((rows - grand) ** 2)) / sigma),
        "within": float(np.sqrt(np.mean((columns - grand) ** 2)) / sigma),
        "interaction": float(np.sqrt(np.mean(residual**2)) / sigma),
        "sd": sigma,
    }
