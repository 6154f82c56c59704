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

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from analysis._checks import describe_keys, ordered_levels, require_columns, to_python
from analysis.errors import DuplicateObservationError, InvalidInputError

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


def probability_matrix(lists: pd.Series | np.ndarray, what: str) -> np.ndarray:
    """Stack a column of probability lists into a float matrix, refusing ragged or bad rows."""
    values = np.asarray(lists, dtype=object)
    try:
        lengths = np.fromiter(map(len, values), dtype=np.int64, count=len(values))
    except TypeError:
        raise InvalidInputError(f"steps column {what!r} must hold lists of probabilities") from None
    if len(values) == 0:
        return np.empty((0, 0))
    if (lengths != lengths[0]).any() or lengths[0] == 0:
        raise InvalidInputError(
            f"steps column {what!r} must hold lists of numbers of the same length within a category"
        )
    try:
        flat = np.fromiter(
            itertools.chain.from_iterable(values), dtype=float, count=int(lengths.sum())
        )
    except (TypeError, ValueError):
        raise InvalidInputError(f"steps column {what!r} must hold lists of numbers") from None
    matrix = flat.reshape(len(values), int(lengths[0]))
    if np.isnan(matrix).any() or (matrix < 0).any() or (matrix > 1).any():
        raise InvalidInputError(f"steps column {what!r} has probabilities outside [0, 1]")
    return matrix


@dataclass(frozen=True)
class _Steps:
    """Validated step log as integer codes, rows sorted by participant, category, iteration."""

    frame: pd.DataFrame  # sorted rows
    participant: np.ndarray  # codes into participants
    participants: np.ndarray
    category: np.ndarray  # codes into categories
    categories: list[Any]
    condition: np.ndarray  # codes into conditions
    conditions: list[Any]
    iteration: np.ndarray


