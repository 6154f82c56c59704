"""Simulation-based power for the linear mixed model trustlab fits, with Monte-Carlo intervals.

The analytic formulas (:mod:`analysis.power`) are the RM-ANOVA's. What trustlab runs on a study
is also a linear mixed model (``rating ~ condition * session + (1 | participant)``, REML,
Satterthwaite df, :mod:`analysis.lmm`), which no closed form covers once data go missing or the
covariance is not compound symmetric. So: simulate many datasets from a model (cell means, the
SD of one rating, ρ; e.g. a pilot's), fit each with trustlab's own REML and Satterthwaite code,
and count the rejections.

Each dataset is fitted by :class:`analysis.reml.RemlDesign` (the REML optimum in lme4's
parameterisation, checked against the boundary) and tested with
:func:`analysis.satterthwaite.f_test_df`: the code :func:`analysis.lmm.fit_mixed_model` runs,
without building its tables, so 1,000 datasets take seconds.
The fixed effects are sum-coded as in :func:`analysis.lmm.linear_mixed_models`, so each F is the
type III test; F does not depend on the basis of the contrasts, and with a random intercept and
balanced data neither do the Satterthwaite df.

Power's Monte-Carlo uncertainty is a Wilson score interval. The same seed gives the same
datasets and so the same figures.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from analysis.errors import InvalidInputError
from analysis.power import EFFECTS
from analysis.power_models import SIMULATED_MODEL_NAMES, SIMULATED_MODELS
from analysis.reml import RemlDesign
from analysis.satterthwaite import f_test_df, varpar_covariance

__all__ = [
    "SIMULATED_MODELS",
    "SIMULATED_MODEL_NAMES",
    "SimulatedPower",
    "check_simulation_size",
    "curve_seed",
    "effect_pattern",
    "simulate_power",
    "simulate_power_curve",
    "wilson_interval",
]


def wilson_interval(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson's score interval of a binomial proportion (never outside [0, 1])."""
    if trials <= 0:
        return float("nan"), float("nan")
    z = float(stats.norm.isf((1 - confidence) / 2))
    p = successes / trials
    denominator = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denominator
    half = z * np.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denominator
    low = 0.0 if successes == 0 else max(0.0, centre - half)  # exactly, not 1e-17
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return float(low), float(high)


def effect_pattern(effect: str, f: float, groups: int, sessions: int) -> np.ndarray:
    """Cell means (σ = 1) with effect size ``f`` for ``effect`` and none for the others:
    groups apart by a linear step (between), a linear trend over sessions (within), or
    groups whose trends diverge linearly (interaction, as in the seed paper)."""
    if effect not in EFFECTS:
        raise InvalidInputError(f"effect must be one of {', '.join(EFFECTS)}, got {effect!r}")
    g = np.arange(groups, dtype=float) - (groups - 1) / 2
    s = np.arange(sessions, dtype=float) - (sessions - 1) / 2
    if effect == "between":
        pattern = np.outer(g, np.ones(sessions))
    elif effect == "within":
        pattern = np.outer(np.ones(groups), s)
    else:
        pattern = np.outer(g, s)
    scale = float(np.sqrt(np.mean(pattern**2)))
    return pattern * (f / scale) if scale > 0 else pattern


@dataclass(frozen=True)
class SimulatedPower:
    """Power of one test of the random-intercept mixed model, estimated by simulation.

    Attributes
    ----------
    effect : str
    n_total, replicates : int
        Participants per dataset (equal groups) and datasets simulated.
    rejections : int
        Datasets whose test had p < alpha.
    failures : int
        Datasets whose fit gave no test (counted as not rejecting).
    power, ci_low, ci_high : float
        rejections / replicates and its 95 % Wilson interval.
    mean_df2 : float
        The mean Satterthwaite denominator df (for comparison with the ANOVA's); NaN for the
        ordinal model's χ² tests.
    seed : int
    kind : {"lmm", "ordinal"}
        The model fitted to each dataset (:data:`SIMULATED_MODELS`).
    """

    effect: str
    n_total: int
    replicates: int
    rejections: int
    failures: int
    power: float
    ci_low: float
    ci_high: float
    mean_df2: float
    seed: int
    kind: str = "lmm"

    def to_dict(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "n_total": self.n_total,
            "replicates": self.replicates,
            "rejections": self.rejections,
            "failures": self.failures,
            "power": self.power,
            "ci_low": self.ci_low,
            "ci_high": self.ci_high,
            "mean_df2": self.mean_df2,
            "seed": self.seed,
            "model": SIMULATED_MODELS[self.kind],
            "kind": self.kind,
        }


