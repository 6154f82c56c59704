"""Adaptation curves from the step log: how fast each learner finds the preferred question.

The paper's objective measure is the probability a participant's learner gives to the question
the participant prefers, iteration by iteration. For every participant × category the curve has
``N + 1`` points: the probability before the first answer, then after each of the ``N`` answers.
The study curve is the mean over participants of a condition, with a t-based confidence band.

Step-log frame (one row per answered adaptation step; familiarisation excluded):

=============  ==================================================================
participant    participant code (str)
condition      condition code (str), constant per participant
category       category key, e.g. ``"conation"``
session        session number (int)
run            run number within the session (int)
iteration      1..N within participant × category, without gaps
action         index of the question asked (int, 0-based arm index)
probs_before   list[float], the learner's probabilities before the answer
probs_after    list[float], after the update
answer         bool (yes = True)
reward         float
=============  ==================================================================
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from analysis._checks import describe_keys, refuse_duplicates, require_columns, to_python
from analysis.descriptives import t_interval
from analysis.errors import InvalidInputError

__all__ = [
    "CURVE_COLUMNS",
    "STEP_COLUMNS",
    "TRAJECTORY_COLUMNS",
    "adaptation_curves",
    "curves_from_trajectories",
    "preferred_probability",
    "probability_matrix",
    "validate_steps",
]

STEP_COLUMNS = (
    "participant",
    "condition",
    "category",
    "session",
    "run",
    "iteration",
    "action",
    "probs_before",
    "probs_after",
    "answer",
    "reward",
)
"""Columns the step-log frame must have."""

TRAJECTORY_COLUMNS = ("participant", "condition", "category", "iteration", "p_preferred")
"""Columns of :func:`preferred_probability`."""

CURVE_COLUMNS = (
    "condition",
    "category",
    "iteration",
    "n",
    "mean",
    "sd",
    "se",
    "ci_low",
    "ci_high",
)
"""Columns of :func:`adaptation_curves`."""


def probability_matrix(lists: pd.Series, what: str) -> np.ndarray:
    """Stack a column of probability lists into a float matrix, refusing ragged or bad rows."""
    try:
        matrix = np.array(lists.tolist(), dtype=float)
    except (TypeError, ValueError):
        raise InvalidInputError(
            f"steps column {what!r} must hold lists of numbers of the same length within a category"
        ) from None
    if matrix.ndim != 2:
        raise InvalidInputError(f"steps column {what!r} must hold lists of probabilities")
    if np.isnan(matrix).any() or (matrix < 0).any() or (matrix > 1).any():
        raise InvalidInputError(f"steps column {what!r} has probabilities outside [0, 1]")
    return matrix


def validate_steps(steps: pd.DataFrame, preferred_arms: Mapping[str, int]) -> pd.DataFrame:
    """Check a step-log frame; return it sorted by participant, category and iteration.

    Raises
    ------
    InvalidInputError
        Missing columns, a category without a declared preferred arm, a participant in two
        conditions, iterations that do not run 1..N, or malformed probability lists.
    DuplicateObservationError
        Two rows for the same participant × category × iteration.
    """
    if not isinstance(steps, pd.DataFrame):
        raise InvalidInputError("steps must be a pandas DataFrame")
    require_columns(steps, STEP_COLUMNS, "steps")
    for column in ("participant", "condition", "category", "iteration"):
        if steps[column].isna().any():
            raise InvalidInputError(f"steps column {column!r} has missing values")
    undeclared = sorted(set(steps["category"].unique()) - set(preferred_arms))
    if undeclared:
        raise InvalidInputError(
            f"steps have category(ies) {describe_keys(undeclared)} without a preferred arm; "
            f"declared: {describe_keys(list(preferred_arms))}"
        )
    refuse_duplicates(steps, ["participant", "category", "iteration"], "steps")
    n_conditions = steps.groupby("participant", sort=False)["condition"].nunique()
    if (n_conditions > 1).any():
        raise InvalidInputError(
            "participant(s) "
            f"{describe_keys(list(n_conditions[n_conditions > 1].index))} appear in more than "
            "one condition in the step log"
        )
    try:
        iteration = steps["iteration"].astype("int64")
    except (TypeError, ValueError):
        raise InvalidInputError("steps column 'iteration' must hold integers") from None
    ordered = steps.assign(iteration=iteration).sort_values(
        ["participant", "category", "iteration"], kind="stable"
    )
    position = ordered.groupby(["participant", "category"], sort=False).cumcount() + 1
    gaps = ordered[ordered["iteration"].to_numpy() != position.to_numpy()]
    if len(gaps):
        keys = list(gaps[["participant", "category"]].drop_duplicates().itertuples(index=False))
        raise InvalidInputError(
            "steps iterations must run 1, 2, … without gaps within participant × category; "
            f"not so for {describe_keys([tuple(k) for k in keys])}"
        )
    return ordered.reset_index(drop=True)


def preferred_probability(steps: pd.DataFrame, preferred_arms: Mapping[str, int]) -> pd.DataFrame:
    """Each participant's probability of the preferred question, before and after every answer.

    Parameters
    ----------
    steps : pandas.DataFrame
        Step log with :data:`STEP_COLUMNS`.
    preferred_arms : mapping of str to int
        Preferred arm index (0-based) of each category, as declared by the protocol.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`TRAJECTORY_COLUMNS`; iteration 0 is ``probs_before`` of iteration 1, and
        iteration ``k`` ≥ 1 is ``probs_after`` of iteration ``k``.
    """
    ordered = validate_steps(steps, preferred_arms)
    parts = []
    for category, rows in ordered.groupby("category", sort=False):
        arm = int(preferred_arms[str(category)])
        after = probability_matrix(rows["probs_after"], "probs_after")
        before = probability_matrix(rows["probs_before"], "probs_before")
        if not 0 <= arm < after.shape[1] or before.shape[1] != after.shape[1]:
            raise InvalidInputError(
                f"category {category!r}: preferred arm {arm} is not one of the "
                f"{after.shape[1]} arms (or probs_before/probs_after lengths differ)"
            )
        first = (rows["iteration"] == 1).to_numpy()
        base = rows[["participant", "condition", "category"]]
        parts.append(
            base[first].assign(iteration=0, p_preferred=before[first, arm]),
        )
        parts.append(base.assign(iteration=rows["iteration"].to_numpy(), p_preferred=after[:, arm]))
    if not parts:
        return pd.DataFrame(columns=list(TRAJECTORY_COLUMNS))
    out = pd.concat(parts, ignore_index=True)
    return out.sort_values(
        ["participant", "category", "iteration"], kind="stable", ignore_index=True
    )[list(TRAJECTORY_COLUMNS)]


def adaptation_curves(
    steps: pd.DataFrame,
    preferred_arms: Mapping[str, int],
    *,
    confidence: float = 0.95,
) -> pd.DataFrame:
    """Mean probability of the preferred question by iteration, per condition and category.

    Parameters
    ----------
    steps : pandas.DataFrame
        Step log with :data:`STEP_COLUMNS`.
    preferred_arms : mapping of str to int
        Preferred arm index of each category.
    confidence : float
        Coverage of the t confidence band.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`CURVE_COLUMNS`, ordered by condition, category (in ``preferred_arms``
        order) and iteration 0..N.

    Notes
    -----
    Exclusions: none. Participants who have not finished (a live study) contribute to the
    iterations they reached, so ``n`` can fall with the iteration. The band is
    ``M ± t(n − 1) · SD/√n`` (NaN with a single participant); it is not clipped to [0, 1].
    """
    trajectories = preferred_probability(steps, preferred_arms)
    return curves_from_trajectories(trajectories, list(preferred_arms), confidence=confidence)


def curves_from_trajectories(
    trajectories: pd.DataFrame, category_order: list[Any], *, confidence: float = 0.95
) -> pd.DataFrame:
    """Summarise :func:`preferred_probability` output into :data:`CURVE_COLUMNS`."""
    if trajectories.empty:
        return pd.DataFrame(columns=list(CURVE_COLUMNS))
    grouped = trajectories.groupby(["condition", "category", "iteration"], sort=False)
    out = grouped["p_preferred"].agg(n="count", mean="mean", sd="std").reset_index()
    rank = {c: i for i, c in enumerate(category_order)}
    out["_cat"] = out["category"].map(rank)
    out = out.sort_values(["condition", "_cat", "iteration"], kind="stable", ignore_index=True)
    out["n"] = out["n"].astype(int)
    out["se"] = out["sd"] / np.sqrt(out["n"])
    out["ci_low"], out["ci_high"] = t_interval(
        out["mean"].to_numpy(), out["se"].to_numpy(), out["n"].to_numpy() - 1, confidence
    )
    out["condition"] = out["condition"].map(to_python)
    return out[list(CURVE_COLUMNS)]
