"""The inputs of a power analysis estimated from a pilot (or an earlier study), with uncertainty.

A power analysis is only as good as its ρ, ε and effect sizes. Guessed, they make any N look
right; estimated from the lab's own participants, they say what this lab's ratings do. This
module estimates them from the complete cases of a long frame (the same participants the
mixed ANOVA uses) and gives each a bootstrap interval over participants, resampled within each
condition with a seed, so a plan can be made with the pessimistic end of what the pilot allows.

Estimates, from the pooled within-condition covariance S of the m sessions (df N − k):

- σ² = the mean of S's diagonal (the variance of one rating), the participant variance = the
  mean of its off-diagonal (the random intercept's variance under compound symmetry), the
  residual variance = σ² minus that, and ρ = their ratio: the correlation among the repeated
  measures that G*Power's "Corr among rep measures" asks for. For balanced complete data
  these are the ANOVA (and, when positive, REML) estimates of the random-intercept model.
- ε = Greenhouse–Geisser's, from S (as :mod:`analysis.anova`).
- f of each effect = the SD of its cell-mean pattern over σ
  (:func:`analysis.power.effect_sizes_from_means`, G*Power's convention).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from analysis._checks import to_python
from analysis.anova import orthonormal_contrasts
from analysis.design import MixedDesign, prepare_mixed_design
from analysis.errors import InvalidInputError
from analysis.power import effect_sizes_from_means

__all__ = ["MIN_PER_GROUP", "PILOT_QUANTITIES", "PilotEstimate", "estimate_pilot"]

MIN_PER_GROUP = 4
"""Fewer complete participants per condition estimate a covariance matrix too poorly to plan on."""

PILOT_QUANTITIES = (
    "rho",
    "epsilon",
    "sd",
    "var_participant",
    "var_residual",
    "f_between",
    "f_within",
    "f_interaction",
)
"""The estimated quantities, in the order they are reported."""


@dataclass(frozen=True)
class PilotEstimate:
    """ρ, ε, variance components and effect sizes of a pilot, with bootstrap intervals.

    Attributes
    ----------
    dv : str
    group_levels, within_levels : tuple
    group_sizes : tuple of int
        Complete participants per condition (those estimated from).
    excluded : int
        Participants left out for a missing session.
    estimates : dict
        :data:`PILOT_QUANTITIES` → the point estimate.
    intervals : dict
        The same keys → (low, high), percentile bootstrap at ``confidence``.
    means : numpy.ndarray
        Cell means, shape (k, m).
    replicates, seed : int
    confidence : float
    """

    dv: str
    group_levels: tuple[Any, ...]
    within_levels: tuple[Any, ...]
    group_sizes: tuple[int, ...]
    excluded: int
    estimates: dict[str, float]
    intervals: dict[str, tuple[float, float]]
    means: np.ndarray = field(repr=False)
    replicates: int = 0
    seed: int = 0
    confidence: float = 0.95

    @property
    def groups(self) -> int:
        return len(self.group_levels)

    @property
    def sessions(self) -> int:
        return len(self.within_levels)

    def f(self, effect: str) -> float:
        """The estimated f of ``between``, ``within`` or ``interaction``."""
        return self.estimates[f"f_{effect}"]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: every estimate with its interval."""
        return {
            "dv": self.dv,
            "groups": [to_python(g) for g in self.group_levels],
            "sessions": [to_python(s) for s in self.within_levels],
            "n_per_group": list(self.group_sizes),
            "excluded_incomplete": self.excluded,
            "estimates": {
                name: {
                    "estimate": self.estimates[name],
                    "ci_low": self.intervals[name][0],
                    "ci_high": self.intervals[name][1],
                }
                for name in PILOT_QUANTITIES
            },
            "cell_means": self.means.tolist(),
            "bootstrap": {
                "replicates": self.replicates,
                "seed": self.seed,
                "confidence": self.confidence,
                "resampled": "participants, within each condition",
            },
        }


