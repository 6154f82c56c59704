"""Simulation-based power for trustlab's ordinal model of one Likert item.

A single rating item is analysed by :func:`analysis.ordinal.ordinal_model`: a proportional-odds
model of ``condition * session`` with a Wald χ² test per term and standard errors clustered by
participant. No closed form gives that test's power (the ratings are categories, the SEs are
sandwich estimates), so: draw many datasets from a population, fit each with trustlab's own
ordinal code, and count the rejections.

The population is the latent-variable form of the mixed proportional-odds model (R's ``clmm``
with a random intercept): participant ``i`` in condition ``g`` at session ``s`` has

    Y* = μ_gs + u_i + e_is,   u_i ~ N(0, σ_u²),   e_is ~ Logistic(0, 1),

and answers category ``j`` when ``θ_{j−1} < Y* ≤ θ_j``, so ``P(Y ≤ j | u) = expit(θ_j − μ − u)``.

- ρ is the latent intra-class correlation, ``σ_u² / (σ_u² + π²/3)``: the correlation among a
  participant's repeated ratings before they are cut into categories (the correlation of the
  ratings themselves is somewhat lower).
- Cohen's f is read on the latent scale: the cell means are an effect pattern with SD f times
  the latent SD of one rating, ``σ = √(π²/3 + σ_u²)``, so an f means for the latent ratings
  what it means for the linear model on continuous ratings.
- The thresholds come from category proportions (a pilot's observed ones: with no effect the
  simulated ratings have those proportions) or, by default, cut ±2σ into K equal bins
  (a centre-heavy distribution, e.g. 12/23/31/23/12 % for five categories).
- Or the whole population comes from a pilot's fitted ordinal model (its cell predictors and
  thresholds). Those are population-averaged (the model is marginal, with clustered SEs); they
  are put on the participant-specific scale by ``√(1 + c² σ_u²)``, ``c = 16√3 / (15π)``, the
  logistic-normal approximation of Zeger, Liang & Albert (1988, Biometrics 44, 1049–1060).

Each dataset is coded by :func:`analysis.ordinal.ordinal_design` and fitted by
:func:`analysis.ordinal.fit_proportional_odds` (the code behind ``ordinal_model``, without its
input checks and the Brant screen, which do not change the test). Datasets whose fit gives no
test count as not rejecting. Wilson intervals and the seeding are those of
:mod:`analysis.power_simulation`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from scipy import optimize, special

from analysis._checks import ordered_levels
from analysis.design import prepare_mixed_design
from analysis.errors import AnalysisError, InvalidInputError
from analysis.ordinal import (
    MAX_ITEM_CATEGORIES,
    fit_proportional_odds,
    not_single_item,
    ordinal_design,
    ordinal_model,
)
from analysis.power import EFFECTS, effect_sizes_from_means
from analysis.power_simulation import (
    SimulatedPower,
    check_simulation_size,
    count_rejections,
    curve_seed,
)

__all__ = [
    "DEFAULT_CATEGORIES",
    "MIN_CATEGORIES",
    "LatentOrdinalModel",
    "equally_spaced_thresholds",
    "latent_model",
    "observed_proportions",
    "pilot_latent_model",
    "simulate_ordinal_power",
    "simulate_ordinal_power_curve",
    "thresholds_from_proportions",
]

DEFAULT_CATEGORIES = 5
"""The protocol's Likert items have five points."""

MIN_CATEGORIES = 3
"""Two categories are a yes/no answer: a binary model, not an ordinal one."""

LOGISTIC_VARIANCE = float(np.pi**2 / 3)
"""The variance of the standard logistic residual."""

_ATTENUATION = 16 * np.sqrt(3) / (15 * np.pi)
_NODES, _WEIGHTS = np.polynomial.hermite_e.hermegauss(40)
_WEIGHTS = _WEIGHTS / np.sqrt(2 * np.pi)


def participant_sd(rho: float) -> float:
    """σ_u of the random intercept for a latent intra-class correlation ρ in [0, 1)."""
    if not 0 <= rho < 1:
        raise InvalidInputError(
            f"the simulation draws a random intercept, so rho must be in [0, 1), got {rho:g}"
        )
    return float(np.sqrt(rho / (1 - rho) * LOGISTIC_VARIANCE))


