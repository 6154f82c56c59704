"""Mixed (split-plot) ANOVA: one between-subject factor × one within-subject factor.

The trust ratings of the study are a 2 (condition) × S (session) mixed design, and PIs compare the
numbers with SPSS, JASP, jamovi or R's afex. Those default to type III sums of squares, while
pingouin (type II) gives a different within-subject effect as soon as the groups are unequal,
e.g. after dropouts. This module computes both from the same wide matrix with numpy (fast enough
for 10,000 participants), always reports the sphericity columns, and computes every p value from
its F and degrees of freedom.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pandas as pd
from scipy import stats

from analysis._checks import to_python
from analysis.design import MixedDesign, prepare_mixed_design
from analysis.errors import CannotComputeError, InvalidInputError

__all__ = [
    "ANOVA_COLUMNS",
    "EFFECTS",
    "MixedAnovaResult",
    "SSType",
    "Sphericity",
    "mixed_anova",
    "mixed_anova_from_design",
    "orthonormal_contrasts",
]

SSType = Literal[2, 3]
EFFECTS = ("between", "within", "interaction")
"""Row order (and the ``effect`` column) of every ANOVA table."""

ANOVA_COLUMNS = (
    "effect",
    "Source",
    "SS",
    "DF1",
    "DF2",
    "MS",
    "F",
    "p_unc",
    "np2",
    "ng2",
    "eps",
    "p_GG_corr",
    "W_spher",
    "p_spher",
    "ss_type",
)
"""Columns of :attr:`MixedAnovaResult.table`, always all present."""

_REL_TOL = 1e-10


@dataclass(frozen=True)
class Sphericity:
    """Mauchly's test and the Greenhouse–Geisser epsilon of the within factor.

    Attributes
    ----------
    W : float
        Mauchly's W (1 with two within levels, 0 when the covariance matrix is singular).
    p : float or None
        p value of Mauchly's test (R's ``mauchly.test`` approximation); ``None`` when the test
        is undefined because there are fewer error degrees of freedom than within contrasts.
    eps_gg : float
        Greenhouse–Geisser epsilon, shared by the within effect and the interaction.
    chi2, dof : float
        The test's chi-square statistic and degrees of freedom.
    note : str
        Why a value is degenerate (empty when the test is ordinary).
    """

    W: float
    p: float | None
    eps_gg: float
    chi2: float
    dof: float
    note: str = ""


@dataclass(frozen=True)
class MixedAnovaResult:
    """Result of :func:`mixed_anova`.

    Attributes
    ----------
    table : pandas.DataFrame
        One row per effect (``between``, ``within``, ``interaction``) with columns
        :data:`ANOVA_COLUMNS`. ``eps``, ``p_GG_corr``, ``W_spher`` and ``p_spher`` are NaN on the
        between row, where sphericity does not apply.
    sphericity : Sphericity
    ss_type : {2, 3}
        Sums of squares used for the within effect.
    design : MixedDesign
        The complete cases analysed, and the excluded participants with reasons.
    """

    table: pd.DataFrame
    sphericity: Sphericity
    ss_type: int
    design: MixedDesign

    @property
    def n_subjects_used(self) -> int:
        """Participants with complete data that entered the ANOVA."""
        return self.design.n_subjects

    @property
    def excluded(self) -> pd.DataFrame:
        """Participants left out (``subject``, ``between``, ``reason``)."""
        return self.design.excluded

    def effect(self, name: str) -> pd.Series:
        """The table row of ``"between"``, ``"within"`` or ``"interaction"``."""
        if name not in EFFECTS:
            raise InvalidInputError(f"effect must be one of {EFFECTS}, got {name!r}")
        return self.table.iloc[EFFECTS.index(name)]

    def to_dict(self) -> dict[str, Any]:
        """The JSON contract of ``trustlab anova --json`` (plain Python types, no NaN).

        ``{"ss_type", "n_subjects_used", "excluded_subjects": [{"subject", "reason"}],
        "effects": {"between"|"within"|"interaction": {"F", "df1", "df2", "p", "np2", "ng2",
        "p_gg" (within and interaction only)}}, "sphericity": {"W", "p", "eps_gg"}}``.
        """
        effects: dict[str, dict[str, Any]] = {}
        for name in EFFECTS:
            row = self.effect(name)
            entry: dict[str, Any] = {
                "F": float(row["F"]),
                "df1": _df_value(row["DF1"]),
                "df2": _df_value(row["DF2"]),
                "p": float(row["p_unc"]),
                "np2": float(row["np2"]),
                "ng2": float(row["ng2"]),
            }
            if name != "between":
                entry["p_gg"] = float(row["p_GG_corr"])
            effects[name] = entry
        return {
            "ss_type": int(self.ss_type),
            "n_subjects_used": self.n_subjects_used,
            "excluded_subjects": [
                {"subject": to_python(r.subject), "reason": str(r.reason)}
                for r in self.excluded.itertuples(index=False)
            ],
            "effects": effects,
            "sphericity": {
                "W": float(self.sphericity.W),
                "p": None if self.sphericity.p is None else float(self.sphericity.p),
                "eps_gg": float(self.sphericity.eps_gg),
            },
        }


def _df_value(value: float) -> int | float:
    as_float = float(value)
    return int(as_float) if as_float.is_integer() else as_float


def mixed_anova(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    ss_type: SSType = 3,
    within_levels: Sequence[Any] | None = None,
) -> MixedAnovaResult:
    """Mixed ANOVA with sphericity statistics, type III (default) or type II sums of squares.

    Parameters
    ----------
    data : pandas.DataFrame
        Long format: one row per subject × within level.
    dv : str
        Dependent variable (numeric; NaN = missing).
    within : str
        Within-subject factor (e.g. ``session``).
    between : str
        Between-subject factor (e.g. ``condition``), two or more levels.
    subject : str
        Participant identifier.
    ss_type : {3, 2}
        Type III (default; SPSS, JASP, jamovi, afex) or type II (pingouin, car's default).
    within_levels : sequence, optional
        The within levels every participant must have; default all levels in ``data``.

    Returns
    -------
    MixedAnovaResult
        ``table`` has F, DF1, DF2, uncorrected p, partial η² (np2), generalised η² (ng2), the
        Greenhouse–Geisser epsilon and corrected p, and Mauchly's W and p.

    Raises
    ------
    InvalidInputError, DuplicateObservationError
        Malformed input (see :func:`analysis.design.prepare_mixed_design`).
    CannotComputeError
        No complete participant, a single group, a single within level, no error degrees of
        freedom (one participant per group), all values equal, or a zero error term.

    Notes
    -----
    Exclusions: participants without a value for every within level are excluded and listed
    in ``result.excluded`` with the reason (complete-case analysis).

    The within effect is tested on orthonormal contrast scores ``Z = Y C`` of the wide matrix
    ``Y``. Type II tests the grand mean of ``Z`` weighted by group size (``SS = N‖z̄‖²``);
    type III tests the unweighted mean of the group means (``SS = ‖z̃‖² / (Σ 1/n_g / G²)``),
    which is what sum-to-zero contrasts give. Both are identical for equal groups. The between
    effect and the interaction are the same under both types.

    Generalised η² is ``SS / (SS + SS_error_between + SS_error_within)`` with no measured
    factors (Olejnik & Algina, 2003; Bakeman, 2005), as in afex's ``ges``.

    Sphericity uses the pooled within-group covariance of the contrast scores (SPSS, car, afex,
    pingouin ≥ 0.7.0); Mauchly's p uses the approximation of R's ``mauchly.test``. With two
    within levels sphericity holds trivially: W = 1, p = 1, ε = 1. The Greenhouse–Geisser p
    multiplies both degrees of freedom by ε (same ε for within and interaction).

    References
    ----------
    Maxwell, S. E., & Delaney, H. D. (2004). Designing Experiments and Analyzing Data (2nd ed.),
    ch. 12 and 14. Greenhouse, S. W., & Geisser, S. (1959). Psychometrika, 24, 95–112.
    Mauchly, J. W. (1940). Ann. Math. Stat., 11, 204–209.
    """
    if ss_type not in (2, 3):
        raise InvalidInputError(f"ss_type must be 2 or 3, got {ss_type!r}")
    design = prepare_mixed_design(
        data, dv=dv, within=within, between=between, subject=subject, within_levels=within_levels
    )
    return mixed_anova_from_design(design, ss_type=ss_type)


def orthonormal_contrasts(n_levels: int) -> np.ndarray:
    """Orthonormal contrasts of ``n_levels`` levels, shape ``(n_levels, n_levels - 1)``.

    Columns are orthogonal to the constant and to each other with unit length (normalised
    Helmert contrasts); F tests, W and ε do not depend on which orthonormal basis is used.
    """
    c = np.zeros((n_levels, n_levels - 1))
    for j in range(1, n_levels):
        c[:j, j - 1] = 1.0
        c[j, j - 1] = -float(j)
        c[:, j - 1] /= np.sqrt(j * (j + 1))
    return c


def mixed_anova_from_design(design: MixedDesign, *, ss_type: SSType = 3) -> MixedAnovaResult:
    """Run the mixed ANOVA on an already prepared :class:`~analysis.design.MixedDesign`.

    Use this to analyse exactly the participants of a design shared with the descriptives
    and post-hoc tests. See :func:`mixed_anova` for the method and the errors.
    """
    if ss_type not in (2, 3):
        raise InvalidInputError(f"ss_type must be 2 or 3, got {ss_type!r}")
    _refuse_degenerate_design(design)
    y = design.values
    g = design.groups
    n, s = y.shape
    n_groups = len(design.group_levels)
    n_g = design.group_sizes.astype(float)
    what = f"the mixed ANOVA of {design.dv!r}"

    # Between-subject stratum: subject means.
    subj_mean = y.mean(axis=1)
    group_mean = np.bincount(g, weights=subj_mean, minlength=n_groups) / n_g
    ss_between = s * float(np.sum(n_g * (group_mean - subj_mean.mean()) ** 2))
    ss_err_between = s * float(np.sum((subj_mean - group_mean[g]) ** 2))

    # Within-subject stratum: orthonormal contrast scores.
    z = y @ orthonormal_contrasts(s)
    z_group = np.vstack([np.bincount(g, weights=z[:, j], minlength=n_groups) for j in range(s - 1)])
    z_group = (z_group / n_g).T  # (groups, contrasts)
    z_weighted = z.mean(axis=0)
    if ss_type == 2:
        ss_within = n * float(z_weighted @ z_weighted)
    else:
        z_unweighted = z_group.mean(axis=0)
        ss_within = float(z_unweighted @ z_unweighted) / (float(np.sum(1.0 / n_g)) / n_groups**2)
    ss_inter = float(np.sum(n_g[:, None] * (z_group - z_weighted) ** 2))
    resid = z - z_group[g]
    ss_err_within = float(np.sum(resid**2))

    scale = float(np.sum((y - y.mean()) ** 2))
    if ss_err_between <= _REL_TOL * scale:
        raise CannotComputeError(
            what,
            f"within each level of {design.between!r} every participant has the same mean "
            f"{design.dv!r}, so the between-subjects error term is zero and F is undefined",
        )
    if ss_err_within <= _REL_TOL * scale:
        raise CannotComputeError(
            what,
            f"within each level of {design.between!r} every participant changes identically "
            f"across {design.within!r}, so the within-subjects error term is zero and F is "
            "undefined",
        )

    df_between, df_err_between = n_groups - 1, n - n_groups
    df_within = s - 1
    df_inter = df_between * df_within
    df_err_within = df_within * df_err_between
    sphericity = _sphericity(resid, df_err_between, s)

    ss = np.array([ss_between, ss_within, ss_inter])
    df1 = np.array([df_between, df_within, df_inter], dtype=float)
    ss_err = np.array([ss_err_between, ss_err_within, ss_err_within])
    df2 = np.array([df_err_between, df_err_within, df_err_within], dtype=float)
    ms = ss / df1
    f_value = ms / (ss_err / df2)
    p_unc = stats.f.sf(f_value, df1, df2)
    eps = sphericity.eps_gg
    p_gg = stats.f.sf(f_value, df1 * eps, df2 * eps)
    nan = float("nan")
    table = pd.DataFrame(
        {
            "effect": list(EFFECTS),
            "Source": [
                design.between,
                design.within,
                f"{design.between} × {design.within}",
            ],
            "SS": ss,
            "DF1": df1,
            "DF2": df2,
            "MS": ms,
            "F": f_value,
            "p_unc": p_unc,
            "np2": ss / (ss + ss_err),
            "ng2": ss / (ss + ss_err_between + ss_err_within),
            "eps": [nan, eps, eps],
            "p_GG_corr": [nan, p_gg[1], p_gg[2]],
            "W_spher": [nan, sphericity.W, sphericity.W],
            "p_spher": [nan, *([nan if sphericity.p is None else sphericity.p] * 2)],
            "ss_type": ss_type,
        },
        columns=list(ANOVA_COLUMNS),
    )
    return MixedAnovaResult(table=table, sphericity=sphericity, ss_type=ss_type, design=design)


def _refuse_degenerate_design(design: MixedDesign) -> None:
    what = f"the mixed ANOVA of {design.dv!r}"
    if design.n_subjects == 0:
        raise CannotComputeError(
            what,
            f"no participant has a {design.dv!r} value for every level of {design.within!r} "
            f"({len(design.excluded)} excluded as incomplete)",
        )
    if len(design.group_levels) < 2:
        raise CannotComputeError(
            what,
            f"only one level of {design.between!r} ({design.group_levels[0]!r}) has participants "
            "with complete data; at least two groups are needed",
        )
    if design.n_levels < 2:
        raise CannotComputeError(
            what,
            f"{design.within!r} has a single level ({design.within_levels[0]!r}); at least two "
            "within-subject levels are needed",
        )
    if design.n_subjects - len(design.group_levels) < 1:
        raise CannotComputeError(
            what,
            f"each level of {design.between!r} has a single participant with complete data, so "
            "there are no error degrees of freedom (participants − groups = 0)",
        )
    if np.ptp(design.values) == 0:
        raise CannotComputeError(
            what,
            f"all {design.values.size} values of {design.dv!r} are equal "
            f"({design.values.flat[0]:g}), so there is no variance to analyse",
        )


def _sphericity(resid: np.ndarray, df_resid: int, n_levels: int) -> Sphericity:
    """Mauchly's test and GG epsilon from within-group residual contrast scores."""
    d = resid.shape[1]
    if d == 1:
        return Sphericity(
            W=1.0, p=1.0, eps_gg=1.0, chi2=0.0, dof=0.0, note="two levels: sphericity holds"
        )
    cov = resid.T @ resid / df_resid
    trace = float(np.trace(cov))
    eps = min(trace**2 / (d * float(np.trace(cov @ cov))), 1.0)
    dof = d * (d + 1) / 2 - 1
    sign, logdet = np.linalg.slogdet(cov)
    if df_resid < d or sign <= 0:
        return Sphericity(
            W=0.0,
            p=None,
            eps_gg=eps,
            chi2=float("inf"),
            dof=dof,
            note=(
                f"Mauchly's test is undefined: the {d}×{d} covariance of the within contrasts "
                f"is singular ({df_resid} error df)"
            ),
        )
    log_w = logdet - d * np.log(trace / d)
    # Bartlett-type correction and second-order term exactly as R's mauchly.test (which uses
    # the number of levels k, not d, in w2).
    rho = 1 - (2 * d**2 + d + 2) / (6 * d * df_resid)
    w2 = (
        (d + 2)
        * (d - 1)
        * (d - 2)
        * (2 * d**3 + 6 * d**2 + 3 * n_levels + 2)
        / (288 * (df_resid * d * rho) ** 2)
    )
    chi2 = -df_resid * rho * log_w
    p1 = stats.chi2.sf(chi2, dof)
    p2 = stats.chi2.sf(chi2, dof + 4)
    p = float(min(max(p1 + w2 * (p2 - p1), 0.0), 1.0))
    return Sphericity(W=float(np.exp(log_w)), p=p, eps_gg=float(eps), chi2=float(chi2), dof=dof)