def _factorize(values: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """Integer codes in sorted order of the values (first-seen order if they cannot be sorted)."""
    try:
        codes, uniques = pd.factorize(values, sort=True)
    except TypeError:
        codes, uniques = pd.factorize(values)
    return codes, np.asarray(uniques, dtype=object)


def _validated_steps(steps: pd.DataFrame, preferred_arms: Mapping[str, int]) -> _Steps:
    if not isinstance(steps, pd.DataFrame):
        raise InvalidInputError("steps must be a pandas DataFrame")
    require_columns(steps, STEP_COLUMNS, "steps")
    for column in ("participant", "condition", "category", "iteration"):
        if steps[column].isna().any():
            raise InvalidInputError(f"steps column {column!r} has missing values")
    p_codes, participants = _factorize(steps["participant"])
    c_codes, categories = _factorize(steps["category"])
    undeclared = sorted(set(categories) - set(preferred_arms), key=str)
    if undeclared:
        raise InvalidInputError(
            f"steps have category(ies) {describe_keys(undeclared)} without a preferred arm; "
            f"declared: {describe_keys(list(preferred_arms))}"
        )
    try:
        iteration = steps["iteration"].to_numpy(dtype=np.int64)
    except (TypeError, ValueError):
        raise InvalidInputError("steps column 'iteration' must hold integers") from None
    order = np.lexsort((iteration, c_codes, p_codes))
    p_sorted, c_sorted, it_sorted = p_codes[order], c_codes[order], iteration[order]
    same_unit = (p_sorted[1:] == p_sorted[:-1]) & (c_sorted[1:] == c_sorted[:-1])
    repeated = same_unit & (it_sorted[1:] == it_sorted[:-1])
    if repeated.any():
        rows = np.flatnonzero(repeated)
        pairs = [
            (participants[p_sorted[i]], categories[c_sorted[i]], int(it_sorted[i])) for i in rows
        ]
        raise DuplicateObservationError(
            "steps has more than one row per participant × category × iteration for "
            f"{len(pairs)} combination(s): {describe_keys(pairs)}; keep exactly one row each",
            pairs,
        )
    starts = np.flatnonzero(np.concatenate([[True], ~same_unit]))
    unit_start = np.repeat(starts, np.diff(np.concatenate([starts, [len(order)]])))
    position = np.arange(len(order)) - unit_start + 1
    gaps = it_sorted != position
    if gaps.any():
        bad = sorted(
            {(participants[p_sorted[i]], categories[c_sorted[i]]) for i in np.flatnonzero(gaps)},
            key=str,
        )
        raise InvalidInputError(
            "steps iterations must run 1, 2, … without gaps within participant × category; "
            f"not so for {describe_keys(bad)}"
        )
    cond_codes, conditions = _factorize(steps["condition"])
    combos = np.unique(p_codes.astype(np.int64) * (len(conditions) + 1) + cond_codes)
    per_participant = np.bincount(combos // (len(conditions) + 1), minlength=len(participants))
    if (per_participant > 1).any():
        names = sorted(participants[per_participant > 1], key=str)
        raise InvalidInputError(
            f"participant(s) {describe_keys(names)} appear in more than one condition in the "
            "step log"
        )
    return _Steps(
        frame=steps.iloc[order].reset_index(drop=True),
        participant=p_sorted,
        participants=participants,
        category=c_sorted,
        categories=list(categories),
        condition=cond_codes[order],
        conditions=list(conditions),
        iteration=it_sorted,
    )


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
    validated = _validated_steps(steps, preferred_arms)
    _preferred_arrays(validated, preferred_arms)  # checks the probability lists
    return validated.frame


def _preferred_arrays(
    validated: _Steps, preferred_arms: Mapping[str, int]
) -> dict[str, np.ndarray]:
    """Row arrays of the trajectories: participant, condition, category codes, iteration, p."""
    frame = validated.frame
    parts: list[dict[str, np.ndarray]] = []
    for code, category in enumerate(validated.categories):
        rows = np.flatnonzero(validated.category == code)
        arm = int(preferred_arms[category])
        after = probability_matrix(frame["probs_after"].to_numpy()[rows], "probs_after")
        before = probability_matrix(frame["probs_before"].to_numpy()[rows], "probs_before")
        if not 0 <= arm < after.shape[1] or before.shape[1] != after.shape[1]:
            raise InvalidInputError(
                f"category {category!r}: preferred arm {arm} is not one of the "
                f"{after.shape[1]} arms (or probs_before/probs_after lengths differ)"
            )
        first = validated.iteration[rows] == 1
        for sel, it, p in (
            (rows[first], np.zeros(int(first.sum()), dtype=np.int64), before[first, arm]),
            (rows, validated.iteration[rows], after[:, arm]),
        ):
            parts.append(
                {
                    "participant": validated.participant[sel],
                    "condition": validated.condition[sel],
                    "category": validated.category[sel],
                    "iteration": it,
                    "p_preferred": p,
                }
            )
    if not parts:
        return {k: np.empty(0, dtype=np.int64) for k in TRAJECTORY_COLUMNS}
    return {k: np.concatenate([part[k] for part in parts]) for k in TRAJECTORY_COLUMNS}


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
        Columns :data:`TRAJECTORY_COLUMNS`, sorted by participant, category and iteration;
        iteration 0 is ``probs_before`` of iteration 1, and iteration ``k`` ≥ 1 is
        ``probs_after`` of iteration ``k``.
    """
    validated = _validated_steps(steps, preferred_arms)
    arrays = _preferred_arrays(validated, preferred_arms)
    order = np.lexsort((arrays["iteration"], arrays["category"], arrays["participant"]))
    return pd.DataFrame(
        {
            "participant": validated.participants[arrays["participant"][order]],
            "condition": np.asarray(validated.conditions, dtype=object)[arrays["condition"][order]],
            "category": np.asarray(validated.categories, dtype=object)[arrays["category"][order]],
            "iteration": arrays["iteration"][order],
            "p_preferred": arrays["p_preferred"][order],
        }
    )


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
    validated = _validated_steps(steps, preferred_arms)
    arrays = _preferred_arrays(validated, preferred_arms)
    category_rank = np.array(
        [list(preferred_arms).index(c) for c in validated.categories], dtype=np.int64
    )
    condition_order = sorted(
        range(len(validated.conditions)), key=lambda i: str(validated.conditions[i])
    )
    condition_rank = np.empty(len(validated.conditions), dtype=np.int64)
    condition_rank[condition_order] = np.arange(len(condition_order))
    return _summarise(
        condition_rank[arrays["condition"]],
        category_rank[arrays["category"]],
        arrays["iteration"],
        arrays["p_preferred"],
        conditions=[validated.conditions[i] for i in condition_order],
        categories=list(preferred_arms),
        confidence=confidence,
    )


def _summarise(
    condition: np.ndarray,
    category: np.ndarray,
    iteration: np.ndarray,
    values: np.ndarray,
    *,
    conditions: list[Any],
    categories: list[Any],
    confidence: float,
) -> pd.DataFrame:
    """Group means, SDs and t intervals by (condition, category, iteration) ranks."""
    if len(values) == 0:
        return pd.DataFrame(columns=list(CURVE_COLUMNS))
    width = int(iteration.max()) + 1
    key = (condition * len(categories) + category) * width + iteration
    groups, inverse = np.unique(key, return_inverse=True)
    n = np.bincount(inverse)
    mean = np.bincount(inverse, weights=values) / n
    ss = np.bincount(inverse, weights=(values - mean[inverse]) ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = np.where(n > 1, np.sqrt(ss / (n - 1)), np.nan)
    se = sd / np.sqrt(n)
    from analysis.descriptives import t_interval  # SciPy: only where curves are summarised

    low, high = t_interval(mean, se, n - 1, confidence)
    cond_idx, rest = np.divmod(groups, len(categories) * width)
    cat_idx, it = np.divmod(rest, width)
    return pd.DataFrame(
        {
            "condition": [to_python(conditions[i]) for i in cond_idx],
            "category": [categories[i] for i in cat_idx],
            "iteration": it.astype(np.int64),
            "n": n.astype(np.int64),
            "mean": mean,
            "sd": sd,
            "se": se,
            "ci_low": low,
            "ci_high": high,
        }
    )


def curves_from_trajectories(
    trajectories: pd.DataFrame, category_order: Sequence[Any], *, confidence: float = 0.95
) -> pd.DataFrame:
    """Summarise a :func:`preferred_probability` frame into :data:`CURVE_COLUMNS`."""
    require_columns(trajectories, TRAJECTORY_COLUMNS, "trajectories")
    conditions = ordered_levels(trajectories["condition"])
    categories = list(category_order)
    unknown = sorted(set(trajectories["category"]) - set(categories), key=str)
    if unknown:
        raise InvalidInputError(
            f"trajectories have category(ies) {describe_keys(unknown)} missing from the order"
        )
    return _summarise(
        pd.Index(conditions).get_indexer(trajectories["condition"]),
        pd.Index(categories).get_indexer(trajectories["category"]),
        trajectories["iteration"].to_numpy(dtype=np.int64),
        trajectories["p_preferred"].to_numpy(dtype=float),
        conditions=conditions,
        categories=categories,
        confidence=confidence,
    )
