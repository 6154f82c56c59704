"""Validated, complete-case layout of a between × within (mixed) design.

Every statistic on the repeated trust ratings needs the same preparation: check the long frame,
refuse ambiguous data (a participant observed twice in one session, a participant in two
conditions), and drop participants without a value for every session, saying why. Doing it once
here keeps the ANOVA, the descriptives and the post-hoc tests on exactly the same participants.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from analysis._checks import (
    describe_keys,
    numeric_values,
    ordered_levels,
    require_columns,
    require_distinct,
    require_frame,
    require_no_missing,
    to_python,
)
from analysis.errors import CannotComputeError, DuplicateObservationError, InvalidInputError

__all__ = ["EXCLUSION_COLUMNS", "MixedDesign", "prepare_mixed_design", "refuse_empty_cells"]

EXCLUSION_COLUMNS = ("subject", "between", "reason")
"""Columns of every exclusions frame returned by this package."""


@dataclass(frozen=True)
class MixedDesign:
    """Complete cases of a mixed design in wide layout.

    Attributes
    ----------
    dv, within, between, subject : str
        Column names of the long frame this design was built from.
    values : numpy.ndarray
        Shape ``(n_subjects, n_within_levels)``; row ``i`` holds subject ``subjects[i]``.
    subjects : tuple
        Subject identifiers (plain Python values) in row order.
    groups : numpy.ndarray
        Integer code of each row's between level (index into ``group_levels``).
    group_levels, within_levels : tuple
        Factor levels, in order (categorical order, else sorted).
    excluded : pandas.DataFrame
        Participants left out, columns ``subject``, ``between``, ``reason``.
    """

    dv: str
    within: str
    between: str
    subject: str
    values: np.ndarray
    subjects: tuple[Any, ...]
    groups: np.ndarray
    group_levels: tuple[Any, ...]
    within_levels: tuple[Any, ...]
    excluded: pd.DataFrame

    @property
    def n_subjects(self) -> int:
        """Number of participants with complete data."""
        return int(self.values.shape[0])

    @property
    def n_levels(self) -> int:
        """Number of within-subject levels."""
        return int(self.values.shape[1])

    @property
    def group_sizes(self) -> np.ndarray:
        """Participants per between level (aligned with ``group_levels``)."""
        return np.bincount(self.groups, minlength=len(self.group_levels))

    def long(self) -> pd.DataFrame:
        """The complete cases as a long frame (subject, between, within, dv)."""
        n, s = self.values.shape
        return pd.DataFrame(
            {
                self.subject: np.repeat(np.asarray(self.subjects, dtype=object), s),
                self.between: np.repeat(
                    np.asarray(self.group_levels, dtype=object)[self.groups], s
                ),
                self.within: np.tile(np.asarray(self.within_levels, dtype=object), n),
                self.dv: self.values.ravel(),
            }
        )


def prepare_mixed_design(
    data: pd.DataFrame,
    *,
    dv: str,
    within: str,
    between: str,
    subject: str,
    within_levels: Sequence[Any] | None = None,
) -> MixedDesign:
    """Validate a long frame and keep the participants with every within level.

    Parameters
    ----------
    data : pandas.DataFrame
        Long format, one row per subject × within level.
    dv, within, between, subject : str
        Column names of the dependent variable and the factors.
    within_levels : sequence, optional
        The levels every participant should have (e.g. sessions 1–4). Default: every level that
        occurs in ``data``. Rows with a level outside this list are refused.

    Returns
    -------
    MixedDesign

    Raises
    ------
    InvalidInputError
        A column is missing or used twice, ``dv`` is not numeric, an identifier is missing, a
        subject appears in two between levels, or a row has an undeclared within level.
    DuplicateObservationError
        Two rows share a subject × within level (never averaged silently).

    Notes
    -----
    Exclusions: a participant is excluded, with the reason recorded, when any within level has
    no row or a missing (NaN) value of ``dv``. This is complete-case analysis, as in SPSS, JASP
    and afex; a mixed-effects model would be needed to use incomplete participants.
    """
    data = require_frame(data)
    require_columns(data, [dv, within, between, subject])
    require_distinct(dv=dv, within=within, between=between, subject=subject)
    values = numeric_values(data, dv)
    require_no_missing(data, [subject, between, within])

    levels = list(within_levels) if within_levels is not None else ordered_levels(data[within])
    if len(set(levels)) != len(levels):
        raise InvalidInputError(f"within_levels lists a level twice: {levels}")
    level_codes = pd.Index(levels).get_indexer(data[within])
    if (level_codes < 0).any():
        unknown = list(pd.unique(data[within][level_codes < 0]))
        raise InvalidInputError(
            f"column {within!r} has level(s) {describe_keys(unknown)} outside the declared "
            f"levels {describe_keys(levels)}"
        )
    subj_codes, subj_uniques = _factorize(data[subject])
    n_subj = len(subj_uniques)
    _refuse_duplicate_cells(subj_codes, level_codes, subj_uniques, levels, subject, within)
    group_codes_row, group_uniques = _factorize(data[between])
    _refuse_subjects_in_two_groups(subj_codes, group_codes_row, subj_uniques, between)

    wide = np.full((n_subj, len(levels)), np.nan)
    wide[subj_codes, level_codes] = values
    group_of_subject = np.empty(n_subj, dtype=object)
    group_of_subject[subj_codes] = group_uniques[group_codes_row]

    complete = ~np.isnan(wide).any(axis=1)
    excluded = _exclusions(
        wide[~complete],
        subj_uniques[~complete],
        group_of_subject[~complete],
        levels,
        dv=dv,
        within=within,
    )

    kept_groups = group_of_subject[complete]
    kept_set = set(kept_groups)
    group_levels = [g for g in ordered_levels(data[between]) if g in kept_set]
    group_codes = pd.Index(group_levels).get_indexer(kept_groups).astype(np.intp)
    order = np.argsort(group_codes, kind="stable")
    return MixedDesign(
        dv=dv,
        within=within,
        between=between,
        subject=subject,
        values=wide[complete][order],
        subjects=tuple(to_python(s) for s in subj_uniques[complete][order]),
        groups=group_codes[order],
        group_levels=tuple(to_python(g) for g in group_levels),
        within_levels=tuple(to_python(level) for level in levels),
        excluded=excluded,
    )


def _factorize(series: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    try:
        codes, uniques = pd.factorize(series, sort=True)
    except TypeError:  # mixed types cannot be sorted; keep first-seen order
        codes, uniques = pd.factorize(series, sort=False)
    return codes, np.asarray(uniques, dtype=object)


def _refuse_duplicate_cells(
    subj_codes: np.ndarray,
    level_codes: np.ndarray,
    subjects: np.ndarray,
    levels: Sequence[Any],
    subject: str,
    within: str,
) -> None:
    """Refuse two rows for one subject × level (pingouin would silently average them)."""
    key = subj_codes.astype(np.int64) * len(levels) + level_codes
    unique, counts = np.unique(key, return_counts=True)
    repeated = unique[counts > 1]
    if len(repeated):
        pairs = [
            (to_python(subjects[k // len(levels)]), to_python(levels[k % len(levels)]))
            for k in repeated
        ]
        raise DuplicateObservationError(
            f"data has more than one row per {subject} × {within} for {len(pairs)} "
            f"combination(s): {describe_keys(pairs)}; keep exactly one row each",
            pairs,
        )


def _refuse_subjects_in_two_groups(
    subj_codes: np.ndarray, group_codes: np.ndarray, subjects: np.ndarray, between: str
) -> None:
    n_groups = int(group_codes.max(initial=0)) + 1
    combos = np.unique(subj_codes.astype(np.int64) * n_groups + group_codes)
    per_subject = np.bincount(combos // n_groups, minlength=len(subjects))
    if (per_subject > 1).any():
        raise InvalidInputError(
            f"subject(s) {describe_keys(list(subjects[per_subject > 1]))} appear in more than "
            f"one level of {between!r}; a subject belongs to exactly one group"
        )


def _exclusions(
    wide: np.ndarray,
    subjects: np.ndarray,
    groups: np.ndarray,
    levels: Sequence[Any],
    *,
    dv: str,
    within: str,
) -> pd.DataFrame:
    rows = []
    for row, subj, group in zip(wide, subjects, groups, strict=True):
        missing = [to_python(level) for level, v in zip(levels, row, strict=True) if np.isnan(v)]
        rows.append(
            {
                "subject": to_python(subj),
                "between": to_python(group),
                "reason": (
                    f"incomplete: no {dv} value for {within} {', '.join(map(str, missing))} "
                    f"(needs all of {', '.join(str(to_python(v)) for v in levels)})"
                ),
            }
        )
    return pd.DataFrame(rows, columns=list(EXCLUSION_COLUMNS))


def refuse_empty_cells(
    between: pd.Series,
    within: pd.Series,
    group_levels: Sequence[Any],
    within_levels: Sequence[Any],
    what: str,
) -> None:
    """Refuse a between × within design with a cell nobody rated (a model with the interaction
    cannot estimate it: at an interim look, say, when no one in one condition has reached the
    last session yet), naming the cells.

    Raises
    ------
    CannotComputeError
        Saying which cells are empty and what to do.
    """
    pairs = pd.DataFrame({"b": between.to_numpy(), "w": within.to_numpy()}).drop_duplicates()
    seen = set(zip(pairs["b"].map(to_python), pairs["w"].map(to_python), strict=True))
    empty = [
        (to_python(b), to_python(w))
        for b in group_levels
        for w in within_levels
        if (to_python(b), to_python(w)) not in seen
    ]
    if empty:
        cells = ", ".join(f"{b} × {w}" for b, w in empty)
        raise CannotComputeError(
            what,
            f"no one has a rating in {len(empty)} cell(s) ({cells}); analyse the sessions every "
            "condition has reached (or wait for more data)",
        )
