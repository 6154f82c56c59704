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
    rows: list[dict[str, Any]] = []
    for k, group in enumerate(design.group_levels):
        block = y[g == k]
        for a, b in combinations(range(design.n_levels), 2):
            row = _paired(block[:, a], block[:, b])
            row.update(
                family=FAMILY_WITHIN,
                factor=design.within,
                at=group,
                A=design.within_levels[a],
                B=design.within_levels[b],
            )
            rows.append(row)
    for s, level in enumerate(design.within_levels):
        for a, b in combinations(range(len(design.group_levels)), 2):
            row = _independent(y[g == a, s], y[g == b, s])
            row.update(
                family=FAMILY_BETWEEN,
                factor=design.between,
                at=level,
                A=design.group_levels[a],
                B=design.group_levels[b],
            )
            rows.append(row)
    out = pd.DataFrame(rows)
    if out.empty:
        return pd.DataFrame(columns=list(POSTHOC_COLUMNS))
    out["p_adj"] = np.nan
    for family in (FAMILY_WITHIN, FAMILY_BETWEEN):
        mask = out["family"] == family
        out.loc[mask, "p_adj"] = adjust_pvalues(out.loc[mask, "p_unc"].to_numpy(), padjust)
    out["p_adjust"] = padjust
    return out[list(POSTHOC_COLUMNS)]


def _paired(x: np.ndarray, y: np.ndarray) -> dict[str, Any]:
    n = len(x)
    diff = x - y
    row: dict[str, Any] = {
        "n_A": n,
        "n_B": n,
        "mean_A": float(x.mean()),
        "mean_B": float(y.mean()),
        "mean_diff": float(diff.mean()),
        "paired": True,
        "welch": False,
        "T": np.nan,
        "dof": float(n - 1),
        "p_unc": np.nan,
        "cohen_d": np.nan,
        "note": "",
    }
    if n < 2:
        row["note"] = "needs at least two participants"
        return row
    sd_diff = float(diff.std(ddof=1))
    if sd_diff == 0:
        row["note"] = "the differences have zero variance; t is undefined"
        return row
    t = float(diff.mean() / (sd_diff / np.sqrt(n)))
    row["T"] = t
    row["p_unc"] = float(2 * stats.t.sf(abs(t), n - 1))
    sd_av = np.sqrt((x.var(ddof=1) + y.var(ddof=1)) / 2)
    row["cohen_d"] = float(diff.mean() / sd_av) if sd_av > 0 else np.nan
    return row


def _independent(x: np.ndarray, y: np.ndarray) -> dict[str, Any]:
    nx, ny = len(x), len(y)
    welch = nx != ny
    row: dict[str, Any] = {
        "n_A": nx,
        "n_B": ny,
        "mean_A": float(x.mean()) if nx else np.nan,
        "mean_B": float(y.mean()) if ny else np.nan,
        "mean_diff": float(x.mean() - y.mean()) if nx and ny else np.nan,
        "paired": False,
        "welch": welch,
        "T": np.nan,
        "dof": np.nan,
        "p_unc": np.nan,
        "cohen_d": np.nan,
        "note": "",
    }
    if nx < 2 or ny < 2:
        row["note"] = "needs at least two participants per group"
        return row
    vx, vy = float(x.var(ddof=1)), float(y.var(ddof=1))
    pooled = ((nx - 1) * vx + (ny - 1) * vy) / (nx + ny - 2)
    if pooled == 0:
        row["note"] = "both groups have zero variance; t is undefined"
        return row
    if welch:
        se2 = vx / nx + vy / ny
        dof = se2**2 / ((vx / nx) ** 2 / (nx - 1) + (vy / ny) ** 2 / (ny - 1))
    else:
        se2 = pooled * (1 / nx + 1 / ny)
        dof = nx + ny - 2
    t = float((x.mean() - y.mean()) / np.sqrt(se2))
    row.update(
        T=t,
        dof=float(dof),
        p_unc=float(2 * stats.t.sf(abs(t), dof)),
        cohen_d=float((x.mean() - y.mean()) / np.sqrt(pooled)),
    )
    return row