def _marginal_cdf(t: np.ndarray, sd_u: float) -> np.ndarray:
    """``P(u + e ≤ t)`` over the participants (Gauss–Hermite, 40 nodes)."""
    t = np.asarray(t, dtype=float)
    return np.asarray(special.expit(t[..., None] - sd_u * _NODES) @ _WEIGHTS)


@dataclass(frozen=True)
class LatentOrdinalModel:
    """The population ordinal datasets are drawn from (see the module's docstring).

    Attributes
    ----------
    cell_means : numpy.ndarray
        μ, shape (k groups, m sessions), on the latent (participant-specific logit) scale.
    thresholds : numpy.ndarray
        θ_1 < … < θ_{K−1}.
    participant_sd : float
        σ_u, the SD of the random intercept.
    source : str
        Where the population comes from, in words.
    """

    cell_means: np.ndarray
    thresholds: np.ndarray
    participant_sd: float
    source: str

    def __post_init__(self) -> None:
        means, cuts = np.asarray(self.cell_means), np.asarray(self.thresholds)
        if means.ndim != 2 or min(means.shape) < 2 or not np.all(np.isfinite(means)):
            raise InvalidInputError(
                "the simulation needs finite cell means for 2 or more groups × sessions"
            )
        if cuts.ndim != 1 or len(cuts) + 1 < MIN_CATEGORIES:
            raise InvalidInputError(
                f"the ordinal model needs {MIN_CATEGORIES} or more rating categories, "
                f"got {len(cuts) + 1 if cuts.ndim == 1 else cuts.size}"
            )
        if not (np.all(np.isfinite(cuts)) and np.all(np.diff(cuts) > 0)):
            raise InvalidInputError("the thresholds must be finite and increasing")
        if not (np.isfinite(self.participant_sd) and self.participant_sd >= 0):
            raise InvalidInputError(f"sigma_u must be 0 or more, got {self.participant_sd:g}")

    @property
    def categories(self) -> int:
        return len(self.thresholds) + 1

    @property
    def rho(self) -> float:
        """The latent intra-class correlation."""
        variance = self.participant_sd**2
        return variance / (variance + LOGISTIC_VARIANCE)

    @property
    def latent_sd(self) -> float:
        """σ, the latent SD of one rating within a cell."""
        return float(np.sqrt(self.participant_sd**2 + LOGISTIC_VARIANCE))

    def effect_sizes(self) -> dict[str, float]:
        """Cohen's f of each effect on the latent scale."""
        sizes = effect_sizes_from_means(np.asarray(self.cell_means), self.latent_sd)
        return {effect: sizes[effect] for effect in EFFECTS}

    def category_proportions(self) -> np.ndarray:
        """The expected share of each category, over the cells (equal weights)."""
        cuts = np.asarray(self.thresholds)[None, :] - np.asarray(self.cell_means).reshape(-1, 1)
        cdf = _marginal_cdf(cuts, self.participant_sd)
        full = np.hstack([np.zeros((len(cdf), 1)), cdf, np.ones((len(cdf), 1))])
        return np.asarray(np.diff(full, axis=1).mean(axis=0))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the population as the simulation used it."""
        return {
            "source": self.source,
            "categories": self.categories,
            "thresholds": [float(t) for t in self.thresholds],
            "category_proportions": [float(p) for p in self.category_proportions()],
            "cell_means_latent": np.asarray(self.cell_means, dtype=float).tolist(),
            "participant_sd": self.participant_sd,
            "rho_latent": self.rho,
            "latent_sd": self.latent_sd,
            "f_latent": self.effect_sizes(),
        }


def equally_spaced_thresholds(categories: int, sd_u: float) -> np.ndarray:
    """K − 1 thresholds cutting ±2 latent SDs into ``categories`` equal bins."""
    _check_categories(categories)
    sigma = np.sqrt(sd_u**2 + LOGISTIC_VARIANCE)
    return np.asarray(sigma * (-2 + 4 * np.arange(1, categories) / categories))


def thresholds_from_proportions(
    proportions: Sequence[float] | np.ndarray, sd_u: float
) -> np.ndarray:
    """The thresholds under which a latent mean of 0 gives these category proportions."""
    shares = np.asarray(proportions, dtype=float)
    _check_categories(len(shares))
    if np.any(shares <= 0) or not np.isclose(shares.sum(), 1):
        raise InvalidInputError("category proportions must be positive and sum to 1")
    cumulative = np.cumsum(shares)[:-1]
    return np.array(
        [
            optimize.brentq(lambda t, c=c: float(_marginal_cdf(np.array(t), sd_u)) - c, -60, 60)
            for c in cumulative
        ]
    )


def _check_categories(categories: int) -> None:
    if not MIN_CATEGORIES <= categories <= MAX_ITEM_CATEGORIES:
        raise InvalidInputError(
            f"the ordinal model needs {MIN_CATEGORIES} to {MAX_ITEM_CATEGORIES} rating "
            f"categories, got {categories}"
        )


def observed_proportions(values: Sequence[float] | np.ndarray, dv: str) -> np.ndarray:
    """The share of each category a pilot's ratings used (categories nobody chose are not
    categories of the fitted model either), refusing what is not one rating item."""
    ratings = np.asarray(values, dtype=float)
    ratings = ratings[np.isfinite(ratings)]
    problem = not_single_item(ratings, dv)
    if problem:
        raise InvalidInputError(f"--model ordinal needs one rating item: {problem}")
    _, counts = np.unique(ratings, return_counts=True)
    if len(counts) < MIN_CATEGORIES:
        raise InvalidInputError(
            f"--model ordinal needs {MIN_CATEGORIES} or more rating categories; the pilot's "
            f"{dv!r} uses {len(counts)}"
        )
    return np.asarray(counts / counts.sum())


def latent_model(
    pattern: np.ndarray,
    *,
    rho: float,
    categories: int = DEFAULT_CATEGORIES,
    proportions: Sequence[float] | np.ndarray | None = None,
    source: str = "",
) -> LatentOrdinalModel:
    """A population from an effect pattern in SD units (e.g.
    :func:`analysis.power_simulation.effect_pattern` with σ = 1), a latent ρ, and either the
    category proportions of a pilot or ``categories`` equally spaced thresholds."""
    sd_u = participant_sd(rho)
    if proportions is not None:
        thresholds = thresholds_from_proportions(proportions, sd_u)
        cut = "thresholds from the pilot's category proportions"
    else:
        thresholds = equally_spaced_thresholds(categories, sd_u)
        cut = f"{categories} categories, thresholds equally spaced over ±2 latent SD"
    sigma = np.sqrt(sd_u**2 + LOGISTIC_VARIANCE)
    return LatentOrdinalModel(
        cell_means=np.asarray(pattern, dtype=float) * sigma,
        thresholds=thresholds,
        participant_sd=sd_u,
        source=f"{source or 'an effect pattern'}; {cut}",
    )


def pilot_latent_model(
    data: pd.DataFrame, *, dv: str, within: str, between: str, subject: str, rho: float
) -> LatentOrdinalModel:
    """The population of a pilot's fitted ordinal model: its cell predictors and thresholds,
    put on the participant-specific scale for a latent ρ (see the module's docstring)."""
    observed_proportions(pd.to_numeric(data[dv], errors="coerce").to_numpy(float), dv)
    fit = ordinal_model(data, dv=dv, within=within, between=between, subject=subject)
    if not fit.converged:
        raise InvalidInputError(f"the pilot's ordinal model has no estimates: {fit.problem}")
    design = prepare_mixed_design(data, dv=dv, within=within, between=between, subject=subject)
    rows = data[pd.to_numeric(data[dv], errors="coerce").notna()]
    group_levels = ordered_levels(rows[between])
    within_levels = [w for w in design.within_levels if w in set(rows[within])]
    k, m = len(group_levels), len(within_levels)
    cells, _ = ordinal_design(
        np.repeat(np.asarray(group_levels, dtype=object), m),
        np.tile(np.asarray(within_levels, dtype=object), k),
        group_levels=group_levels,
        within_levels=within_levels,
        between=between,
        within=within,
    )
    beta = fit.coefficients.set_index("term")["estimate"]
    if list(cells.columns) != list(beta.index):
        raise InvalidInputError("the pilot's ordinal model does not have the design's terms")
    sd_u = participant_sd(rho)
    scale = float(np.sqrt(1 + (_ATTENUATION * sd_u) ** 2))
    eta = cells.to_numpy(float) @ beta.to_numpy(float)
    return LatentOrdinalModel(
        cell_means=scale * eta.reshape(k, m),
        thresholds=scale * fit.thresholds["estimate"].to_numpy(float),
        participant_sd=sd_u,
        source=(
            f"the pilot's fitted ordinal model ({len(fit.categories)} categories, "
            f"{fit.n_clusters} participants), scaled by {scale:.3f} to the participant level"
        ),
    )


def simulate_ordinal_power(
    effect: str,
    *,
    population: LatentOrdinalModel,
    n_total: int,
    replicates: int,
    seed: int = 0,
    alpha: float = 0.05,
    progress: Callable[[], None] | None = None,
) -> SimulatedPower:
    """Simulate ``replicates`` datasets and count how often the ordinal model's test rejects.

    Parameters
    ----------
    effect : {"between", "within", "interaction"}
        The Wald χ² test counted (condition, session, or condition × session).
    population : LatentOrdinalModel
    n_total : int
        Participants per dataset, a multiple of k (equal groups), every session rated.
    replicates, seed : int
    alpha : float
    progress : callable, optional
        Called once per dataset (a progress bar).
    """
    if effect not in EFFECTS:
        raise InvalidInputError(f"effect must be one of {', '.join(EFFECTS)}, got {effect!r}")
    means = np.asarray(population.cell_means, dtype=float)
    k, m = means.shape
    check_simulation_size(n_total, k, replicates)
    per_group = n_total // k
    exog, terms = ordinal_design(
        np.repeat(np.arange(k), per_group * m),
        np.tile(np.arange(m), n_total),
        group_levels=list(range(k)),
        within_levels=list(range(m)),
        between="condition",
        within="session",
    )
    term = list(terms)[EFFECTS.index(effect)]
    tested = {term: terms[term]}
    subjects = pd.Series(np.repeat(np.arange(n_total), m))
    mu = np.repeat(means, per_group, axis=0).ravel()  # participant by participant
    thresholds = np.asarray(population.thresholds, dtype=float)

    def test_one(rng: np.random.Generator) -> tuple[float, float]:
        latent = (
            mu
            + np.repeat(rng.normal(0, population.participant_sd, n_total), m)
            + rng.logistic(0, 1, len(mu))
        )
        ratings = np.searchsorted(thresholds, latent) + 1  # Y* ≤ θ_1 → 1, …
        return _ordinal_test(ratings, exog, subjects, tested), float("nan")  # χ²: no df2

    return count_rejections(
        test_one,
        effect=effect,
        n_total=n_total,
        replicates=replicates,
        seed=seed,
        alpha=alpha,
        progress=progress,
        kind="ordinal",
    )


def _ordinal_test(
    ratings: np.ndarray, exog: pd.DataFrame, subjects: pd.Series, tested: dict[str, list[str]]
) -> float:
    """p of the tested term's clustered Wald χ², NaN when the fit gives none."""
    try:
        fit = fit_proportional_odds(
            pd.Series(ratings, name="rating"),
            exog,
            groups=subjects,
            terms=tested,
            formula="rating ~ condition * session",
            check_po=False,
        )
    except AnalysisError:  # e.g. every rating the same category
        return float("nan")
    if not fit.converged or fit.tests.empty:
        return float("nan")
    return float(fit.tests["p"].iloc[0])


def simulate_ordinal_power_curve(
    effect: str,
    *,
    population: LatentOrdinalModel,
    n_values: Sequence[int],
    replicates: int,
    seed: int = 0,
    alpha: float = 0.05,
    progress: Callable[[], None] | None = None,
) -> list[SimulatedPower]:
    """:func:`simulate_ordinal_power` at each N, each N with its own seed
    (:func:`analysis.power_simulation.curve_seed`)."""
    return [
        simulate_ordinal_power(
            effect,
            population=population,
            n_total=n,
            replicates=replicates,
            seed=curve_seed(seed, n),
            alpha=alpha,
            progress=progress,
        )
        for n in n_values
    ]
