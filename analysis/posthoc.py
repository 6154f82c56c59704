"""Post-hoc pairwise comparisons for a mixed design, Holm-corrected.

After an interaction the PI asks two questions: in which sessions do the conditions differ
(independent t tests at each session), and between which sessions does trust change within a
condition (paired t tests). Each question is one family of tests for the multiple-comparison
correction.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations
from typing import Any, Literal

import numpy as np
import pandas as pd
from scipy import stats

from analysis.design import MixedDesign, prepare_mixed_design
from analysis.errors import CannotComputeError, InvalidInputError

__all__ = [
    "POSTHOC_COLUMNS",
    "PAdjust",
    "adjust_pvalues",
    "pairwise_comparisons",
    "pairwise_comparisons_from_design",
]

PAdjust = Literal["holm", "bonferroni", "none"]

POSTHOC_COLUMNS = (
    "family",
    "factor",
    "at",
    "A",
    "B",
    "n_A",
    "n_B",
    "mean_A",
    "mean_B",
    "mean_diff",
    "paired",
    "welch",
    "T",
    "dof",
    "p_unc",
    "p_adj",
    "p_adjust",
    "cohen_d",
    "note",
)
"""Columns of :func:`pairwise_comparisons`."""

FAMILY_WITHIN = "within"
"""Family label: levels of the within factor compared inside each group (paired tests)."""
FAMILY_BETWEEN = "between"
"""Family label: groups compared at each within level (independent tests)."""


def adjust_pvalues(p: Sequence[float] | np.ndarray, method: PAdjust = "holm") -> np.ndarray:
    """Adjust a family of p values (Holm 1979 step-down, Bonferroni, or none).

    NaN p values are left NaN and do not count towards the family size.
    """
    p_arr = np.asarray(p, dtype=float)
    out = np.full_like(p_arr, np.nan)
    ok = ~np.isnan(p_arr)
    m = int(ok.sum())
    if method == "none" or m == 0:
        out[ok] = p_arr[ok]
        return out
    if method == "bonferroni":
        out[ok] = np.minimum(p_arr[ok] * m, 1.0)
        return out
    if method != "holm":
        raise InvalidInputError(f"padjust must be 'holm', 'bonferroni' or 'none', got {method!r}")
    vals = p_arr[ok]
    order = np.argsort(vals, kind="stable")
    stepped = np.maximum.accumulate((m - np.arange(m)) * vals[order])
    adjusted = np.empty(m)
    adjusted[order] = np.minimum(stepped, 1.0)
    out[ok] = adjusted
    return out


def pairwise_comparisons(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    padjust: PAdjust = "holm",
    within_levels: Sequence[Any] | None = None,
) -> pd.DataFrame:
    """Sessions compared within each condition and conditions compared within each session.

    Parameters
    ----------
    data : pandas.DataFrame
        Long format, as for :func:`analysis.anova.mixed_anova`.
    dv, within, between, subject : str
        Column names.
    padjust : {"holm", "bonferroni", "none"}
        Correction applied separately to each family (default Holm).
    within_levels : sequence, optional
        Levels every participant must have.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`POSTHOC_COLUMNS`. ``family`` is ``"within"`` (paired t tests between
        every pair of within levels, ``at`` = the group) or ``"between"`` (independent t tests
        between every pair of groups, ``at`` = the within level). ``mean_diff = mean_A − mean_B``.

    Notes
    -----
    Exclusions: the complete cases of the mixed ANOVA (participants with every within level).

    A family is every comparison of one kind (all paired comparisons, or all independent
    comparisons), as in pingouin's ``pairwise_tests`` for the interaction, so the Holm
    correction accounts for all tests the PI looks at together. Independent tests use Student's
    t with equal group sizes and Welch's t with unequal sizes (Zimmerman, 2004; pingouin's
    ``correction="auto"``). Cohen's d uses the pooled SD for independent groups and the average
    of the two variances (d_av; Cumming, 2012) for paired data. A comparison whose test is
    undefined (e.g. zero variance) has NaN statistics and a ``note``; it is not counted in its
    family's correction.

    References
    ----------
    Holm, S. (1979). Scand. J. Statist., 6, 65–70. Zimmerman, D. W. (2004). Br. J. Math.
    Stat. Psychol., 57, 173–181. Cumming, G. (2012). Understanding the New Statistics.
    """
    design = prepare_mixed_design(
        data, dv=dv, within=within, between=between, subject=subject, within_levels=within_levels
    )
    return pairwise_comparisons_from_design(design, padjust=padjust)


def pairwise_comparisons_from_design(
    design: MixedDesign, *, padjust: PAdjust = "holm"
) -> pd.DataFrame:
    """:func:`pairwise_comparisons` on an already prepared design."""
    if padjust not in ("holm", "bonferroni", "none"):
        raise InvalidInputError(f"padjust must be 'holm', 'bonferroni' or 'none', got {padjust!r}")
    if design.n_subjects == 0:
        raise CannotComputeError("post-hoc comparisons", "no participant has complete data")
    y, g = design.values, design.groups
    parts: list[dict[str, Any]] = []
    pairs_within = list(combinations(range(design.n_levels), 2))
    a_idx = np.array([a for a, _ in pairs_within], dtype=np.intp)
    b_idx = np.array([b for _, b in pairs_within], dtype=np.intp)
    for k, group in enumerate(design.group_levels):
        if not pairs_within:
            break
        block = y[g == k]
        part = _paired(block[:, a_idx], block[:, b_idx])
        part.update(
            family=FAMILY_WITHIN,
            factor=design.within,
            at=[group] * len(pairs_within),
            A=[design.within_levels[a] for a in a_idx],
            B=[design.within_levels[b] for b in b_idx],
        )
        parts.append(part)
    pairs_between = list(combinations(range(len(design.group_levels)), 2))
    between_parts = []
    for a, b in pairs_between:
        part = _independent(y[g == a], y[g == b])
        part.update(
            family=FAMILY_BETWEEN,
            factor=design.between,
            at=list(design.within_levels),
            A=[design.group_levels[a]] * design.n_levels,
            B=[design.group_levels[b]] * design.n_levels,
        )
        between_parts.append(part)
    if between_parts:
        # Order the between family by within level (then pair), as people read it.
        merged = _concat(between_parts)
        order = np.argsort(np.tile(np.arange(design.n_levels), len(between_parts)), kind="stable")
        parts.append(
            {key: np.asarray(values, dtype=object)[order] for key, values in merged.items()}
        )
    if not parts:
        return pd.DataFrame(columns=list(POSTHOC_COLUMNS))
    columns = _concat(parts)
    family = np.asarray(columns["family"], dtype=object)
    p_unc = np.asarray(columns["p_unc"], dtype=float)
    p_adj = np.full(len(p_unc), np.nan)
    for name in (FAMILY_WITHIN, FAMILY_BETWEEN):
        mask = family == name
        p_adj[mask] = adjust_pvalues(p_unc[mask], padjust)
    columns["p_adj"] = p_adj
    columns["p_adjust"] = padjust
    out = pd.DataFrame({key: columns[key] for key in POSTHOC_COLUMNS})
    for key in ("T", "dof", "p_unc", "cohen_d", "mean_A", "mean_B", "mean_diff"):
        out[key] = out[key].astype(float)
    for key in ("n_A", "n_B"):
        out[key] = out[key].astype(int)
    for key in ("paired", "welch"):
        out[key] = out[key].astype(bool)
    return out


def _concat(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Concatenate column dicts; scalar entries are broadcast to their part's length."""
    out: dict[str, list[Any]] = {}
    for part in parts:
        length = len(part["T"])
        for key, value in part.items():
            values = list(value) if isinstance(value, (list, np.ndarray)) else [value] * length
            out.setdefault(key, []).extend(values)
    return out


