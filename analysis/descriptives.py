"""Descriptive statistics of a mixed design: cell summaries and estimated marginal means.

PIs read the ANOVA next to the numbers it explains: the mean, spread and 95 % confidence
interval of each condition × session cell (the paper's figures), and the estimated marginal
means that the main effects compare.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import pandas as pd
from scipy import stats

from analysis._checks import (
    numeric_values,
    ordered_levels,
    require_columns,
    require_distinct,
    require_frame,
    require_no_missing,
    to_python,
)
from analysis.design import MixedDesign, prepare_mixed_design
from analysis.errors import CannotComputeError, InvalidInputError

__all__ = [
    "CELL_COLUMNS",
    "MARGINAL_COLUMNS",
    "cell_descriptives",
    "marginal_means",
    "marginal_means_from_design",
    "t_interval",
]

CELL_COLUMNS = ("n", "mean", "sd", "se", "ci_low", "ci_high")
"""Statistic columns of :func:`cell_descriptives` (after the two factor columns)."""

MARGINAL_COLUMNS = ("n", "mean", "se", "df", "ci_low", "ci_high")
"""Statistic columns of :func:`marginal_means` (after the factor column)."""


def t_interval(
    mean: np.ndarray, se: np.ndarray, df: np.ndarray, confidence: float = 0.95
) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided t confidence interval ``mean ± t(1 − α/2, df) · se`` (NaN where df < 1)."""
    if not 0 < confidence < 1:
        raise InvalidInputError(f"confidence must be between 0 and 1, got {confidence}")
    df_arr = np.asarray(df, dtype=float)
    with np.errstate(invalid="ignore"):
        crit = np.where(
            df_arr >= 1, stats.t.ppf(0.5 + confidence / 2, np.maximum(df_arr, 1)), np.nan
        )
    half = crit * np.asarray(se, dtype=float)
    return np.asarray(mean) - half, np.asarray(mean) + half