def check_simulation_size(n_total: int, groups: int, replicates: int) -> None:
    """Refuse (one line) a simulation without datasets or with unequal or tiny groups."""
    if replicates < 1:
        raise InvalidInputError(f"--simulate needs 1 or more datasets, got {replicates}")
    if n_total % groups or n_total // groups < 2:
        raise InvalidInputError(
            f"the simulation needs equal groups of 2 or more: N = {n_total} is not a multiple "
            f"of {groups} of at least {2 * groups}"
        )


def curve_seed(seed: int, n_total: int) -> int:
    """The seed of one N of a power curve, derived from ``seed`` and N, so adding an N to the
    curve does not change the others."""
    return int(np.random.SeedSequence([seed, n_total]).generate_state(1)[0])


def _design_matrix(
    groups: int, sessions: int, per_group: int
) -> tuple[np.ndarray, dict[str, slice]]:
    """Sum-coded fixed effects (intercept, group, session, group × session) of a balanced
    design, rows ordered participant by participant, and the columns of each term."""

    def sum_coding(levels: int) -> np.ndarray:
        return np.vstack([np.eye(levels - 1), -np.ones(levels - 1)])

    group_codes = np.repeat(np.arange(groups), per_group * sessions)
    session_codes = np.tile(np.arange(sessions), groups * per_group)
    a = sum_coding(groups)[group_codes]
    b = sum_coding(sessions)[session_codes]
    ab = np.einsum("ni,nj->nij", a, b).reshape(len(a), -1)
    x = np.hstack([np.ones((len(a), 1)), a, b, ab])
    ka, kb = groups - 1, sessions - 1
    terms = {
        "between": slice(1, 1 + ka),
        "within": slice(1 + ka, 1 + ka + kb),
        "interaction": slice(1 + ka + kb, 1 + ka + kb + ka * kb),
    }
    return x, terms


def simulate_power(
    effect: str,
    *,
    means: np.ndarray | Sequence[Sequence[float]],
    sd: float,
    rho: float,
    n_total: int,
    replicates: int,
    seed: int = 0,
    alpha: float = 0.05,
    progress: Callable[[], None] | None = None,
) -> SimulatedPower:
    """Simulate ``replicates`` datasets and count how often the mixed model's test rejects.

    Parameters
    ----------
    effect : {"between", "within", "interaction"}
    means : array-like, shape (k, m)
        The true cell means (e.g. a pilot's, or :func:`effect_pattern`).
    sd : float
        The SD of one rating.
    rho : float
        The correlation among a participant's ratings, in [0, 1): a random intercept of
        variance ρ σ² plus a residual of variance (1 − ρ) σ² (compound symmetry).
    n_total : int
        Participants per dataset, a multiple of k (equal groups).
    replicates : int
    seed : int
    alpha : float
    progress : callable, optional
        Called once per dataset (a progress bar).
    """
    table = np.asarray(means, dtype=float)
    if table.ndim != 2 or table.shape[0] < 2 or table.shape[1] < 2:
        raise InvalidInputError("the simulation needs cell means for 2 or more groups × sessions")
    k, m = table.shape
    if effect not in EFFECTS:
        raise InvalidInputError(f"effect must be one of {', '.join(EFFECTS)}, got {effect!r}")
    if not 0 <= rho < 1:
        raise InvalidInputError(
            f"the simulation draws a random intercept, so rho must be in [0, 1), got {rho:g}"
        )
    if not sd > 0:
        raise InvalidInputError(f"the SD of one rating must be positive, got {sd:g}")
    check_simulation_size(n_total, k, replicates)
    per_group = n_total // k
    x, terms = _design_matrix(k, m, per_group)
    z = np.ones((len(x), 1))
    subjects = np.repeat(np.arange(n_total), m)
    mu = np.repeat(table, per_group, axis=0).ravel()  # participant by participant
    contrast = np.eye(x.shape[1])[terms[effect]]
    sd_u, sd_e = sd * np.sqrt(rho), sd * np.sqrt(1 - rho)

    def test_one(rng: np.random.Generator) -> tuple[float, float]:
        y = mu + np.repeat(rng.normal(0, sd_u, n_total), m) + rng.normal(0, sd_e, len(mu))
        return _mixed_model_test(y, x, z, subjects, contrast)

    return count_rejections(
        test_one,
        effect=effect,
        n_total=n_total,
        replicates=replicates,
        seed=seed,
        alpha=alpha,
        progress=progress,
        kind="lmm",
    )