def _paired(x: np.ndarray, y: np.ndarray) -> dict[str, Any]:
    """Paired t tests column by column (x, y: participants × comparisons)."""
    n, m = x.shape
    diff = x - y
    mean_diff = diff.mean(axis=0) if n else np.full(m, np.nan)
    note = np.full(m, "", dtype=object)
    t = np.full(m, np.nan)
    p = np.full(m, np.nan)
    d = np.full(m, np.nan)
    if n < 2:
        note[:] = "needs at least two participants"
    else:
        sd_diff = diff.std(axis=0, ddof=1)
        zero = sd_diff == 0
        note[zero] = "the differences have zero variance; t is undefined"
        ok = ~zero
        t[ok] = mean_diff[ok] / (sd_diff[ok] / np.sqrt(n))
        p[ok] = 2 * stats.t.sf(np.abs(t[ok]), n - 1)
        sd_av = np.sqrt((x.var(axis=0, ddof=1) + y.var(axis=0, ddof=1)) / 2)
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.where(sd_av > 0, mean_diff / sd_av, np.nan)
    return {
        "n_A": np.full(m, n),
        "n_B": np.full(m, n),
        "mean_A": x.mean(axis=0) if n else np.full(m, np.nan),
        "mean_B": y.mean(axis=0) if n else np.full(m, np.nan),
        "mean_diff": mean_diff,
        "paired": True,
        "welch": False,
        "T": t,
        "dof": np.full(m, float(n - 1)),
        "p_unc": p,
        "cohen_d": d,
        "note": note,
    }


def _independent(x: np.ndarray, y: np.ndarray) -> dict[str, Any]:
    """Independent t tests column by column (x: n_x × levels, y: n_y × levels)."""
    nx, ny = x.shape[0], y.shape[0]
    m = x.shape[1]
    welch = nx != ny
    mean_x = x.mean(axis=0) if nx else np.full(m, np.nan)
    mean_y = y.mean(axis=0) if ny else np.full(m, np.nan)
    note = np.full(m, "", dtype=object)
    t = np.full(m, np.nan)
    p = np.full(m, np.nan)
    dof = np.full(m, np.nan)
    d = np.full(m, np.nan)
    if nx < 2 or ny < 2:
        note[:] = "needs at least two participants per group"
    else:
        vx, vy = x.var(axis=0, ddof=1), y.var(axis=0, ddof=1)
        pooled = ((nx - 1) * vx + (ny - 1) * vy) / (nx + ny - 2)
        zero = pooled == 0
        note[zero] = "both groups have zero variance; t is undefined"
        ok = ~zero
        if welch:
            se2 = vx / nx + vy / ny
            with np.errstate(invalid="ignore", divide="ignore"):
                dof = se2**2 / ((vx / nx) ** 2 / (nx - 1) + (vy / ny) ** 2 / (ny - 1))
        else:
            se2 = pooled * (1 / nx + 1 / ny)
            dof = np.full(m, float(nx + ny - 2))
        dof = np.where(ok, dof, np.nan)
        t[ok] = (mean_x[ok] - mean_y[ok]) / np.sqrt(se2[ok])
        p[ok] = 2 * stats.t.sf(np.abs(t[ok]), dof[ok])
        d[ok] = (mean_x[ok] - mean_y[ok]) / np.sqrt(pooled[ok])
    return {
        "n_A": np.full(m, nx),
        "n_B": np.full(m, ny),
        "mean_A": mean_x,
        "mean_B": mean_y,
        "mean_diff": mean_x - mean_y,
        "paired": False,
        "welch": welch,
        "T": t,
        "dof": dof,
        "p_unc": p,
        "cohen_d": d,
        "note": note,
    }
