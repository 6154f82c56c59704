"""Proportional-odds models of single Likert items, with participant-clustered standard errors.

A single five-point item is ordinal: the distance from "disagree" to "neutral" need not equal
the one from "neutral" to "agree", so a mean (and an ANOVA on it) can mislead. A cumulative-link
(proportional-odds) model treats the answer as ordered categories: ``logit P(Y ≤ j) = θ_j − x'β``,
the parameterisation of R's ``ordinal::clm``, so a positive coefficient means higher ratings.

No maintained Python library fits the mixed version (R's ``clmm``, with a random intercept per
participant), so :func:`ordinal_models` fits the marginal model with statsmodels' ``OrderedModel``
and makes its inference honest about the repeated ratings with cluster-robust (sandwich)
standard errors by participant, the approach of generalised estimating equations with an
independence working correlation. Coefficients are population-averaged log odds ratios, which
are somewhat smaller than a CLMM's subject-specific ones; the tests are valid with enough
participants (about 20 or more; fewer makes sandwich SEs optimistic).

The proportional-odds assumption (one β for every cut-point) is checked with Brant's (1990)
Wald test, which compares the slopes of the separate binary logits ``Y > j``; like Brant's
original it treats the ratings as independent, so it is a screen, not an exact test, here.
"""

from __future__ import annotations

import functools
import itertools
import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from analysis._checks import fit_status, json_records, json_value, ordered_levels, to_python
from analysis.design import prepare_mixed_design, refuse_empty_cells
from analysis.errors import CannotComputeError, InvalidInputError
from analysis.lmm import term_labeller

__all__ = [
    "COEFFICIENT_COLUMNS",
    "PO_CHECK_COLUMNS",
    "THRESHOLD_COLUMNS",
    "WALD_COLUMNS",
    "OrdinalFit",
    "fit_proportional_odds",
    "not_single_item",
    "ordinal_design",
    "ordinal_model",
]

COEFFICIENT_COLUMNS = ("term", "estimate", "se", "z", "p", "ci_low", "ci_high", "odds_ratio")
"""Columns of :attr:`OrdinalFit.coefficients` (log odds ratios; ``odds_ratio`` = exp)."""

THRESHOLD_COLUMNS = ("threshold", "estimate", "se")
"""Columns of :attr:`OrdinalFit.thresholds` (``"1|2"``: the cut between categories 1 and 2)."""

WALD_COLUMNS = ("effect", "Source", "chi2", "df", "p")
"""Columns of :attr:`OrdinalFit.tests`: a Wald χ² test per model term."""

PO_CHECK_COLUMNS = ("Source", "chi2", "df", "p")
"""Columns of :attr:`OrdinalFit.po_check`: Brant's test, omnibus first, then per term."""


