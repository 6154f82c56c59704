"""Input checks shared by the statistics functions (internal)."""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import pandas as pd

from analysis.errors import DuplicateObservationError, InvalidInputError

MAX_LISTED = 10
"""How many offending keys an error message names before it says "and N more"."""


def describe_keys(keys: Sequence[Any], limit: int = MAX_LISTED) -> str:
    """Render offending keys for an error message, shortening long lists."""
    shown = ", ".join(_plain_repr(k) for k in keys[:limit])
    if len(keys) > limit:
        shown += f" and {len(keys) - limit} more"
    return shown


def _plain_repr(key: Any) -> str:
    if isinstance(key, tuple):
        return "(" + ", ".join(_plain_repr(k) for k in key) + ")"
    plain = to_python(key)
    if isinstance(plain, float) and plain.is_integer():
        return repr(int(plain))  # 8.0 reads as 8 in a message about a Likert answer
    return repr(plain)


def to_python(value: Any) -> Any:
    """Convert numpy/pandas scalars to plain Python objects (for messages and JSON)."""
    if value is None or value is pd.NA or value is pd.NaT:
        return None
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and np.isnan(value):
        return None
    return value


def json_value(value: Any) -> Any:
    """A plain Python value for JSON: NumPy scalars unwrapped, NaN and ±inf as None."""
    value = to_python(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def fit_status(problem: str, notes: Sequence[str]) -> str:
    """A fitted model's state in one line: its problem, else its notes, else "converged"."""
    if problem:
        return problem
    return "; ".join(notes) if notes else "converged"


def json_records(frame: pd.DataFrame) -> list[dict[str, Any]]:
    """The rows of ``frame`` as JSON-ready dicts (see :func:`json_value`)."""
    return [{k: json_value(v) for k, v in row.items()} for row in frame.to_dict("records")]


def require_frame(data: object, what: str = "data") -> pd.DataFrame:
    """Refuse anything that is not a non-empty DataFrame."""
    if not isinstance(data, pd.DataFrame):
        raise InvalidInputError(f"{what} must be a pandas DataFrame, got {type(data).__name__}")
    if data.empty:
        raise InvalidInputError(f"{what} is empty")
    return data


def require_columns(data: pd.DataFrame, columns: Iterable[str], what: str = "data") -> None:
    """Refuse a frame that lacks any of ``columns``, naming every missing one."""
    missing = [c for c in columns if c not in data.columns]
    if missing:
        available = ", ".join(map(str, data.columns))
        raise InvalidInputError(
            f"{what} has no column {', '.join(map(repr, missing))} (columns: {available})"
        )


def require_distinct(**roles: str) -> None:
    """Refuse the same column used in two roles (e.g. ``within == between``)."""
    seen: dict[str, str] = {}
    for role, column in roles.items():
        if column in seen:
            raise InvalidInputError(f"column {column!r} is given as both {seen[column]} and {role}")
        seen[column] = role


def numeric_values(data: pd.DataFrame, column: str, what: str = "data") -> np.ndarray:
    """Return ``column`` as float64 with NaN for missing, refusing text and infinities."""
    series = data[column]
    if pd.api.types.is_bool_dtype(series) or not pd.api.types.is_numeric_dtype(series):
        converted = pd.to_numeric(series, errors="coerce")
        bad = series[converted.isna() & series.notna()]
        if len(bad) or pd.api.types.is_bool_dtype(series):
            examples = describe_keys(list(bad.unique()) or [True])
            raise InvalidInputError(f"{what} column {column!r} must be numeric; found {examples}")
        series = converted
    values = series.to_numpy(dtype="float64", na_value=np.nan)
    if np.isinf(values).any():
        raise InvalidInputError(f"{what} column {column!r} contains infinite values")
    return values


def require_no_missing(data: pd.DataFrame, columns: Iterable[str], what: str = "data") -> None:
    """Refuse missing identifiers: a row without a subject or level cannot be placed."""
    for column in columns:
        n_missing = int(data[column].isna().sum())
        if n_missing:
            raise InvalidInputError(
                f"{what} column {column!r} has {n_missing} missing value(s); "
                "every row needs an identifier"
            )


def refuse_duplicates(data: pd.DataFrame, keys: Sequence[str], what: str = "data") -> None:
    """Refuse repeated key combinations instead of silently averaging them."""
    dup_mask = data.duplicated(subset=list(keys), keep=False)
    if dup_mask.any():
        dup = data.loc[dup_mask, list(keys)].drop_duplicates()
        pairs = [tuple(to_python(v) for v in row) for row in dup.itertuples(index=False)]
        names = " × ".join(keys)
        raise DuplicateObservationError(
            f"{what} has more than one row per {names} for {len(pairs)} combination(s): "
            f"{describe_keys(pairs)}; keep exactly one row each",
            pairs,
        )


def ordered_levels(series: pd.Series) -> list[Any]:
    """Levels of a factor in a stable, meaningful order.

    Categorical columns keep their declared category order (only observed categories);
    anything else is sorted, so sessions 1..S come out in time order; text labels are sorted
    naturally ("S2" before "S10"). Labels without numbers ("pre", "post") sort alphabetically:
    declare their order where it matters.
    """
    if isinstance(series.dtype, pd.CategoricalDtype):
        present = set(series.dropna().unique())
        return [c for c in series.cat.categories if c in present]
    levels = list(pd.unique(series.dropna()))
    if levels and all(isinstance(level, str) for level in levels):
        return sorted(levels, key=_natural_key)
    try:
        return sorted(levels)
    except TypeError:
        return sorted(levels, key=str)


def _natural_key(text: str) -> tuple[tuple[int, Any], ...]:
    """Sort key that orders the digits in a label by value: "S2" before "S10"."""
    return tuple(
        (0, int(part)) if part.isdigit() else (1, part) for part in re.split(r"(\d+)", text) if part
    )
