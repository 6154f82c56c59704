"""Linear mixed models of the repeated trust ratings, beside (never instead of) the mixed ANOVA.

The RM-ANOVA drops every participant who missed a session; a linear mixed model keeps every
rating. :func:`linear_mixed_models` fits ``dv ~ between * within + (1 | subject)`` and, on request,
the random-slope model ``(1 + within_step | subject)`` by REML, compares the two with a
likelihood-ratio test and AIC, tests the fixed effects with Satterthwaite degrees of freedom
(:mod:`analysis.satterthwaite`, as R's lmerTest), and gives estimated marginal means of every
between × within cell. :func:`fit_mixed_model` is the general fitter underneath, for any formula
with one grouping factor (the tests check it against lme4's ``sleepstudy``).

The fit is lme4's own method, done here (:mod:`analysis.reml`): the REML criterion profiled over
``σ`` in the relative Cholesky factor ``θ``, minimised by BFGS with its exact gradient from lme4's
start, the boundary model fitted as well and kept when it is at least as good (a variance of zero
or a correlation of ±1 is reported there, as singular). With one grouping factor the criterion
is a batch of ``q × q`` blocks over the participants' sufficient statistics, so a thousand
participants take milliseconds (statsmodels' ``MixedLM``, used before with several optimisers
to find a start, took seconds to minutes there). A fit whose optimiser stops away from a
stationary point is reported as not converged, never with silent estimates.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from analysis._checks import fit_status, json_records, json_value, ordered_levels, to_python
from analysis.descriptives import t_interval
from analysis.design import prepare_mixed_design, refuse_empty_cells
from analysis.errors import CannotComputeError, InvalidInputError
from analysis.reml import SINGULAR_TOL, RemlDesign, RemlFit
from analysis.satterthwaite import contrast_df, f_test_df, varpar_covariance

__all__ = [
    "EMM_COLUMNS",
    "FIXED_COLUMNS",
    "TEST_COLUMNS",
    "VARIANCE_COLUMNS",
    "LinearMixedModels",
    "MixedModelFit",
    "fit_mixed_model",
    "linear_mixed_models",
    "term_labeller",
]

FIXED_COLUMNS = ("term", "estimate", "se", "df", "t", "p", "ci_low", "ci_high")
"""Columns of :attr:`MixedModelFit.fixed`."""

TEST_COLUMNS = ("effect", "Source", "F", "df1", "df2", "p")
"""Columns of :attr:`MixedModelFit.tests` (type III: sum-to-zero coding)."""

VARIANCE_COLUMNS = ("component", "variance", "sd", "corr")
"""Columns of :attr:`MixedModelFit.variance`; ``corr`` only on the intercept–slope row."""

EMM_COLUMNS = ("emmean", "se", "df", "ci_low", "ci_high")
"""Statistic columns of :attr:`MixedModelFit.emmeans` (after the between and within columns)."""

_NO_RESIDUAL = 1e-10
"""A residual sum of squares at or below this share of the total is zero (as the ANOVA's)."""
_GRADIENT_TOL = 2e-3
"""A fit whose profiled REML criterion has a gradient element above this where the optimiser
stopped has not converged (lme4's ``check.conv.grad`` tolerance)."""


@dataclass
class _Inference:
    """What tests and marginal means need from a fit: β̂, C = Var(β̂), ∂C/∂varpar and
    cov(varpar), varpar = (θ, σ) as lmerTest (:mod:`analysis.satterthwaite`)."""

    beta: np.ndarray
    cov: np.ndarray
    jacobian: np.ndarray | None
    varpar_cov: np.ndarray | None

    @property
    def satterthwaite(self) -> bool:
        return self.varpar_cov is not None and self.jacobian is not None

    def contrast(self, row: np.ndarray) -> tuple[float, float, float]:
        """Estimate, SE and df of ``row · β`` (df = ∞ without Satterthwaite)."""
        variance = float(row @ self.cov @ row)
        df = (
            contrast_df(row, self.jacobian, self.varpar_cov, variance)  # type: ignore[arg-type]
            if self.satterthwaite
            else float("inf")
        )
        return float(row @ self.beta), float(np.sqrt(max(variance, 0.0))), df

    def f_test(self, matrix: np.ndarray) -> tuple[float, float, float]:
        """F, df1, df2 of ``matrix · β = 0`` (df2 = ∞, a Wald χ²/q, without Satterthwaite)."""
        if self.satterthwaite:
            return f_test_df(matrix, self.beta, self.cov, self.jacobian, self.varpar_cov)  # type: ignore[arg-type]
        lcl = matrix @ self.cov @ matrix.T
        est = matrix @ self.beta
        q = matrix.shape[0]
        return float(est @ np.linalg.solve(lcl, est) / q), float(q), float("inf")


@dataclass(frozen=True)
class MixedModelFit:
    """One fitted linear mixed model (REML).

    Attributes
    ----------
    name : str
        ``"random intercept"`` or ``"random slope"`` (or the caller's name).
    formula : str
        The model in lme4 notation, e.g. ``trust ~ condition * session + (1 | participant)``.
    converged : bool
        False when no optimiser converged: then ``problem`` says so and every table is empty.
    problem : str
        Empty, or one line: why the model has no estimates (with the optimisers' messages).
    notes : tuple of str
        Warnings that do not void the fit: a boundary (singular) fit, degrees of freedom that
        fell back to the normal approximation.
    df_method : str
        ``"Satterthwaite"`` or ``"normal approximation"`` (when θ's covariance is unavailable).
    optimizer : str
        How the optimum was found (BFGS on lme4's profiled REML criterion).
    loglik, aic : float
        REML log-likelihood and ``−2 logLik + 2 k`` (k = fixed + covariance parameters), as
        lme4 reports for REML fits: comparable between models with the same fixed effects only.
    n_obs, n_subjects : int
    fixed : pandas.DataFrame
        :data:`FIXED_COLUMNS`, with t tests on Satterthwaite df and t-based CIs.
    tests : pandas.DataFrame
        :data:`TEST_COLUMNS`: one F test per model term (empty for :func:`fit_mixed_model` calls
        whose formula has no terms beyond the intercept).
    variance : pandas.DataFrame
        :data:`VARIANCE_COLUMNS`: random-effect variances and SDs, their correlation, the residual.
    emmeans : pandas.DataFrame
        Estimated marginal means per between × within cell (:func:`linear_mixed_models` only).
    """

    name: str
    formula: str
    converged: bool
    problem: str
    notes: tuple[str, ...]
    df_method: str
    optimizer: str
    loglik: float
    aic: float
    n_obs: int
    n_subjects: int
    n_params: int
    fixed: pd.DataFrame
    tests: pd.DataFrame
    variance: pd.DataFrame
    emmeans: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(columns=list(EMM_COLUMNS)))
    inference: _Inference | None = field(default=None, repr=False, compare=False)
    design_info: Any = field(default=None, repr=False, compare=False)

    @property
    def status(self) -> str:
        """One line for a reader: the problem, else the notes, else "converged"."""
        return fit_status(self.problem, self.notes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: every number a float (NaN → None), tables as lists of records."""

        return {
            "name": self.name,
            "formula": self.formula,
            "converged": self.converged,
            "problem": self.problem,
            "notes": list(self.notes),
            "df_method": self.df_method,
            "optimizer": self.optimizer,
            "loglik": json_value(self.loglik),
            "aic": json_value(self.aic),
            "n_obs": self.n_obs,
            "n_subjects": self.n_subjects,
            "fixed": json_records(self.fixed),
            "tests": json_records(self.tests),
            "variance": json_records(self.variance),
            "emmeans": json_records(self.emmeans),
        }


@dataclass(frozen=True)
class LinearMixedModels:
    """Result of :func:`linear_mixed_models`.

    Attributes
    ----------
    dv, within, between, subject : str
    intercept : MixedModelFit
        ``dv ~ between * within + (1 | subject)``.
    slope : MixedModelFit or None
        ``dv ~ between * within + (1 + within_step | subject)``, when asked for.
    comparison : dict or None
        Likelihood-ratio test of the slope model against the intercept model: ``chi2``, ``df``,
        ``p`` (50:50 mixture of χ²(1) and χ²(2), since the slope variance is tested on its
        boundary), ``aic_intercept``, ``aic_slope`` and ``preferred`` (the model name).
    kept : pandas.DataFrame
        ``subject``, ``between``, ``reason``: participants the ANOVA excludes (a missing
        session) and the mixed model keeps, with the ANOVA's reason.
    n_obs, n_subjects : int
        Ratings and participants used by the mixed models.
    within_levels : tuple
        The within levels with ratings, in order; level ``i`` is slope step ``i``.
    slope_skipped : str
        Why the random-slope model was asked for but not fitted (fewer than three within levels).
    """

    dv: str
    within: str
    between: str
    subject: str
    intercept: MixedModelFit
    slope: MixedModelFit | None
    comparison: dict[str, Any] | None
    kept: pd.DataFrame
    n_obs: int
    n_subjects: int
    within_levels: tuple[Any, ...] = ()
    slope_skipped: str = ""

    @property
    def preferred(self) -> MixedModelFit:
        """The model the comparison prefers (the intercept model without a usable comparison)."""
        if (
            self.slope is not None
            and self.comparison
            and self.comparison["preferred"] == self.slope.name
        ):
            return self.slope
        return self.intercept

    @property
    def models(self) -> tuple[MixedModelFit, ...]:
        """The fitted models, intercept first."""
        return (self.intercept,) if self.slope is None else (self.intercept, self.slope)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the ``trustlab mixed --json`` contract)."""
        return {
            "dv": self.dv,
            "within": self.within,
            "between": self.between,
            "subject": self.subject,
            "n_obs": self.n_obs,
            "n_subjects": self.n_subjects,
            "models": [m.to_dict() for m in self.models],
            "comparison": (
                {k: json_value(v) for k, v in self.comparison.items()} if self.comparison else None
            ),
            "preferred": self.preferred.name,
            "slope_skipped": self.slope_skipped,
            "within_levels": [json_value(level) for level in self.within_levels],
            "kept_by_mixed_model": json_records(self.kept),
        }


def fit_mixed_model(
    data: pd.DataFrame,
    *,
    formula: str,
    subject: str,
    re_formula: str | None = None,
    name: str = "mixed model",
    display: str | None = None,
    confidence: float = 0.95,
    labels: Callable[[str], str] | None = None,
) -> MixedModelFit:
    """Fit a linear mixed model by REML and test its fixed effects with Satterthwaite df.

    Parameters
    ----------
    data : pandas.DataFrame
        Long data; rows with a missing value in a model column are dropped by the caller.
    formula : str
        Fixed part in patsy notation, e.g. ``"Reaction ~ Days"``.
    subject : str
        Grouping column (one random-effects vector per level).
    re_formula : str, optional
        Random part, e.g. ``"~Days"`` for a random intercept and slope; default intercept only.
    name, display : str
        Model name, and its lme4-style formula for readers (default: built from the others).
    confidence : float
        Coverage of the coefficient CIs.
    labels : callable, optional
        Design column or term name → readable name (default: unchanged).

    Returns
    -------
    MixedModelFit

    Raises
    ------
    InvalidInputError
        A formula the data cannot fill, or a confidence outside (0, 1).
    CannotComputeError
        Too few observations or subjects, a constant response, collinear fixed effects, or a
        model that reproduces every value to rounding error (no residual variation: REML has no
        optimum, and any F would be an artefact of rounding).

    Notes
    -----
    The fixed-effect t tests use Satterthwaite df (lmerTest's default); when the covariance of
    the variance parameters cannot be computed (a degenerate Hessian), they fall back to the
    normal approximation and a note says so. Term F tests are type III when the formula uses
    sum-to-zero coding (``C(x, Sum)``), as :func:`linear_mixed_models` does.
    """
    from patsy import dmatrices, dmatrix

    display = display or (
        f"{formula} + ({'1' if re_formula is None else re_formula.lstrip('~ ') + ' + 1'}"
        f" | {subject})"
    )
    try:
        endog, exog = dmatrices(formula, data, NA_action="raise")
        exog_re: Any = (
            np.ones((len(data), 1))
            if re_formula is None
            else dmatrix(re_formula, data, NA_action="raise")
        )
        groups = pd.factorize(data[subject])[0]
    except Exception as error:  # patsy's PatsyError and friends: a formula the data cannot fill
        raise InvalidInputError(f"cannot build the model {display}: {error}") from None
    return _fit_matrices(
        _Matrices(
            y=np.asarray(endog, float)[:, 0],
            x=np.asarray(exog, float),
            z=np.asarray(exog_re, float),
            groups=groups,
            design_info=exog.design_info,
            re_names=(
                ["Intercept"] if re_formula is None else list(exog_re.design_info.column_names)
            ),
        ),
        subject=subject,
        name=name,
        display=display,
        confidence=confidence,
        labels=labels,
    )


@dataclass(frozen=True)
class _Matrices:
    """A model's data as the fit needs them: response, fixed and random designs, group codes
    (0 … subjects − 1), patsy's description of ``x`` (terms, contrasts) and the names of the
    random effects (``Intercept`` and the slope's column)."""

    y: np.ndarray
    x: np.ndarray
    z: np.ndarray
    groups: np.ndarray
    design_info: Any
    re_names: list[str]


def _fit_matrices(
    matrices: _Matrices,
    *,
    subject: str,
    name: str,
    display: str,
    confidence: float,
    labels: Callable[[str], str] | None,
) -> MixedModelFit:
    """:func:`fit_mixed_model` once its design matrices are built."""
    if not 0 < confidence < 1:
        raise InvalidInputError(f"confidence must be between 0 and 1, got {confidence!r}")
    y, x, z, groups = matrices.y, matrices.x, matrices.z, matrices.groups
    re_names = matrices.re_names
    n_obs, k_fe = x.shape
    n_subjects = int(groups.max()) + 1 if len(groups) else 0
    n_params = k_fe + z.shape[1] * (z.shape[1] + 1) // 2 + 1
    if n_obs <= k_fe:
        raise CannotComputeError(
            f"the mixed model {display}",
            f"it has {k_fe} fixed effects but only {n_obs} observations",
        )
    if n_subjects < 2:
        raise CannotComputeError(f"the mixed model {display}", "it needs two or more subjects")
    if np.ptp(y) == 0:
        raise CannotComputeError(
            f"the mixed model {display}", f"every value is the same ({y[0]:g})"
        )
    if np.linalg.matrix_rank(x) < k_fe:
        raise CannotComputeError(
            f"the mixed model {display}",
            "its fixed effects are not all estimable from these data (collinear predictors)",
        )
    reml = RemlDesign(y, x, z, groups)
    if reml.residual_share() <= _NO_RESIDUAL:
        # y lies in the span of the fixed effects and every subject's random effects: REML has
        # no optimum (the likelihood grows without bound) and any F would be rounding error.
        raise CannotComputeError(
            f"the mixed model {display}",
            "its fixed and random effects reproduce every value to rounding error (no residual "
            "variation), so its variances and tests are undefined",
        )
    names = list(matrices.design_info.column_names)
    labels = labels or (lambda column: column)
    estimate = reml.refine()
    if not (np.isfinite(estimate.loglik) and estimate.max_gradient <= _GRADIENT_TOL):
        return MixedModelFit(
            **_empty_fit(name, display, n_obs, n_subjects, n_params),
            converged=False,
            problem=(
                f"{name} model did not converge (bfgs: stopped after {estimate.iterations} "
                f"iterations and Newton's steps with a REML gradient of "
                f"{estimate.max_gradient:.3g}); no estimates"
            ),
        )
    cov, jacobian = reml.beta_covariance_jacobian(estimate.varpar)
    notes: list[str] = []
    varpar_cov: np.ndarray | None
    try:
        varpar_cov = varpar_covariance(reml, estimate.varpar)
    except np.linalg.LinAlgError as error:
        varpar_cov = None
        notes.append(f"Satterthwaite df unavailable ({error}); tests use the normal approximation")
    inference = _Inference(beta=estimate.beta, cov=cov, jacobian=jacobian, varpar_cov=varpar_cov)
    scale = estimate.sigma**2
    notes.extend(_boundary_notes(estimate, re_names))
    fixed = _fixed_table(inference, names, labels, confidence)
    design_info = matrices.design_info
    tests = _term_tests(inference, design_info, labels)
    return MixedModelFit(
        name=name,
        formula=display,
        converged=True,
        problem="",
        notes=tuple(notes),
        df_method="Satterthwaite" if inference.satterthwaite else "normal approximation",
        optimizer="BFGS on lme4's profiled REML criterion",
        loglik=estimate.loglik,
        aic=-2 * estimate.loglik + 2 * n_params,
        n_obs=n_obs,
        n_subjects=n_subjects,
        n_params=n_params,
        fixed=fixed,
        tests=tests,
        variance=_variance_table(estimate.cov_re, scale, re_names, subject),
        inference=inference,
        design_info=design_info,
    )


def _empty_fit(
    name: str, display: str, n_obs: int, n_subjects: int, n_params: int
) -> dict[str, Any]:
    return {
        "name": name,
        "formula": display,
        "notes": (),
        "df_method": "",
        "optimizer": "",
        "loglik": float("nan"),
        "aic": float("nan"),
        "n_obs": n_obs,
        "n_subjects": n_subjects,
        "n_params": n_params,
        "fixed": pd.DataFrame(columns=list(FIXED_COLUMNS)),
        "tests": pd.DataFrame(columns=list(TEST_COLUMNS)),
        "variance": pd.DataFrame(columns=list(VARIANCE_COLUMNS)),
    }


def _boundary_notes(estimate: RemlFit, names: list[str]) -> list[str]:
    """Why a singular fit is singular: a variance estimated at zero, else a correlation of ±1
    (lme4's ``isSingular``: a diagonal element of the relative Cholesky factor below 10⁻⁴)."""
    if not estimate.singular:
        return []
    sds = np.sqrt(np.clip(np.diag(estimate.cov_re), 0, None))
    zero = sds < SINGULAR_TOL * estimate.sigma
    notes = [
        f"boundary (singular) fit: the {_re_label(re_name)} variance is estimated at zero"
        for re_name, is_zero in zip(names, zero, strict=True)
        if is_zero
    ]
    if not notes and len(sds) == 2:
        corr = estimate.cov_re[0, 1] / (sds[0] * sds[1])
        notes.append(f"boundary (singular) fit: the intercept–slope correlation is {corr:+.3f}")
    return notes or ["boundary (singular) fit: the random-effects covariance is singular"]


def _re_label(name: str) -> str:
    return "random-intercept" if name in ("Group", "Intercept") else f"random-slope ({name})"


def _fixed_table(
    inference: _Inference, names: list[str], labels: Callable[[str], str], confidence: float
) -> pd.DataFrame:
    rows = []
    for i, column in enumerate(names):
        row = np.zeros(len(names))
        row[i] = 1.0
        estimate, se, df = inference.contrast(row)
        t = estimate / se if se > 0 else float("nan")
        rows.append(
            {
                "term": labels(column),
                "estimate": estimate,
                "se": se,
                "df": df,
                "t": t,
                "p": _t_p(t, df),
            }
        )
    table = pd.DataFrame(rows, columns=list(FIXED_COLUMNS[:6]))
    low, high = _interval(table["estimate"], table["se"], table["df"], confidence)
    return table.assign(ci_low=low, ci_high=high)


def _interval(
    estimate: pd.Series, se: pd.Series, df: pd.Series, confidence: float
) -> tuple[np.ndarray, np.ndarray]:
    """t interval, or the normal one where df is infinite (no Satterthwaite)."""
    dfs = df.to_numpy(float)
    low, high = t_interval(
        estimate.to_numpy(float),
        se.to_numpy(float),
        np.where(np.isfinite(dfs), dfs, 1e9),
        confidence,
    )
    return low, high


def _t_p(t: float, df: float) -> float:
    if not np.isfinite(t) or not df > 0:
        return float("nan")
    return (
        float(2 * stats.t.sf(abs(t), df)) if np.isfinite(df) else float(2 * stats.norm.sf(abs(t)))
    )


def _term_tests(
    inference: _Inference, design_info: Any, labels: Callable[[str], str]
) -> pd.DataFrame:
    rows = []
    for term in design_info.terms:
        if not term.factors:  # the intercept
            continue
        matrix = _term_contrasts(design_info, term, len(inference.beta))
        f, df1, df2 = inference.f_test(matrix)
        p = (
            float(stats.f.sf(f, df1, df2))
            if np.isfinite(df2)
            else float(stats.chi2.sf(f * df1, df1))
        )
        name = term.name()
        rows.append(
            {"effect": name, "Source": labels(name), "F": f, "df1": df1, "df2": df2, "p": p}
        )
    return pd.DataFrame(rows, columns=list(TEST_COLUMNS))


def _term_contrasts(design_info: Any, term: Any, n_columns: int) -> np.ndarray:
    """The type III hypothesis of one term, written in lmerTest's basis.

    F is the same in any basis of the hypothesis, but the Satterthwaite df of a multi-df test
    (Fai & Cornelius' combination of one df per rotated contrast) is not. lmerTest's
    ``anova(type = 3)`` tests a factor coded with sum-to-zero contrasts as the differences of
    each level from the first (``level j − level 1`` of the marginal means), and an interaction
    as the products of those differences; this builds the same rows from patsy's contrast
    matrices (patsy varies the first factor of an interaction fastest, hence the reversed
    Kronecker product). Other codings keep the term's own columns.
    """
    columns = design_info.term_slices[term]
    identity = np.eye(n_columns)[columns]
    codings = design_info.term_codings[term]
    if len(codings) != 1:
        return identity
    subterm = codings[0]
    blocks: list[np.ndarray] = []
    for factor in subterm.factors:
        contrast = subterm.contrast_matrices.get(factor)
        if contrast is None:  # a numeric factor: its own columns
            blocks.append(np.eye(design_info.factor_infos[factor].num_columns))
            continue
        matrix = np.asarray(contrast.matrix, float)
        if not np.allclose(matrix.sum(axis=0), 0):  # not a sum-to-zero coding
            return identity
        blocks.append(matrix[1:] - matrix[0])
    rows: np.ndarray = blocks[-1]
    for block in reversed(blocks[:-1]):
        rows = np.kron(rows, block)
    if rows.shape[1] != columns.stop - columns.start:
        return identity
    full = np.zeros((rows.shape[0], n_columns))
    full[:, columns] = rows
    return full


def _variance_table(
    cov_re: np.ndarray, scale: float, names: list[str], subject: str
) -> pd.DataFrame:
    rows = []
    sds = np.sqrt(np.clip(np.diag(cov_re), 0, None))
    for i, re_name in enumerate(names):
        label = "(Intercept)" if re_name in ("Group", "Intercept") else re_name
        corr = float("nan")
        if i == 1 and sds[0] > 0 and sds[1] > 0:
            corr = float(cov_re[0, 1] / (sds[0] * sds[1]))
        rows.append(
            {
                "component": f"{subject}: {label}",
                "variance": float(cov_re[i, i]),
                "sd": float(sds[i]),
                "corr": corr,
            }
        )
    rows.append(
        {
            "component": "Residual",
            "variance": scale,
            "sd": float(np.sqrt(scale)),
            "corr": float("nan"),
        }
    )
    return pd.DataFrame(rows, columns=list(VARIANCE_COLUMNS))


# --- the study's model: between × within ---------------------------------------------------

_TERM = re.compile(r"C\((\w+), Sum\)\[S\.(.*?)\]")


def linear_mixed_models(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    random_slope: bool = True,
    within_levels: list[Any] | None = None,
    confidence: float = 0.95,
    covariates: Sequence[str] = (),
) -> LinearMixedModels:
    """The mixed-model counterpart of :func:`analysis.anova.mixed_anova`.

    Parameters
    ----------
    data : pandas.DataFrame
        Long format, one row per subject × within level (a missing row or NaN is allowed: the
        participant keeps the other ratings).
    dv, within, between, subject : str
        Column names.
    random_slope : bool
        Also fit ``(1 + within_step | subject)`` and compare it with the intercept model.
        ``within_step`` is the within level's position (0 for the first session, levels taken as
        equally spaced), so the random intercept is the participant's first-session level and the
        slope their change per session. Needs three or more within levels; with two the model is
        not fitted and ``slope_skipped`` says why.
    within_levels : list, optional
        The declared within levels (default: those in the data).
    confidence : float
        Coverage of every CI.
    covariates : sequence of str
        Participant-level categorical columns (e.g. ``language`` in a study run in several)
        added as main effects, sum-coded, so each gets its own type III test and the
        condition and session effects are adjusted for it. The estimated marginal means
        average over its levels with equal weights. Each needs one value per participant and
        two or more levels among those who rated.

    Returns
    -------
    LinearMixedModels

    Raises
    ------
    InvalidInputError, DuplicateObservationError
        As :func:`analysis.design.prepare_mixed_design`.
    CannotComputeError
        Fewer than two participants with a rating, only one between or within level, or data
        the random-intercept model reproduces exactly (no residual variation). When only the
        random-slope model reproduces them exactly, it alone is refused: its ``problem`` says
        why and the intercept model stands.

    Notes
    -----
    Both factors use sum-to-zero coding, so each term's F test is type III, as in the ANOVA.
    With balanced complete data and a positive participant variance, the random-intercept
    model's F for the within effect and the interaction equal the RM-ANOVA's (under compound
    symmetry); the mixed model differs where the ANOVA drops incomplete participants.
    References: Kuznetsova et al. (2017), lmerTest; Stram & Lee (1994) for the boundary LRT.
    """
    # Validation (columns, numbers, duplicates, one group per subject) and the ANOVA's list of
    # participants it would drop, from the same code as the ANOVA.
    design = prepare_mixed_design(
        data, dv=dv, within=within, between=between, subject=subject, within_levels=within_levels
    )
    levels = list(design.within_levels)
    frame = pd.DataFrame(
        {
            "y": pd.to_numeric(data[dv], errors="coerce").to_numpy(float),
            "subject": _as_text(data[subject]),
            "between": data[between].to_numpy(),
            "within": data[within].to_numpy(),
        }
    )
    covariate_names = _covariate_columns(data, covariates, subject, (dv, within, between, subject))
    for column, name in covariate_names.items():
        frame[column] = _as_text(data[name])
    frame = frame[np.isfinite(frame["y"])].reset_index(drop=True)
    for column, name in covariate_names.items():
        if frame[column].nunique() < 2:
            raise InvalidInputError(
                f"covariate {name!r} has one level among the participants who rated: leave it out"
            )
    if len(frame) and frame["y"].nunique() == 1:
        raise CannotComputeError(
            f"the mixed model of {dv!r}", f"every rating is the same ({frame['y'].iloc[0]:g})"
        )
    group_levels = ordered_levels(data.loc[data[dv].notna(), between])
    rated = set(frame["within"].unique())
    present_levels = [lv for lv in levels if lv in rated]
    if frame["subject"].nunique() < 2:
        raise CannotComputeError(f"the mixed model of {dv!r}", "fewer than two participants rated")
    if len(group_levels) < 2 or len(present_levels) < 2:
        raise CannotComputeError(
            f"the mixed model of {dv!r}",
            f"it needs two or more levels of {between!r} and of {within!r} with ratings",
        )
    what = f"the mixed model of {dv!r}"
    refuse_empty_cells(frame["between"], frame["within"], group_levels, present_levels, what)
    frame["between"] = pd.Categorical(frame["between"], categories=group_levels)
    frame["within"] = pd.Categorical(frame["within"], categories=present_levels)
    frame["within_step"] = frame["within"].cat.codes.astype(float)
    slope_skipped = ""
    if random_slope and len(present_levels) < 3:
        # With two ratings per participant, intercept variance, slope variance, their
        # covariance and the residual cannot be told apart (lme4 refuses this model too).
        slope_skipped = (
            f"a random slope needs three or more levels of {within!r} (there are "
            f"{len(present_levels)}): with two ratings per participant it cannot be told apart "
            "from the residual"
        )
        random_slope = False
    formula = "y ~ C(between, Sum) * C(within, Sum)" + "".join(
        f" + C({column}, Sum)" for column in covariate_names
    )
    labels = term_labeller(between, within, covariate_names)
    base = f"{dv} ~ {between} * {within}" + "".join(f" + {n}" for n in covariate_names.values())
    covariate_levels = {column: sorted(frame[column].unique()) for column in covariate_names}
    study = _study_design(
        frame, formula, {"between": group_levels, "within": present_levels, **covariate_levels}
    )
    intercept = study.matrices
    fits = [
        _fit_matrices(
            intercept,
            subject="subject",
            name="random intercept",
            display=f"{base} + (1 | {subject})",
            confidence=confidence,
            labels=labels,
        )
    ]
    if random_slope:
        slope_display = f"{base} + (1 + {within}_step | {subject})"
        try:
            slope = _fit_matrices(
                replace(
                    intercept,
                    z=np.column_stack([intercept.z, frame["within_step"].to_numpy(float)]),
                    re_names=["Intercept", "within_step"],
                ),
                subject="subject",
                name="random slope",
                display=slope_display,
                confidence=confidence,
                labels=labels,
            )
        except CannotComputeError as error:  # e.g. no residual left: the intercept model stands
            empty = _empty_fit(
                "random slope",
                slope_display,
                fits[0].n_obs,
                fits[0].n_subjects,
                fits[0].n_params + 2,
            )
            slope = MixedModelFit(**empty, converged=False, problem=str(error))
        fits.append(slope)
    fits = [
        _with_emmeans(fit, between, within, group_levels, present_levels, confidence, study.cells)
        for fit in fits
    ]
    fits = [_study_names(fit, subject, within, covariate_names) for fit in fits]
    kept = design.excluded[design.excluded["subject"].astype(str).isin(set(frame["subject"]))]
    return LinearMixedModels(
        dv=dv,
        within=within,
        between=between,
        subject=subject,
        intercept=fits[0],
        slope=fits[1] if random_slope else None,
        comparison=_compare(fits[0], fits[1]) if random_slope else None,
        slope_skipped=slope_skipped,
        within_levels=tuple(to_python(level) for level in present_levels),
        kept=kept.reset_index(drop=True),
        n_obs=len(frame),
        n_subjects=int(frame["subject"].nunique()),
    )


def _as_text(column: pd.Series) -> np.ndarray:
    """``column.map(to_python).astype(str)``, converting each distinct value once (a Python
    call per rating cost a tenth of a second at 10,000 participants)."""
    codes, uniques = pd.factorize(column, use_na_sentinel=False)
    return np.array([str(to_python(value)) for value in uniques], dtype=object)[codes]


@dataclass(frozen=True)
class _StudyDesign:
    """The study model's matrices and the fixed-effect row of each between × within cell's
    marginal mean (between levels outer, within inner; covariates averaged with equal weights,
    as emmeans does by default)."""

    matrices: _Matrices
    cells: np.ndarray


def _study_design(frame: pd.DataFrame, formula: str, factors: dict[str, list[Any]]) -> _StudyDesign:
    """``X`` built by patsy once, for every combination of the factors' levels.

    ``X`` depends on a rating's between, within and covariate levels only, so each rating takes
    its combination's row: the same matrix as patsy on every rating, without patsy's per-value
    conversion of ``C(x, Sum)`` (a Python call per rating, a second at 10,000 participants),
    and the marginal means' rows are averages of the same rows (no second patsy design)."""
    from patsy import dmatrices

    grid = pd.DataFrame(list(itertools.product(*factors.values())), columns=list(factors))
    for column, levels in factors.items():
        grid[column] = pd.Categorical(grid[column], categories=levels)
    grid["y"] = 0.0
    _, exog = dmatrices(formula, grid, NA_action="raise")
    full = np.asarray(exog, float)
    codes = [pd.Categorical(frame[c], categories=levels).codes for c, levels in factors.items()]
    index = np.ravel_multi_index(codes, [len(levels) for levels in factors.values()])
    n_cells = len(factors["between"]) * len(factors["within"])
    return _StudyDesign(
        matrices=_Matrices(
            y=frame["y"].to_numpy(float),
            x=full[index],
            z=np.ones((len(frame), 1)),
            groups=pd.factorize(frame["subject"])[0],
            design_info=exog.design_info,
            re_names=["Intercept"],
        ),
        cells=full.reshape(n_cells, -1, full.shape[1]).mean(axis=1),
    )


def _covariate_columns(
    data: pd.DataFrame, covariates: Sequence[str], subject: str, taken: Sequence[str]
) -> dict[str, str]:
    """The model's column for each covariate (``cov0``…), after checking it can be one."""
    columns = {}
    for index, name in enumerate(covariates):
        if name not in data.columns:
            raise InvalidInputError(f"no covariate column {name!r}; columns: {list(data.columns)}")
        if name in taken:
            raise InvalidInputError(f"{name!r} is already in the model; it cannot be a covariate")
        if data[name].isna().any():
            raise InvalidInputError(f"covariate {name!r} has missing values")
        if (data.groupby(subject)[name].nunique() > 1).any():
            raise InvalidInputError(
                f"covariate {name!r} must have one value per participant ({subject!r})"
            )
        columns[f"cov{index}"] = name
    return columns


def term_labeller(
    between: str, within: str, covariates: dict[str, str] | None = None
) -> Callable[[str], str]:
    """Readable names of the patsy columns and terms.

    ``C(between, Sum)[S.C1]`` becomes ``condition[C1]`` and ``C(between, Sum):C(within, Sum)``
    becomes ``condition × session``; ``covariates`` maps a covariate's model column (``cov0``)
    to its name (``language``)."""
    names = {"between": between, "within": within, **(covariates or {})}

    def label(column: str) -> str:
        if column == "Intercept":
            return "(Intercept)"
        text = _TERM.sub(lambda m: f"{names[m[1]]}[{m[2]}]", column)
        text = re.sub(r"C\((\w+), Sum\)", lambda m: names[m[1]], text)
        return text.replace(":", " × ") if "[" not in text else text

    return label


def _with_emmeans(
    fit: MixedModelFit,
    between: str,
    within: str,
    group_levels: list[Any],
    within_levels: list[Any],
    confidence: float,
    rows: np.ndarray,
) -> MixedModelFit:
    """Each condition × session cell's estimated marginal mean: ``rows`` (one per cell,
    between levels outer) times β, with its SE and Satterthwaite df."""
    if not fit.converged or fit.inference is None:
        empty = pd.DataFrame(columns=[between, within, *EMM_COLUMNS])
        return replace(fit, emmeans=empty)
    stats_rows = [fit.inference.contrast(row) for row in rows]
    table = pd.DataFrame(
        {
            between: [to_python(b) for b in group_levels for _ in within_levels],
            within: [to_python(w) for _ in group_levels for w in within_levels],
            "emmean": [s[0] for s in stats_rows],
            "se": [s[1] for s in stats_rows],
            "df": [s[2] for s in stats_rows],
        }
    )
    low, high = _interval(table["emmean"], table["se"], table["df"], confidence)
    return replace(fit, emmeans=table.assign(ci_low=low, ci_high=high))


def _study_names(
    fit: MixedModelFit, subject: str, within: str, covariates: dict[str, str] | None = None
) -> MixedModelFit:
    effects = {
        "C(between, Sum)": "between",
        "C(within, Sum)": "within",
        "C(between, Sum):C(within, Sum)": "interaction",
        **{f"C({column}, Sum)": name for column, name in (covariates or {}).items()},
    }
    tests = fit.tests.assign(effect=fit.tests["effect"].map(lambda e: effects.get(e, e)))
    variance = fit.variance.assign(
        component=fit.variance["component"]
        .str.replace("subject: ", f"{subject}: ", regex=False)
        .str.replace("within_step", f"{within}_step", regex=False)
    )
    return replace(fit, variance=variance, tests=tests)


def _compare(intercept: MixedModelFit, slope: MixedModelFit) -> dict[str, Any] | None:
    """LRT and AIC of the two REML fits (same fixed effects, so REML likelihoods compare)."""
    if not (intercept.converged and slope.converged):
        return None
    chi2 = max(0.0, 2 * (slope.loglik - intercept.loglik))
    df = slope.n_params - intercept.n_params
    p = 0.5 * stats.chi2.sf(chi2, df - 1) + 0.5 * stats.chi2.sf(chi2, df)
    preferred = slope.name if slope.aic < intercept.aic and p < 0.05 else intercept.name
    return {
        "chi2": chi2,
        "df": df,
        "p": float(p),
        "aic_intercept": intercept.aic,
        "aic_slope": slope.aic,
        "preferred": preferred,
    }