@dataclass(frozen=True)
class OrdinalFit:
    """A fitted proportional-odds (cumulative logit) model.

    Attributes
    ----------
    formula : str
        For readers, e.g. ``trust_1 ~ condition * session (cumulative logit)``.
    converged : bool
    problem : str
        Empty, or one line saying why there are no estimates.
    notes : tuple of str
        Caveats that do not void the fit (e.g. a category nobody used, a PO check that failed).
    se_type : str
        ``"cluster-robust by participant (G clusters)"`` or ``"model-based"``.
    loglik, aic : float
    n_obs, n_clusters : int
    categories : tuple
        The observed response categories, in order.
    coefficients, thresholds, tests, po_check : pandas.DataFrame
        See :data:`COEFFICIENT_COLUMNS`, :data:`THRESHOLD_COLUMNS`, :data:`WALD_COLUMNS`,
        :data:`PO_CHECK_COLUMNS`.
    po_problem : str
        Why the proportional-odds check could not be computed (empty when it was).
    """

    formula: str
    converged: bool
    problem: str
    notes: tuple[str, ...]
    se_type: str
    loglik: float
    aic: float
    n_obs: int
    n_clusters: int
    categories: tuple[Any, ...]
    coefficients: pd.DataFrame
    thresholds: pd.DataFrame
    tests: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(columns=list(WALD_COLUMNS)))
    po_check: pd.DataFrame = field(
        default_factory=lambda: pd.DataFrame(columns=list(PO_CHECK_COLUMNS))
    )
    po_problem: str = ""

    @property
    def status(self) -> str:
        """One line for a reader: the problem, else the notes, else "converged"."""
        return fit_status(self.problem, self.notes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN → None)."""

        return {
            "formula": self.formula,
            "converged": self.converged,
            "problem": self.problem,
            "notes": list(self.notes),
            "se_type": self.se_type,
            "loglik": json_value(self.loglik),
            "aic": json_value(self.aic),
            "n_obs": self.n_obs,
            "n_clusters": self.n_clusters,
            "categories": [to_python(c) for c in self.categories],
            "coefficients": json_records(self.coefficients),
            "thresholds": json_records(self.thresholds),
            "tests": json_records(self.tests),
            "po_check": json_records(self.po_check),
            "po_problem": self.po_problem,
        }


def fit_proportional_odds(
    y: pd.Series,
    exog: pd.DataFrame,
    *,
    groups: pd.Series | None = None,
    terms: dict[str, list[str]] | None = None,
    formula: str = "",
    confidence: float = 0.95,
    check_po: bool = True,
) -> OrdinalFit:
    """Fit ``logit P(y ≤ j) = θ_j − exog · β`` by maximum likelihood.

    Parameters
    ----------
    y : pandas.Series
        Ordered responses (numbers or an ordered categorical); categories in sorted order.
    exog : pandas.DataFrame
        Predictors without a constant (the thresholds play the intercept's part).
    groups : pandas.Series, optional
        Cluster of each row (the participant): standard errors become cluster-robust.
    terms : dict, optional
        Term name → its exog columns, for the Wald tests and the per-term PO check.
    formula : str
        Shown to readers.
    confidence : float
        Coverage of the coefficient CIs.
    check_po : bool
        Run Brant's test of proportional odds.

    Returns
    -------
    OrdinalFit

    Notes
    -----
    The cluster-robust covariance is ``G/(G−1) · H⁻¹ (Σ_g s_g s_g') H⁻¹`` with the per-cluster
    score sums ``s_g``; threshold SEs come from it by the delta method.
    """
    if not 0 < confidence < 1:
        raise InvalidInputError(f"confidence must be between 0 and 1, got {confidence!r}")
    categories = tuple(sorted(pd.unique(y)))
    codes = pd.Categorical(y, categories=list(categories), ordered=True)
    formula = formula or f"{y.name} ~ {' + '.join(map(str, exog.columns))}"
    n_cats = len(categories)
    if n_cats < 2:
        raise CannotComputeError(
            f"the ordinal model of {y.name!r}", "every rating is the same category"
        )
    exog = exog.astype(float)
    if (
        np.linalg.matrix_rank(np.column_stack([np.ones(len(exog)), exog.to_numpy()]))
        <= exog.shape[1]
    ):
        raise CannotComputeError(
            f"the ordinal model of {y.name!r}",
            "its predictors are not all estimable from these data (collinear, or one is constant)",
        )
    model = _logit_ordered_model()(pd.Series(codes, name=y.name), exog, distr="logit")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            # skip_hessian: statsmodels' own covariance is not used; the Hessian is taken once,
            # below, for the model-based and the sandwich covariance.
            result = model.fit(method="bfgs", maxiter=2000, disp=False, skip_hessian=True)
        except (np.linalg.LinAlgError, ValueError) as error:
            return _failed(formula, categories, len(y), f"the ordinal model failed: {error}")
    retvals = getattr(result, "mle_retvals", {}) or {}
    converged = bool(retvals.get("converged", True)) and np.all(np.isfinite(result.params))
    if not converged:
        messages = "; ".join(sorted({str(w.message).splitlines()[0] for w in caught}))
        return _failed(
            formula,
            categories,
            len(y),
            "the ordinal model did not converge (BFGS: "
            f"{messages or retvals.get('message', 'no message')}); no estimates",
        )
    params = np.asarray(result.params, dtype=float)
    k = exog.shape[1]
    hessian = model.hessian(params)
    notes: list[str] = []
    n_clusters = 0
    try:
        bread = np.linalg.inv(-hessian)
    except np.linalg.LinAlgError:
        return _failed(
            formula,
            categories,
            len(y),
            "the ordinal model's information matrix is singular "
            "(a category or cell without ratings separates the data); no estimates",
        )
    if groups is not None:
        scores = model.score_obs(params)
        codes_g, uniques = pd.factorize(pd.Series(groups).reset_index(drop=True))
        n_clusters = len(uniques)
        summed = np.zeros((n_clusters, scores.shape[1]))
        np.add.at(summed, codes_g, scores)
        meat = summed.T @ summed
        cov = n_clusters / (n_clusters - 1) * bread @ meat @ bread if n_clusters > 1 else bread
        se_type = f"cluster-robust ({n_clusters} clusters)"
    else:
        cov = bread
        se_type = "model-based"
    beta, beta_cov = params[:k], cov[:k, :k]
    se = np.sqrt(np.clip(np.diag(beta_cov), 0, None))
    z = beta / se
    crit = stats.norm.ppf(0.5 + confidence / 2)
    coefficients = pd.DataFrame(
        {
            "term": list(exog.columns),
            "estimate": beta,
            "se": se,
            "z": z,
            "p": 2 * stats.norm.sf(np.abs(z)),
            "ci_low": beta - crit * se,
            "ci_high": beta + crit * se,
            "odds_ratio": np.exp(beta),
        }
    )
    cuts, jac = _thresholds(params[k:])
    cut_cov = jac @ cov[k:, k:] @ jac.T
    thresholds = pd.DataFrame(
        {
            "threshold": [f"{a}|{b}" for a, b in itertools.pairwise(categories)],
            "estimate": cuts,
            "se": np.sqrt(np.clip(np.diag(cut_cov), 0, None)),
        }
    )
    tests = _wald_tests(beta, beta_cov, list(exog.columns), terms)
    po_check, po_problem, po_notes = (
        proportional_odds_check(codes.codes, exog, terms, categories)
        if check_po
        else (pd.DataFrame(columns=list(PO_CHECK_COLUMNS)), "", [])
    )
    notes.extend(po_notes)
    llf = float(result.llf)
    return OrdinalFit(
        formula=formula,
        converged=True,
        problem="",
        notes=tuple(notes),
        se_type=se_type,
        loglik=llf,
        aic=-2 * llf + 2 * len(params),
        n_obs=len(y),
        n_clusters=n_clusters,
        categories=categories,
        coefficients=coefficients,
        thresholds=thresholds,
        tests=tests,
        po_check=po_check,
        po_problem=po_problem,
    )


@functools.cache
def _logit_ordered_model() -> type:
    """statsmodels' ``OrderedModel`` with the logistic cdf as ``scipy.special.expit``.

    ``scipy.stats.logistic.cdf`` is ``expit`` behind a distribution object whose argument
    checks cost most of a fit's time (BFGS and the numerical Hessian call it ~1,000 times):
    the same numbers, bit for bit, about five times faster, which matters to the simulated
    power (:mod:`analysis.power_ordinal`) that fits hundreds of datasets.
    """
    from scipy import special
    from statsmodels.miscmodels.ordinal_model import OrderedModel

    class LogitOrderedModel(OrderedModel):
        def cdf(self, x: np.ndarray) -> np.ndarray:
            return special.expit(x)

        def pdf(self, x: np.ndarray) -> np.ndarray:
            p = special.expit(x)
            return p * (1 - p)

    return LogitOrderedModel


def _failed(formula: str, categories: tuple[Any, ...], n: int, problem: str) -> OrdinalFit:
    return OrdinalFit(
        formula=formula,
        converged=False,
        problem=problem,
        notes=(),
        se_type="",
        loglik=float("nan"),
        aic=float("nan"),
        n_obs=n,
        n_clusters=0,
        categories=categories,
        coefficients=pd.DataFrame(columns=list(COEFFICIENT_COLUMNS)),
        thresholds=pd.DataFrame(columns=list(THRESHOLD_COLUMNS)),
    )


def _thresholds(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cut-points from statsmodels' parameters (first cut, then log increments) and their
    Jacobian: ``θ_j = a_1 + Σ_{i ≤ j} exp(b_i)``."""
    increments = np.concatenate([[raw[0]], np.exp(raw[1:])])
    cuts = np.cumsum(increments)
    jac = np.zeros((len(raw), len(raw)))
    jac[:, 0] = 1.0
    for j in range(1, len(raw)):
        jac[j:, j] = np.exp(raw[j])
    return cuts, jac


def _wald_tests(
    beta: np.ndarray, cov: np.ndarray, columns: list[str], terms: dict[str, list[str]] | None
) -> pd.DataFrame:
    rows = []
    for term, names in (terms or {}).items():
        index = [columns.index(n) for n in names]
        b = beta[index]
        try:
            chi2 = float(b @ np.linalg.solve(cov[np.ix_(index, index)], b))
        except np.linalg.LinAlgError:
            chi2 = float("nan")
        rows.append(
            {
                "effect": term,
                "Source": term,
                "chi2": chi2,
                "df": len(index),
                "p": float(stats.chi2.sf(chi2, len(index))),
            }
        )
    return pd.DataFrame(rows, columns=list(WALD_COLUMNS))


def proportional_odds_check(
    codes: np.ndarray,
    exog: pd.DataFrame,
    terms: dict[str, list[str]] | None,
    categories: tuple[Any, ...],
) -> tuple[pd.DataFrame, str, list[str]]:
    """Brant's test as a result: the table, why it is missing (if it is) and notes to show."""
    empty = pd.DataFrame(columns=list(PO_CHECK_COLUMNS))
    if len(categories) < 3:
        return empty, "the proportional-odds check needs three or more categories", []
    try:
        table, skipped = brant_test(codes, exog, terms)
    except CannotComputeError as error:
        return empty, str(error), [str(error)]
    if not skipped:
        return table, "", []
    cuts = ", ".join(f"{categories[j]}|{categories[j + 1]}" for j in skipped)
    return table, "", [f"the proportional-odds check leaves out the sparse cut-point(s) {cuts}"]


def brant_test(
    codes: np.ndarray, exog: pd.DataFrame, terms: dict[str, list[str]] | None = None
) -> tuple[pd.DataFrame, list[int]]:
    """Brant's Wald test that each slope is the same at every cut-point.

    Parameters
    ----------
    codes : numpy.ndarray
        Category codes 0..J−1 of the responses.
    exog : pandas.DataFrame
        Predictors without a constant.
    terms : dict, optional
        Term name → columns, for the per-term rows.

    Returns
    -------
    pandas.DataFrame
        :data:`PO_CHECK_COLUMNS`; the first row (``Source`` = "omnibus") tests every slope.
    list of int
        Cut-points left out (code ``j``: the split between categories ``j`` and ``j + 1``)
        because their binary logit is (quasi-)separated: sparse categories make some cell
        all-below or all-above, where the slopes do not exist.

    Raises
    ------
    CannotComputeError
        Fewer than two cut-points can be fitted, or the covariance is singular.

    Notes
    -----
    For cut ``j`` the binary logit of ``Y > j`` gives ``β_j``; the covariance of ``β_j`` and
    ``β_m`` (``j < m``) is ``(X'W_jX)⁻¹ X'W_jm X (X'W_mX)⁻¹`` with ``w_jm = π_m (1 − π_j)``
    (Brant 1990, eq. 2.5). The statistic is ``(Dβ)'(DVD')⁻¹(Dβ)`` for the differences
    ``D β = (β_1 − β_2, …, β_1 − β_{J−1})`` of the slopes.
    """
    x = np.column_stack([np.ones(len(codes)), exog.to_numpy(float)])
    p = exog.shape[1]
    betas, probs, informations, skipped = [], [], [], []
    for cut in range(int(codes.max())):
        fitted = _logit(x, (codes > cut).astype(float))
        if fitted is None:
            skipped.append(cut)
            continue
        betas.append(fitted[0])
        probs.append(fitted[1])
        informations.append(fitted[2])
    n_cuts = len(betas)
    if n_cuts < 2:
        raise CannotComputeError(
            "the proportional-odds check",
            "fewer than two cut-points can be fitted as binary splits (in some cell every "
            "rating lies on one side of the others)",
        )
    inverse = [np.linalg.inv(info) for info in informations]
    total = np.zeros((n_cuts * (p + 1), n_cuts * (p + 1)))
    for j in range(n_cuts):
        for m in range(j, n_cuts):
            w = probs[m] * (1 - probs[j])
            block = inverse[j] @ (x.T * w) @ x @ inverse[m]
            total[j * (p + 1) : (j + 1) * (p + 1), m * (p + 1) : (m + 1) * (p + 1)] = block
            total[m * (p + 1) : (m + 1) * (p + 1), j * (p + 1) : (j + 1) * (p + 1)] = block.T
    slopes = np.concatenate([b[1:] for b in betas])
    slope_index = np.concatenate(
        [np.arange(j * (p + 1) + 1, (j + 1) * (p + 1)) for j in range(n_cuts)]
    )
    v = total[np.ix_(slope_index, slope_index)]
    columns = list(exog.columns)
    groups = {"omnibus": columns, **(terms or {})}
    rows = []
    for name, names in groups.items():
        index = [columns.index(c) for c in names]
        d = np.zeros(((n_cuts - 1) * len(index), n_cuts * p))
        for row, (cut, col) in enumerate((cut, col) for cut in range(1, n_cuts) for col in index):
            d[row, col] = 1.0
            d[row, cut * p + col] = -1.0
        diff = d @ slopes
        try:
            chi2 = float(diff @ np.linalg.solve(d @ v @ d.T, diff))
        except np.linalg.LinAlgError:
            raise CannotComputeError(
                "the proportional-odds check", "the binary splits' covariance is singular"
            ) from None
        df = d.shape[0]
        rows.append({"Source": name, "chi2": chi2, "df": df, "p": float(stats.chi2.sf(chi2, df))})
    return pd.DataFrame(rows, columns=list(PO_CHECK_COLUMNS)), skipped


def _logit(x: np.ndarray, outcome: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Binary logit by statsmodels: coefficients, fitted probabilities, information; None when
    the split is (quasi-)separated (no convergence, or fitted probabilities of 0 or 1)."""
    import statsmodels.api as sm

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            result = sm.Logit(outcome, x).fit(disp=False, maxiter=200)
        except Exception:  # statsmodels' PerfectSeparationError, LinAlgError
            return None
    beta = np.asarray(result.params, dtype=float)
    if not result.mle_retvals.get("converged", False) or not np.all(np.isfinite(beta)):
        return None
    pi = 1 / (1 + np.exp(-(x @ beta)))
    if np.min(np.minimum(pi, 1 - pi)) < 1e-5:
        return None
    info = (x.T * (pi * (1 - pi))) @ x
    return beta, pi, info


# --- the study's model: between × within ---------------------------------------------------

MAX_ITEM_CATEGORIES = 11
"""More distinct values than this (a 0–10 scale has 11) is not one rating item."""


def not_single_item(values: np.ndarray, dv: str) -> str:
    """Why ``values`` are not the ratings of one item (empty when they are): whole numbers with
    at most :data:`MAX_ITEM_CATEGORIES` distinct values. A mean of items is not ordinal."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    fractional = finite[finite != np.round(finite)]
    if len(fractional):
        return f"{dv} has {fractional[0]:g}, not a whole-number rating (e.g. a scale mean)"
    if len(np.unique(finite)) > MAX_ITEM_CATEGORIES:
        return f"{dv} has more than {MAX_ITEM_CATEGORIES} distinct values"
    return ""


def ordinal_design(
    between_values: pd.Series | np.ndarray,
    within_values: pd.Series | np.ndarray,
    *,
    group_levels: list[Any] | tuple[Any, ...],
    within_levels: list[Any] | tuple[Any, ...],
    between: str,
    within: str,
    additive: bool = False,
) -> tuple[pd.DataFrame, dict[str, list[str]]]:
    """The predictors :func:`ordinal_model` fits, and the columns of each term.

    ``between * within`` (or ``between + within`` when ``additive``), both factors sum-to-zero
    coded, without the intercept (the thresholds play its part); columns and terms named as
    :func:`analysis.lmm.term_labeller` names them (``condition``, ``session``,
    ``condition × session``). Shared with the simulated power, so the datasets it fits are
    coded exactly as a study's ratings are.
    """
    from patsy import dmatrix

    frame = pd.DataFrame(
        {
            "between": pd.Categorical(np.asarray(between_values), categories=list(group_levels)),
            "within": pd.Categorical(np.asarray(within_values), categories=list(within_levels)),
        }
    )
    operator = "+" if additive else "*"
    matrix = dmatrix(f"C(between, Sum) {operator} C(within, Sum)", frame, return_type="dataframe")
    label = term_labeller(between, within)
    exog = matrix.drop(columns="Intercept").rename(columns=label)
    terms = {
        label(term): [label(c) for c in matrix.columns[cols]]
        for term, cols in matrix.design_info.term_name_slices.items()
        if term != "Intercept"
    }
    return exog, terms


def ordinal_model(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    within_levels: list[Any] | None = None,
    confidence: float = 0.95,
) -> OrdinalFit:
    """``dv ~ between * within`` as a proportional-odds model, clustered by participant.

    Parameters
    ----------
    data : pandas.DataFrame
        Long format; ``dv`` holds whole-number ratings (a single Likert item). Missing ratings
        are skipped; every other rating of the participant is kept.
    dv, within, between, subject : str
    within_levels : list, optional
    confidence : float

    Returns
    -------
    OrdinalFit
        Sum-to-zero coding of both factors, so each term's Wald test is type III.

    Raises
    ------
    InvalidInputError
        As :func:`analysis.design.prepare_mixed_design`, or ratings that are not whole numbers.
    CannotComputeError
        One category only, or one level of a factor.
    """
    design = prepare_mixed_design(
        data, dv=dv, within=within, between=between, subject=subject, within_levels=within_levels
    )
    ratings = pd.to_numeric(data[dv], errors="coerce")
    rows = data[ratings.notna()].reset_index(drop=True)
    values = ratings[ratings.notna()].to_numpy(float)
    problem = not_single_item(values, dv)
    if problem:
        raise InvalidInputError(f"the ordinal model needs one rating item: {problem}")
    group_levels = ordered_levels(rows[between])
    within_present = [w for w in design.within_levels if w in set(rows[within])]
    if len(group_levels) < 2 or len(within_present) < 2:
        raise CannotComputeError(
            f"the ordinal model of {dv!r}",
            f"it needs two or more levels of {between!r} and of {within!r} with ratings",
        )
    refuse_empty_cells(
        rows[between], rows[within], group_levels, within_present, f"the ordinal model of {dv!r}"
    )
    coding = {
        "group_levels": group_levels,
        "within_levels": within_present,
        "between": between,
        "within": within,
    }
    exog, terms = ordinal_design(rows[between], rows[within], **coding)  # type: ignore[arg-type]
    y = pd.Series(values.astype(int), name=dv)
    fit = fit_proportional_odds(
        y,
        exog,
        groups=rows[subject].map(to_python).astype(str),
        terms=terms,
        formula=f"{dv} ~ {between} * {within} (cumulative logit, clustered by {subject})",
        confidence=confidence,
        check_po=False,
    )
    if not fit.converged:
        return fit
    # The check uses the main effects: the between × within cells are too sparse for separate
    # binary fits at every cut-point in studies of typical size.
    additive, _ = ordinal_design(rows[between], rows[within], additive=True, **coding)  # type: ignore[arg-type]
    po_terms = {k: v for k, v in terms.items() if k in (between, within)}
    po_check, po_problem, po_notes = proportional_odds_check(
        pd.Categorical(y, ordered=True).codes, additive, po_terms, fit.categories
    )
    effects = {between: "between", within: "within", f"{between} × {within}": "interaction"}
    tests = fit.tests.assign(effect=fit.tests["effect"].map(lambda e: effects.get(e, e)))
    missing = [c for c in range(int(min(values)), int(max(values)) + 1) if c not in set(values)]
    notes = (*fit.notes, *po_notes)
    if missing:
        notes = (
            *notes,
            f"no rating of {', '.join(map(str, missing))}: those cut-points are merged",
        )
    return replace(fit, tests=tests, notes=notes, po_check=po_check, po_problem=po_problem)