def count_rejections(
    test_one: Callable[[np.random.Generator], tuple[float, float]],
    *,
    effect: str,
    n_total: int,
    replicates: int,
    seed: int,
    alpha: float,
    progress: Callable[[], None] | None,
    kind: str,
) -> SimulatedPower:
    """The Monte-Carlo loop both simulated models share: ``test_one(rng)`` draws one dataset and
    tests it, returning (p, denominator df); a NaN p is a fit that gave no test, counted as not
    rejecting and reported as a failure. One generator, seeded once, serves every dataset, so a
    seed reproduces the whole run."""
    rng = np.random.default_rng(seed)
    rejections = failures = 0
    df2s: list[float] = []
    for _ in range(replicates):
        p, df2 = test_one(rng)
        if np.isfinite(p):
            rejections += int(p < alpha)
            if np.isfinite(df2):
                df2s.append(df2)
        else:
            failures += 1
        if progress is not None:
            progress()
    low, high = wilson_interval(rejections, replicates)
    return SimulatedPower(
        effect=effect,
        n_total=n_total,
        replicates=replicates,
        rejections=rejections,
        failures=failures,
        power=rejections / replicates,
        ci_low=low,
        ci_high=high,
        mean_df2=float(np.mean(df2s)) if df2s else float("nan"),
        seed=seed,
        kind=kind,
    )


def _mixed_model_test(
    y: np.ndarray, x: np.ndarray, z: np.ndarray, subjects: np.ndarray, contrast: np.ndarray
) -> tuple[float, float]:
    """p and denominator df of ``contrast · β = 0`` in the REML random-intercept fit."""
    try:
        reml = RemlDesign(y, x, z, subjects)
        estimate = reml.refine(np.ones(reml.n_theta))
        cov, jacobian = reml.beta_covariance_jacobian(estimate.varpar)
        varpar_cov = varpar_covariance(reml, estimate.varpar)
        f, df1, df2 = f_test_df(contrast, estimate.beta, cov, jacobian, varpar_cov)
    except (np.linalg.LinAlgError, ValueError):
        return float("nan"), float("nan")
    if not (np.isfinite(f) and np.isfinite(df2)):
        return float("nan"), float("nan")
    return float(stats.f.sf(f, df1, df2)), float(df2)


def simulate_power_curve(
    effect: str,
    *,
    means: np.ndarray | Sequence[Sequence[float]],
    sd: float,
    rho: float,
    n_values: Sequence[int],
    replicates: int,
    seed: int = 0,
    alpha: float = 0.05,
    progress: Callable[[], None] | None = None,
) -> list[SimulatedPower]:
    """:func:`simulate_power` at each N (each N with its own seed, derived from ``seed``, so
    adding an N to the curve does not change the others)."""
    return [
        simulate_power(
            effect,
            means=means,
            sd=sd,
            rho=rho,
            n_total=n,
            replicates=replicates,
            seed=curve_seed(seed, n),
            alpha=alpha,
            progress=progress,
        )
        for n in n_values
    ]