def cell_descriptives(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    confidence: float = 0.95,
) -> pd.DataFrame:
    """n, mean, SD, SE and t-based confidence interval of every between × within cell.

    Parameters
    ----------
    data : pandas.DataFrame
        Long format with columns ``dv``, ``within`` and ``between``.
    dv, within, between : str
        Column names.
    confidence : float
        Coverage of the interval (default 0.95).

    Returns
    -------
    pandas.DataFrame
        Columns ``between``, ``within`` (named as in ``data``), then :data:`CELL_COLUMNS`, one row
        per cell in factor order. ``sd``/``se``/CI are NaN in a cell with a single value.

    Notes
    -----
    Exclusions: rows with a missing ``dv`` are not counted. The descriptives use whichever rows
    are passed: give them ``MixedDesign.long()`` to describe exactly the ANOVA's participants.
    SD uses ``n − 1``; the CI is ``M ± t(n − 1) · SD/√n``.
    """
    data = require_frame(data)
    require_columns(data, [dv, within, between])
    require_distinct(dv=dv, within=within, between=between)
    require_no_missing(data, [within, between])
    values = numeric_values(data, dv)
    ok = ~np.isnan(values)
    if not ok.any():
        raise CannotComputeError("descriptives", f"column {dv!r} has no non-missing value")
    b_levels = ordered_levels(data[between])
    w_levels = ordered_levels(data[within])
    b_codes = pd.Index(b_levels).get_indexer(data[between])[ok]
    w_codes = pd.Index(w_levels).get_indexer(data[within])[ok]
    y = values[ok]
    cell = b_codes.astype(np.int64) * len(w_levels) + w_codes
    cells, inverse = np.unique(cell, return_inverse=True)
    n = np.bincount(inverse)
    mean = np.bincount(inverse, weights=y) / n
    ss = np.bincount(inverse, weights=(y - mean[inverse]) ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = np.where(n > 1, np.sqrt(ss / np.maximum(n - 1, 1)), np.nan)
    se = sd / np.sqrt(n)
    low, high = t_interval(mean, se, n - 1, confidence)
    b_index, w_index = np.divmod(cells, len(w_levels))
    return pd.DataFrame(
        {
            between: [to_python(b_levels[i]) for i in b_index],
            within: [to_python(w_levels[i]) for i in w_index],
            "n": n.astype(int),
            "mean": mean,
            "sd": sd,
            "se": se,
            "ci_low": low,
            "ci_high": high,
        }
    )


def marginal_means(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    by: Literal["between", "within"] = "between",
    confidence: float = 0.95,
    within_levels: Sequence[Any] | None = None,
) -> pd.DataFrame:
    """Estimated marginal means (M, SE, CI) of the conditions (default) or of the sessions.

    Parameters
    ----------
    data : pandas.DataFrame
        Long format, as for :func:`analysis.anova.mixed_anova`.
    dv, within, between, subject : str
        Column names.
    by : {"between", "within"}
        Marginalise over sessions to get one mean per condition, or over conditions to get one
        mean per session.
    confidence : float
        Coverage of the t interval.
    within_levels : sequence, optional
        Levels every participant must have (see :func:`analysis.design.prepare_mixed_design`).

    Returns
    -------
    pandas.DataFrame
        Columns: the factor (named as in ``data``), then :data:`MARGINAL_COLUMNS`.

    Notes
    -----
    Exclusions: computed on the complete cases of the mixed ANOVA (participants with every
    within level), so they describe the same model.

    Condition means are the mean of the participants' session means, with
    ``SE = √(s²_pooled / n_g)`` where ``s²_pooled`` is the pooled within-group variance of the
    participant means (``df = N − G``). Session means are the unweighted average of the
    condition cell means, with ``SE = √(Σ_g s²_s / n_g) / G`` and ``s²_s`` the pooled
    within-group variance at that session (``df = N − G``). This is the multivariate model that
    afex (≥ 1.0) hands to emmeans, so unequal groups are weighted equally (type III logic).
    """
    design = prepare_mixed_design(
        data, dv=dv, within=within, between=between, subject=subject, within_levels=within_levels
    )
    return marginal_means_from_design(design, by=by, confidence=confidence)


def marginal_means_from_design(
    design: MixedDesign,
    *,
    by: Literal["between", "within"] = "between",
    confidence: float = 0.95,
) -> pd.DataFrame:
    """:func:`marginal_means` on an already prepared design (same participants as the ANOVA)."""
    if by not in ("between", "within"):
        raise InvalidInputError(f"by must be 'between' or 'within', got {by!r}")
    n_groups = len(design.group_levels)
    df_err = design.n_subjects - n_groups
    if design.n_subjects == 0:
        raise CannotComputeError("marginal means", "no participant has complete data")
    if df_err < 1:
        raise CannotComputeError(
            "marginal means",
            "there are no error degrees of freedom (each group has a single participant)",
        )
    y, g = design.values, design.groups
    n_g = design.group_sizes.astype(float)
    cell_mean = np.vstack([y[g == k].mean(axis=0) for k in range(n_groups)])  # (G, S)
    if by == "between":
        subj_mean = y.mean(axis=1)
        group_mean = cell_mean.mean(axis=1)
        pooled = float(np.sum((subj_mean - group_mean[g]) ** 2)) / df_err
        mean = group_mean
        se = np.sqrt(pooled / n_g)
        n = design.group_sizes
        factor, levels = design.between, design.group_levels
    else:
        pooled_s = np.sum((y - cell_mean[g]) ** 2, axis=0) / df_err  # (S,)
        mean = cell_mean.mean(axis=0)
        se = np.sqrt(pooled_s * float(np.sum(1.0 / n_g))) / n_groups
        n = np.full(design.n_levels, design.n_subjects)
        factor, levels = design.within, design.within_levels
    df = np.full(len(levels), float(df_err))
    low, high = t_interval(mean, se, df, confidence)
    return pd.DataFrame(
        {
            factor: list(levels),
            "n": np.asarray(n, dtype=int),
            "mean": mean,
            "se": se,
            "df": df,
            "ci_low": low,
            "ci_high": high,
        }
    )