def estimate_pilot(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    replicates: int = 500,
    seed: int = 0,
    confidence: float = 0.95,
) -> PilotEstimate:
    """Estimate a power analysis's inputs from a pilot's long data.

    Parameters
    ----------
    data : pandas.DataFrame
        Long format, one row per participant × session (as :func:`analysis.anova.mixed_anova`).
    dv, within, between, subject : str
        Column names.
    replicates : int
        Bootstrap resamples (0: no intervals).
    seed : int
        Seed of the resampling: the same seed gives the same intervals.
    confidence : float

    Raises
    ------
    InvalidInputError
        Malformed data (as the ANOVA), a single session, or fewer than :data:`MIN_PER_GROUP`
        complete participants in a condition.
    """
    if replicates < 0:
        raise InvalidInputError(f"replicates must be 0 or more, got {replicates}")
    if not 0 < confidence < 1:
        raise InvalidInputError(f"confidence must be between 0 and 1, got {confidence:g}")
    design = prepare_mixed_design(data, dv=dv, within=within, between=between, subject=subject)
    _refuse_small(design)
    values, groups = design.values, design.groups
    k = len(design.group_levels)
    point = _estimates(values, groups, k)
    rng = np.random.default_rng(seed)
    members = [np.flatnonzero(groups == g) for g in range(k)]
    draws = np.empty((replicates, len(PILOT_QUANTITIES)))
    for b in range(replicates):
        rows = np.concatenate([rng.choice(idx, size=len(idx), replace=True) for idx in members])
        estimates = _estimates(values[rows], groups[rows], k)
        draws[b] = [estimates[name] for name in PILOT_QUANTITIES]
    tail = (1 - confidence) / 2 * 100
    intervals: dict[str, tuple[float, float]] = {}
    for j, name in enumerate(PILOT_QUANTITIES):
        if replicates:
            low, high = np.nanpercentile(draws[:, j], [tail, 100 - tail])
            intervals[name] = (float(low), float(high))
        else:
            intervals[name] = (float("nan"), float("nan"))
    means = np.vstack([values[groups == g].mean(axis=0) for g in range(k)])
    return PilotEstimate(
        dv=dv,
        group_levels=design.group_levels,
        within_levels=design.within_levels,
        group_sizes=tuple(int(n) for n in design.group_sizes),
        excluded=len(design.excluded),
        estimates=point,
        intervals=intervals,
        means=means,
        replicates=replicates,
        seed=seed,
        confidence=confidence,
    )


def _refuse_small(design: MixedDesign) -> None:
    if len(design.within_levels) < 2:
        raise InvalidInputError(
            f"a pilot needs two or more sessions to estimate their correlation; "
            f"{design.within!r} has one ({to_python(design.within_levels[0])!r})"
        )
    if len(design.group_levels) < 2:
        raise InvalidInputError(
            f"a pilot needs two or more levels of {design.between!r} with complete data"
        )
    sizes = design.group_sizes
    small = [
        f"{to_python(level)}: {int(n)}"
        for level, n in zip(design.group_levels, sizes, strict=True)
        if n < MIN_PER_GROUP
    ]
    if small:
        raise InvalidInputError(
            f"a pilot needs {MIN_PER_GROUP} or more participants with every session in each "
            f"group; {', '.join(small)}"
        )


def _estimates(values: np.ndarray, groups: np.ndarray, k: int) -> dict[str, float]:
    n, m = values.shape
    means = np.vstack([values[groups == g].mean(axis=0) for g in range(k)])
    residual = values - means[groups]
    cov = residual.T @ residual / (n - k)
    variance = float(np.mean(np.diag(cov)))
    participant = float((cov.sum() - np.trace(cov)) / (m * (m - 1)))
    contrasts = orthonormal_contrasts(m)
    a = contrasts.T @ cov @ contrasts
    trace_sq = float(np.trace(a @ a))
    epsilon = float(np.trace(a) ** 2 / ((m - 1) * trace_sq)) if trace_sq > 0 else float("nan")
    if variance <= 0:
        nan = float("nan")
        return dict.fromkeys(PILOT_QUANTITIES, nan)
    sizes = effect_sizes_from_means(means, np.sqrt(variance))
    return {
        "rho": participant / variance,
        "epsilon": min(epsilon, 1.0),
        "sd": float(np.sqrt(variance)),
        "var_participant": participant,
        "var_residual": variance - participant,
        "f_between": sizes["between"],
        "f_within": sizes["within"],
        "f_interaction": sizes["interaction"],
    }
